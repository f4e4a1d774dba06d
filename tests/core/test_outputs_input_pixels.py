"""A run processed at a smaller size than its input writes what a user looks at in the input's own pixels: the
panoptic PNGs and their preview, keyframes.json's image camera, and the exports (cameras and images agree)."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import fakes
from pvslam_core.cli import main
from pvslam_core.outputs.export import export_run
from pvslam_core.outputs.keyframes_io import read_keyframes, write_keyframes
from pvslam_core.outputs.panoptic_png import decode_ids
from pvslam_core.outputs.trajectory_io import write_tum
from pvslam_core.types import Intrinsics


@pytest.fixture
def shrunk_run(fake_registry, fake_config_file, tmp_path, monkeypatch, capsys):
    """The fake pipeline on frames that are the input (128x96) shrunk by 2."""
    from pvslam_core import registry as r

    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    code = main(["run", "-c", str(fake_config_file), "-q", "--panoptic-vis", "--set", "dataset.input_scale=2"])
    err = capsys.readouterr().err
    assert code == 0, err
    (run_dir,) = list((tmp_path / "runs").iterdir())
    return run_dir, err


def test_the_console_says_the_processing_size_once(shrunk_run):
    _, err = shrunk_run
    assert err.count("pvslam: processing 128x96 frames at 64x48") == 1


def test_panoptic_pngs_and_preview_are_at_the_input_size(shrunk_run):
    run_dir, _ = shrunk_run
    names = sorted(p.name for p in (run_dir / "panoptic").glob("*.png"))
    assert names
    rgb = cv2.imread(str(run_dir / "panoptic" / names[0]))[..., ::-1]
    ids = decode_ids(np.ascontiguousarray(rgb))
    assert ids.shape == (96, 128)
    # the fake segmenter's left half (frame columns < 32) and right half, nearest: input columns < 64 and >= 64
    left, right = np.unique(ids[:, :64]), np.unique(ids[:, 64:])
    assert len(left) == 1 and len(right) == 1 and left[0] != right[0] and 0 not in (left[0], right[0])
    vis = cv2.imread(str(run_dir / "panoptic_vis" / names[0]))
    assert vis.shape == (96, 128, 3)
    images = json.loads((run_dir / "panoptic" / "segments.json").read_text())["images"]
    assert {(im["width"], im["height"]) for im in images} == {(128, 96)}


def test_keyframes_json_and_the_exports_use_the_input_camera(shrunk_run):
    run_dir, _ = shrunk_run
    kf = read_keyframes(run_dir)
    image = kf["intrinsics"]["image"]
    assert (image["width"], image["height"], image["fx"]) == (128, 96, 2 * fakes.F)
    assert image["cx"] == pytest.approx((128 - 1) / 2) and image["cy"] == pytest.approx((96 - 1) / 2)
    summary = export_run(run_dir, "colmap")
    cams = (run_dir / "export" / "colmap" / "cameras.txt").read_text().split("\n")
    cam = [line for line in cams if line and not line.startswith("#")][0].split()
    assert cam[2:4] == ["128", "96"] and float(cam[4]) == 2 * fakes.F
    # the fake dataset yields 64x48 frames only: no image of another size than the cameras is written
    assert "64x48, not the 128x96 of keyframes.json" in summary["images_missing"]
    assert not list((run_dir / "export" / "colmap" / "images").glob("*.png"))
    ns = export_run(run_dir, "nerfstudio")
    tf = json.loads((run_dir / "export" / "nerfstudio" / "transforms.json").read_text())
    assert (tf["w"], tf["h"]) == (128, 96) and ns["depth"].startswith("128x96")
    depth = sorted((run_dir / "export" / "nerfstudio").rglob("*depth*/*.png"))
    assert depth and cv2.imread(str(depth[0]), cv2.IMREAD_UNCHANGED).shape == (96, 128)


# ---------------------------------------------------------------------- exports re-read the input's frames --
W, H = 128, 96
K_IN = Intrinsics(100.0, 100.0, 63.5, 47.5, W, H)


def _image(i: int) -> np.ndarray:
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)


def _run_dir(tmp_path, image_camera: Intrinsics):
    """A run directory of the images reader (max_pixels 4096: 72x48 processed) with 2 keyframes."""
    from pvslam_core.config import load_config

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        cv2.imwrite(str(frames / f"{i}.png"), _image(i))
    resolved = load_config(None, {"dataset": {"plugin": "images", "path": str(frames), "max_pixels": 4096,
                                              "calib": [K_IN.fx, K_IN.fy, K_IN.cx, K_IN.cy]}})
    d = tmp_path / "run"
    d.mkdir()
    (d / "config.json").write_text(resolved.to_json())
    poses = np.array([[0, 0, 0, 0, 0, 0, 1.0], [0.1, 0, 0, 0, 0, 0, 1.0]])
    fi = np.array([0, 2])
    write_keyframes(d, fi, 0.1 * fi, poses, np.full((2, 6, 9), 0.25, np.float32), [9.0, 9.0, 4.0, 2.5],
                    image_camera)
    write_tum(d / "trajectory.txt", 0.1 * np.arange(3), np.tile([0, 0, 0, 0, 0, 0, 1.0], (3, 1)))
    return d


def test_exported_images_are_the_input_frames_at_the_input_size(tmp_path):
    d = _run_dir(tmp_path, K_IN)
    summary = export_run(d, "nerfstudio")
    assert "images_missing" not in summary
    for i in (0, 2):
        img = cv2.imread(str(d / "export" / "nerfstudio" / "images" / f"{i:06d}.png"))
        assert img.shape == (H, W, 3) and np.array_equal(img, _image(i))  # the input's own pixels
    tf = json.loads((d / "export" / "nerfstudio" / "transforms.json").read_text())
    assert (tf["w"], tf["h"], tf["fl_x"]) == (W, H, K_IN.fx)


def test_a_run_that_recorded_the_processed_camera_exports_processed_frames(tmp_path):
    """keyframes.json of a run that recorded the processed frames' camera: the images match it, not the input."""
    processed = Intrinsics(57.03, 57.29, 35.0, 23.5, 72, 48)
    d = _run_dir(tmp_path, processed)
    assert "images_missing" not in export_run(d, "colmap")
    img = cv2.imread(str(d / "export" / "colmap" / "images" / "000002.png"))
    assert img.shape == (48, 72, 3)
