"""A run's standard results: COCO panoptic segments.json, clean point clouds, keyframe depth with
intrinsics, and `pvslam export` from the run directory."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pvslam_core.api import run_config
from pvslam_core.cli import main
from pvslam_core.evaluation.coco_panoptic import coco_panoptic_problems
from pvslam_core.outputs.keyframes_io import read_keyframes
from pvslam_core.outputs.ply import read_ply
from pvslam_core.outputs.trajectory_io import read_tum


@pytest.fixture
def fake_run(fake_registry, fake_config_file):
    res = run_config(fake_config_file, registry=fake_registry, overrides=["dataset.frames=16"])
    return Path(res.run_dir)


def test_panoptic_output_obeys_coco_rules(fake_run):
    assert coco_panoptic_problems(fake_run / "panoptic", stuff_once=True) == []
    meta = json.loads((fake_run / "panoptic" / "segments.json").read_text())
    assert [im["id"] for im in meta["images"]] == list(range(16))
    assert meta["images"][3]["file_name"] == "fake3" and meta["images"][3]["width"] == 64


def test_keyframe_depth_and_intrinsics(fake_run):
    kf = read_keyframes(fake_run)
    kts, kposes = read_tum(fake_run / "keyframes.txt")
    np.testing.assert_allclose(kf["timestamps"], kts)
    np.testing.assert_allclose(kf["poses"], kposes, atol=1e-12)
    assert kf["depth"].shape == (len(kts), 12, 16)  # 48x64 at graph.ba_downsample = 4; c' = (c + 0.5) / 4 - 0.5
    assert kf["intrinsics"]["depth"] == {"fx": 10.0, "fy": 10.0, "cx": 7.5, "cy": 5.5, "width": 16,
                                         "height": 12}
    assert kf["intrinsics"]["image"]["cx"] == 31.5 and kf["names"][0] == "fake0"
    assert (kf["depth"] > 0).mean() > 0.9


def test_clean_cloud_points_come_from_keyframes_within_the_relative_depth(fake_run):
    pts, cols, extra = read_ply(fake_run / "cloud_rgb.ply")
    kf = read_keyframes(fake_run)
    assert len(pts) > 100 and set(np.unique(extra["frame_index"])) <= set(kf["frame_index"].tolist())
    from scipy.spatial.transform import Rotation

    for n, f in enumerate(kf["frame_index"]):  # no point beyond 3x its keyframe's median depth
        sel = extra["frame_index"] == f
        if not sel.any():
            continue
        z = Rotation.from_quat(kf["poses"][n][3:]).inv().apply(pts[sel] - kf["poses"][n][:3])[:, 2]
        med = np.median(kf["depth"][n][kf["depth"][n] > 0])
        assert (z > 0).all() and (z <= 3.0 * med * (1 + 1e-5)).all()


def test_export_cli_writes_colmap_with_images(fake_run, fake_registry, monkeypatch, capsys):
    from PIL import Image

    from pvslam_core import registry as r

    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    assert main(["export", str(fake_run), "--format", "colmap"]) == 0
    out = fake_run / "export" / "colmap"
    cam = [ln for ln in (out / "cameras.txt").read_text().splitlines() if not ln.startswith("#")][0].split()
    kf = read_keyframes(fake_run)
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == [f"{i:06d}.png" for i in kf["frame_index"]]
    with Image.open(out / "images" / names[0]) as im:
        assert im.size == (int(cam[2]), int(cam[3])) == (64, 48)
    assert "points" in capsys.readouterr().out
    assert main(["export", str(fake_run), "--format", "tum-aligned", "--out", str(fake_run / "al")]) == 0
    ts, _ = read_tum(fake_run / "al" / "trajectory_aligned.txt")
    assert len(ts) == 16


def test_export_cli_without_dataset_still_writes_the_model(fake_run, monkeypatch, capsys):
    from pvslam_core import registry as r
    from pvslam_core.registry import build_registry

    monkeypatch.setattr(r, "_REGISTRY", build_registry())  # no test plugins: the run's dataset is gone
    assert main(["export", str(fake_run), "--format", "nerfstudio"]) == 0
    out = fake_run / "export" / "nerfstudio"
    assert (out / "transforms.json").is_file() and not (out / "images").exists()
    assert "images_missing" in capsys.readouterr().out
