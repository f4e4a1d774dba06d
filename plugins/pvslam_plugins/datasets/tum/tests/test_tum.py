"""The ``tum`` reader on TUM RGB-D layouts written by the test."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pvslam_core.datasets.base import DatasetError
from pvslam_plugins.datasets.tum.config import TumConfig
from pvslam_plugins.datasets.tum.reader import PRESETS, TumReader

RGB_T = [1305031102.175304, 1305031102.211214, 1305031102.243211, 1305031102.275326]
DEPTH_T = [1305031102.160407, 1305031102.226738, 1305031102.300000, 1305031102.340000]
GT_T = [1305031102.1758, 1305031102.2159, 1305031102.2458, 1305031102.2759]


def fake_tum(root: Path, name: str = "rgbd_dataset_freiburg1_xyz", size=(640, 480)) -> Path:
    seq = root / name
    (seq / "rgb").mkdir(parents=True)
    (seq / "depth").mkdir()
    w, h = size
    rgb_lines = ["# color images", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    for i, t in enumerate(RGB_T):
        cv2.imwrite(str(seq / f"rgb/{t:.6f}.png"), np.full((h, w, 3), (10 * i, 50, 90), np.uint8))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    depth_lines = ["# depth maps", "# timestamp filename"]
    for i, t in enumerate(DEPTH_T):
        d = np.full((h, w), 5000 + 1000 * i, np.uint16)
        d[:10] = 0
        cv2.imwrite(str(seq / f"depth/{t:.6f}.png"), d)
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (seq / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (seq / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for i, t in enumerate(GT_T):
        gt.append(f"{t:.4f} {1.3 + 0.01 * i} 0.6 1.6 0.6574 0.6126 -0.2949 -0.3248")
    (seq / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    return seq


def test_association_depth_and_groundtruth(tmp_path):
    seq = fake_tum(tmp_path)
    r = TumReader(TumConfig(path=str(seq), undistort=False, crop_multiple=1))
    info = r.info()
    assert info.num_frames == 4 and info.has_gt_pose and info.has_gt_depth
    frames = list(r)
    assert [f.timestamp for f in frames] == pytest.approx(RGB_T)
    # nearest depth: rgb 0 <-> depth 0 (14.9 ms), rgb 1 <-> depth 1 (15.5 ms), rgb 2 <-> depth 1 (16.5 ms),
    # rgb 3: nearest is depth 2 at 24.7 ms > 20 ms -> none
    assert frames[0].gt_depth[20, 20].item() == pytest.approx(1.0)
    assert frames[0].gt_depth[0, 0].item() == 0.0
    assert frames[1].gt_depth[20, 20].item() == pytest.approx(1.2)
    assert frames[2].gt_depth[20, 20].item() == pytest.approx(1.2)
    assert frames[3].gt_depth is None
    assert frames[0].gt_pose[0].item() == pytest.approx(1.3)
    assert frames[2].gt_pose[0].item() == pytest.approx(1.32)
    assert frames[0].gt_pose.tolist()[3:] == [0.6574, 0.6126, -0.2949, -0.3248]
    assert frames[1].image[:, 0, 0].tolist() == [90, 50, 10]


def test_max_diff_is_configurable(tmp_path):
    seq = fake_tum(tmp_path)
    r = TumReader(TumConfig(path=str(seq), max_diff=0.016, undistort=False))
    depths = [f.gt_depth is not None for f in r]
    assert depths == [True, True, False, False]


def test_intrinsics_precedence_preset_then_calib_txt_then_config(tmp_path):
    seq = fake_tum(tmp_path)
    k = TumReader(TumConfig(max_pixels=None, path=str(seq), undistort=False, crop_multiple=1)).info().intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) + k.dist == PRESETS["freiburg1"] and (k.width, k.height) == (640, 480)
    und = TumReader(TumConfig(max_pixels=None, path=str(seq))).info().intrinsics
    assert und.dist == () and und.fx == 517.3
    (seq / "calib.txt").write_text("525.0 525.0 319.5 239.5\n")
    k = TumReader(TumConfig(max_pixels=None, path=str(seq))).info().intrinsics
    assert (k.fx, k.cx, k.dist) == (525.0, 319.5, ())
    k = TumReader(TumConfig(max_pixels=None, path=str(seq), calib=[500, 501, 320, 240])).info().intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (500, 501, 320, 240)


def test_freiburg3_preset_has_no_distortion(tmp_path):
    seq = fake_tum(tmp_path, "rgbd_dataset_freiburg3_walking_xyz")
    k = TumReader(TumConfig(max_pixels=None, path=str(seq), undistort=False)).info().intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (535.4, 539.2, 320.1, 247.6) and not k.has_distortion


def test_unknown_camera_needs_a_calibration(tmp_path):
    seq = fake_tum(tmp_path, "my_recording", size=(64, 48))
    with pytest.raises(DatasetError, match=r"my_recording: no intrinsics"):
        TumReader(TumConfig(path=str(seq)))
    assert TumReader(TumConfig(path=str(seq), calib=[50, 50, 31.5, 23.5])).info().intrinsics.width == 64


def test_preset_with_wrong_image_size(tmp_path):
    seq = fake_tum(tmp_path, "rgbd_dataset_freiburg2_desk", size=(64, 48))
    with pytest.raises(DatasetError, match="freiburg2 preset is for 640x480 images, found 64x48"):
        TumReader(TumConfig(path=str(seq)))


# ------------------------------------------------------------------------------------------------ errors ----
def test_missing_frame_names_file_and_list(tmp_path):
    seq = fake_tum(tmp_path)
    (seq / f"rgb/{RGB_T[2]:.6f}.png").unlink()
    with pytest.raises(DatasetError, match=rf"{RGB_T[2]:.6f}\.png: frame missing \(listed in .*rgb\.txt\)"):
        TumReader(TumConfig(path=str(seq)))


def test_missing_depth_names_file(tmp_path):
    seq = fake_tum(tmp_path)
    (seq / f"depth/{DEPTH_T[1]:.6f}.png").unlink()
    with pytest.raises(DatasetError, match=rf"{DEPTH_T[1]:.6f}\.png: depth image missing"):
        TumReader(TumConfig(path=str(seq)))


def test_duplicate_rgb_timestamps_name_the_list(tmp_path):
    seq = fake_tum(tmp_path)
    with open(seq / "rgb.txt", "a") as fh:
        fh.write(f"{RGB_T[-1]:.6f} rgb/{RGB_T[-1]:.6f}.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt: duplicate timestamps"):
        TumReader(TumConfig(path=str(seq)))


def test_unsorted_groundtruth_names_the_file(tmp_path):
    seq = fake_tum(tmp_path)
    lines = (seq / "groundtruth.txt").read_text().splitlines()
    lines[2], lines[3] = lines[3], lines[2]
    (seq / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"groundtruth\.txt.*unsorted"):
        TumReader(TumConfig(path=str(seq)))


def test_calibration_with_wrong_count_names_file_and_count(tmp_path):
    seq = fake_tum(tmp_path)
    (seq / "calib.txt").write_text("525.0 525.0 319.5 239.5 0.1\n")
    with pytest.raises(DatasetError, match=r"calib\.txt.*found 5"):
        TumReader(TumConfig(path=str(seq)))


def test_corrupt_depth_names_the_file(tmp_path):
    seq = fake_tum(tmp_path)
    (seq / f"depth/{DEPTH_T[0]:.6f}.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(DatasetError, match=rf"{DEPTH_T[0]:.6f}\.png: unreadable or corrupt"):
        TumReader(TumConfig(path=str(seq)))[0]


def test_registered_through_the_hook(monkeypatch):
    import pvslam_plugins.datasets.tum as plugin
    from pvslam_core.registry import build_registry

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    assert build_registry(extra_modules=(plugin,)).get("dataset", "tum").config_model is TumConfig


def test_undistorted_frames_match_the_pinhole_intrinsics(tmp_path):
    """Blobs drawn where the freiburg1 model (with k3) projects 3D points land where the undistorted,
    resized and cropped intrinsics project them."""
    seq = fake_tum(tmp_path)
    pts = np.array([[0.0, 0.0, 2.0], [-0.8, -0.5, 2.2], [0.7, 0.6, 2.0], [0.9, -0.55, 2.4], [-0.9, 0.5, 2.1]])
    fx, fy, cx, cy, *dist = PRESETS["freiburg1"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.array(dist))
    ys, xs = np.mgrid[0:480, 0:640].astype(np.float64)
    img = sum(np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * 3.0**2)) for u, v in uv.reshape(-1, 2))
    img = np.clip(img * 255, 0, 255).astype(np.uint8)
    cv2.imwrite(str(seq / f"rgb/{RGB_T[0]:.6f}.png"), np.dstack([img] * 3))
    r = TumReader(TumConfig(path=str(seq), resize=(324, 244), crop_multiple=8))
    f = r[0]
    k = f.intrinsics
    assert k.dist == () and (k.width, k.height) == (320, 240) == (f.width, f.height)
    out = f.image[0].numpy().astype(np.float64)
    for X in pts:
        u, v = k.fx * X[0] / X[2] + k.cx, k.fy * X[1] / X[2] + k.cy
        x0, y0 = int(round(u)), int(round(v))
        win = out[y0 - 6 : y0 + 7, x0 - 6 : x0 + 7]
        win = np.clip(win - 0.05 * win.max(), 0, None)
        wy, wx = np.mgrid[y0 - 6 : y0 + 7, x0 - 6 : x0 + 7]
        got = np.array([(win * wx).sum(), (win * wy).sum()]) / win.sum()
        assert np.linalg.norm(got - [u, v]) < 0.15, (X, got, (u, v))
