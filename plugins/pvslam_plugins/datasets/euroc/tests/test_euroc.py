"""The ``euroc`` reader on an ASL-layout sequence written by the test."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pvslam_core.datasets.base import DatasetError
from pvslam_core.outputs.trajectory_io import pose_to_matrix
from pvslam_plugins.datasets.euroc.config import EurocConfig
from pvslam_plugins.datasets.euroc.reader import EurocReader, _parse_yaml_subset, parse_sensor

# T_BS of EuRoC's cam0 (MH_01_easy sensor.yaml)
T_BS = np.array([
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
])

SENSOR_YAML = """# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [{w}, {h}]
camera_model: pinhole
intrinsics: [{fu}, {fv}, {cu}, {cv}] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""

T0 = 1403636579763555584
DT = 50_000_000  # 20 Hz


def quat_wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def body_pose(t_ns: int) -> np.ndarray:
    s = (t_ns - T0) * 1e-9
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.1 * s, -0.2 + 0.05 * s, 0.3]))[0]
    T[:3, 3] = [4.0 + s, -1.0 + 0.5 * s, 0.8 - 0.1 * s]
    return T


def fake_euroc(root: Path, n: int = 5, w: int = 96, h: int = 64) -> Path:
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    stamps = [T0 + i * DT for i in range(n)]
    rows = ["#timestamp [ns],filename"]
    for i, t in enumerate(stamps):
        cv2.imwrite(str(cam / "data" / f"{t}.png"), np.full((h, w), 30 + 10 * i, np.uint8))
        rows.append(f"{t},{t}.png")
    (cam / "data.csv").write_text("\n".join(rows) + "\n")
    (cam / "sensor.yaml").write_text(SENSOR_YAML.format(w=w, h=h, fu=80.5, fv=80.1, cu=47.3, cv=31.6))
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
             "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
             "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"]
    # 200 Hz ground truth offset by 1 ms from the frames, ending before the last frame
    for t in range(T0 + 1_000_000, stamps[-1] - 20_000_000, 5_000_000):
        T = body_pose(t)
        vals = [*T[:3, 3], *quat_wxyz(T[:3, :3]), 0, 0, 0, 0, 0, 0, 0, 0, 0]
        lines.append(f"{t}," + ",".join(f"{v:.12f}" for v in vals))
    (gt / "data.csv").write_text("\n".join(lines) + "\n")
    return root


def test_ground_truth_is_converted_to_the_camera(tmp_path):
    fake_euroc(tmp_path)
    r = EurocReader(EurocConfig(path=str(tmp_path), undistort=False, crop_multiple=1))
    frames = list(r)
    assert len(frames) == 5 and r.info().has_gt_pose
    for f in frames[:4]:
        t_ns = T0 + f.index * DT
        assert f.timestamp == pytest.approx(t_ns * 1e-9)
        # ground truth sampled 1 ms after the frame (within the 5 ms default)
        expected = body_pose(t_ns + 1_000_000) @ T_BS
        assert np.allclose(pose_to_matrix(f.gt_pose.numpy()), expected, atol=1e-9)
        # camera centre = body position + R_wb * (camera position in the body frame)
        Twb = body_pose(t_ns + 1_000_000)
        assert np.allclose(f.gt_pose[:3].numpy(), Twb[:3, 3] + Twb[:3, :3] @ T_BS[:3, 3], atol=1e-9)
    assert frames[4].gt_pose is None  # no ground truth within 5 ms of the last frame
    assert frames[0].image[:, 0, 0].tolist() == [30, 30, 30]


def test_gt_max_diff_is_configurable(tmp_path):
    fake_euroc(tmp_path)
    r = EurocReader(EurocConfig(path=str(tmp_path), gt_max_diff=0.0005))
    assert not r.info().has_gt_pose and r[0].gt_pose is None


def test_intrinsics_and_undistortion(tmp_path):
    fake_euroc(tmp_path)
    raw = EurocReader(EurocConfig(path=str(tmp_path), undistort=False, crop_multiple=1)).info().intrinsics
    assert (raw.fx, raw.fy, raw.cx, raw.cy, raw.width, raw.height) == (80.5, 80.1, 47.3, 31.6, 96, 64)
    assert raw.dist == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    und = EurocReader(EurocConfig(path=str(tmp_path))).info().intrinsics
    assert und.dist == () and (und.fx, und.cx, und.width, und.height) == (80.5, 47.3, 96, 64)
    # path may also point at mav0 itself
    assert EurocReader(EurocConfig(path=str(tmp_path / "mav0"))).info().num_frames == 5


def test_yaml_subset_parser_agrees_with_pyyaml(tmp_path):
    text = SENSOR_YAML.format(w=752, h=480, fu=458.654, fv=457.296, cu=367.215, cv=248.375)
    mine = _parse_yaml_subset(text)
    assert mine["T_BS"]["data"] == pytest.approx(T_BS.reshape(-1).tolist())
    assert mine["resolution"] == [752, 480] and mine["rate_hz"] == 20
    assert mine["distortion_model"] == "radial-tangential"
    yaml = pytest.importorskip("yaml")
    ref = yaml.safe_load(text)
    for key in ("intrinsics", "resolution", "distortion_coefficients", "distortion_model", "camera_model"):
        assert mine[key] == ref[key]
    assert mine["T_BS"] == ref["T_BS"]


def test_works_without_pyyaml(tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_yaml(name, *args, **kwargs):
        if name == "yaml":
            raise ImportError("no yaml")
        return real_import(name, *args, **kwargs)

    fake_euroc(tmp_path)
    monkeypatch.setattr(builtins, "__import__", no_yaml)
    intr, tbs = parse_sensor(tmp_path / "mav0/cam0/sensor.yaml")
    assert np.allclose(tbs, T_BS) and intr.fx == 80.5


# ------------------------------------------------------------------------------------------------ errors ----
def test_missing_frame_names_file_and_list(tmp_path):
    fake_euroc(tmp_path)
    (tmp_path / f"mav0/cam0/data/{T0 + DT}.png").unlink()
    with pytest.raises(DatasetError, match=rf"{T0 + DT}\.png: frame missing \(listed in .*data\.csv\)"):
        EurocReader(EurocConfig(path=str(tmp_path)))


def test_unsorted_groundtruth_names_the_file(tmp_path):
    fake_euroc(tmp_path)
    p = tmp_path / "mav0/state_groundtruth_estimate0/data.csv"
    lines = p.read_text().splitlines()
    lines[2], lines[3] = lines[3], lines[2]
    p.write_text("\n".join(lines))
    with pytest.raises(DatasetError, match=r"state_groundtruth_estimate0/data\.csv: unsorted"):
        EurocReader(EurocConfig(path=str(tmp_path)))


def test_duplicate_frame_timestamps_name_the_file(tmp_path):
    fake_euroc(tmp_path)
    p = tmp_path / "mav0/cam0/data.csv"
    lines = p.read_text().splitlines()
    lines.insert(2, lines[1])
    p.write_text("\n".join(lines))
    with pytest.raises(DatasetError, match=r"cam0/data\.csv: duplicate"):
        EurocReader(EurocConfig(path=str(tmp_path)))


def test_bad_intrinsics_count_names_the_file(tmp_path):
    fake_euroc(tmp_path)
    p = tmp_path / "mav0/cam0/sensor.yaml"
    p.write_text(p.read_text().replace("intrinsics: [80.5, 80.1, 47.3, 31.6]", "intrinsics: [80.5, 80.1, 47.3]"))
    with pytest.raises(DatasetError, match=r"sensor\.yaml: 'intrinsics' must have 4 values, found 3"):
        EurocReader(EurocConfig(path=str(tmp_path)))


def test_corrupt_image_names_the_file(tmp_path):
    fake_euroc(tmp_path)
    (tmp_path / f"mav0/cam0/data/{T0}.png").write_bytes(b"")
    with pytest.raises(DatasetError, match=rf"{T0}\.png: unreadable or corrupt"):
        EurocReader(EurocConfig(path=str(tmp_path)))[0]


def test_not_an_euroc_folder(tmp_path):
    with pytest.raises(DatasetError, match="mav0/cam0"):
        EurocReader(EurocConfig(path=str(tmp_path)))


def test_registered_through_the_hook(monkeypatch):
    import pvslam_plugins.datasets.euroc as plugin
    from pvslam_core.registry import build_registry

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    assert build_registry(extra_modules=(plugin,)).get("dataset", "euroc").config_model is EurocConfig
