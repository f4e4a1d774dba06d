"""EuRoC MAV reader (ASL folder layout).

::

    <path>/mav0/cam0/data.csv          "#timestamp [ns],filename" then one "ns,name.png" line per frame
    <path>/mav0/cam0/data/<ns>.png     8-bit grayscale, 752x480
    <path>/mav0/cam0/sensor.yaml       T_BS (4x4 row-major, sensor -> body), resolution, intrinsics [fu, fv, cu, cv],
                                       distortion_model radial-tangential, distortion_coefficients [k1, k2, p1, p2]
    <path>/mav0/state_groundtruth_estimate0/data.csv
                                       "#timestamp, p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x, q_RS_y, q_RS_z, ..."

The ground truth is the body (IMU) pose in the world, ``T_wb``; the camera pose is ``T_wc = T_wb T_BS``.  It is
attached to a frame when a ground-truth sample lies within ``gt_max_diff`` seconds (nearest timestamp).

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "euroc"
    path = "/data/euroc/MH_01_easy"         # holds mav0/
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Optional

import numpy as np

from pvslam_core.datasets.base import DatasetError, ImageFileReader
from pvslam_core.datasets.io import associate_poses, check_timestamps, read_file_list
from pvslam_core.types import Intrinsics

from .config import EurocConfig

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------- sensor.yaml ----
def _parse_yaml_subset(text: str) -> dict[str, Any]:
    """The part of EuRoC's sensor.yaml pvslam needs, without PyYAML.

    Handles ``key: scalar``, ``key: [flow, list]`` (possibly spanning lines) and one level of nesting
    (``T_BS:`` followed by indented ``cols/rows/data``).  Comments (``#``) are dropped.
    """
    lines = [ln.split("#", 1)[0].rstrip() for ln in text.splitlines()]
    out: dict[str, Any] = {}
    parent: Optional[dict[str, Any]] = None
    i = 0
    while i < len(lines):
        raw = lines[i]
        i += 1
        if not raw.strip() or raw.lstrip().startswith("%") or raw.strip() == "---":
            continue
        indent = len(raw) - len(raw.lstrip())
        m = re.match(r"\s*([A-Za-z_][\w\-]*)\s*:\s*(.*)$", raw)
        if not m:
            continue
        key, val = m.group(1), m.group(2).strip()
        target = out if indent == 0 or parent is None else parent
        if indent == 0:
            parent = None
        if val == "":
            child: dict[str, Any] = {}
            out[key] = child
            parent = child
            continue
        if val.startswith("["):
            while "]" not in val and i < len(lines):
                val += " " + lines[i].strip()
                i += 1
            body = val[1 : val.index("]")]
            items = [t.strip() for t in body.split(",") if t.strip()]
            target[key] = [_scalar(t) for t in items]
        else:
            target[key] = _scalar(val)
    return out


def _scalar(tok: str) -> Any:
    tok = tok.strip().strip("'\"")
    try:
        return int(tok)
    except ValueError:
        pass
    try:
        return float(tok)
    except ValueError:
        return tok


def load_sensor_yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise DatasetError(f"{path}: camera sensor.yaml not found")
    text = path.read_text()
    try:
        import yaml  # PyYAML is optional (not a pvslam dependency)
    except ImportError:
        return _parse_yaml_subset(text)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a YAML mapping")
    return data


def _numbers(d: dict[str, Any], key: str, count: int, path: Path) -> list[float]:
    v = d.get(key)
    if not isinstance(v, (list, tuple)):
        raise DatasetError(f"{path}: missing {key!r} (a list of {count} numbers)")
    if len(v) != count:
        raise DatasetError(f"{path}: {key!r} must have {count} values, found {len(v)}")
    try:
        return [float(x) for x in v]
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {key!r} holds a non-number: {v}") from None


def parse_sensor(path: Path) -> tuple[Intrinsics, np.ndarray]:
    """sensor.yaml -> (intrinsics with distortion, T_BS 4x4)."""
    d = load_sensor_yaml(path)
    fu, fv, cu, cv = _numbers(d, "intrinsics", 4, path)
    w, h = (int(x) for x in _numbers(d, "resolution", 2, path))
    model = str(d.get("distortion_model", "radial-tangential"))
    if model not in ("radial-tangential", "radtan", "plumb_bob"):
        raise DatasetError(f"{path}: distortion_model {model!r} is not supported (only radial-tangential)")
    dist = tuple(_numbers(d, "distortion_coefficients", 4, path))
    tbs = d.get("T_BS")
    if not isinstance(tbs, dict):
        raise DatasetError(f"{path}: missing T_BS (with data: [16 numbers])")
    T_BS = np.asarray(_numbers(tbs, "data", 16, path), dtype=np.float64).reshape(4, 4)
    try:
        intr = Intrinsics(fu, fv, cu, cv, w, h, dist)
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from exc
    return intr, T_BS


# ----------------------------------------------------------------------------------------------- csv files ----
def _parse_ns(tok: str) -> int:
    try:
        return int(tok)
    except ValueError:
        return int(round(float(tok)))


def read_image_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """cam0/data.csv -> (timestamps int64 ns, file names)."""
    if not path.is_file():
        raise DatasetError(f"{path}: image list not found")
    return read_file_list(path, parse=_parse_ns, dtype=np.int64, what="timestamp in ns")

def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """state_groundtruth_estimate0/data.csv -> (timestamps int64 ns, T_wb float64 [N, 4, 4])."""
    from pvslam_core.outputs.trajectory_io import pose_to_matrix

    ts: list[int] = []
    vals: list[list[float]] = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if len(parts) < 8:
            raise DatasetError(f"{path}:{lineno}: expected timestamp, p_xyz, q_wxyz (8+ values), found {len(parts)}")
        try:
            ts.append(_parse_ns(parts[0]))
            vals.append([float(p) for p in parts[1:8]])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: non-numeric value in {s!r}") from None
    t = np.asarray(ts, dtype=np.int64)
    check_timestamps(t, path)
    v = np.asarray(vals, dtype=np.float64).reshape(-1, 7)
    # EuRoC quaternions are w, x, y, z; ours are x, y, z, w
    p7 = np.concatenate([v[:, :3], v[:, 4:7], v[:, 3:4]], axis=1)
    if np.any(np.linalg.norm(p7[:, 3:], axis=1) < 1e-9):
        raise DatasetError(f"{path}: zero quaternion")
    return t, pose_to_matrix(p7)


# ------------------------------------------------------------------------------------------------- reader ----
class EurocReader(ImageFileReader):
    def __init__(self, options: EurocConfig):
        super().__init__(options)
        self.cfg = options
        root = Path(options.path).expanduser()
        mav = root / "mav0" if (root / "mav0").is_dir() else root
        self.cam_dir = mav / options.camera
        if not self.cam_dir.is_dir():
            raise DatasetError(f"{root}: no mav0/{options.camera}/ folder (expected the EuRoC ASL layout)")
        csv = self.cam_dir / "data.csv"
        self.ts_ns, names = read_image_list(csv)
        self.timestamps = self.ts_ns * 1e-9
        if len(names) == 0:
            raise DatasetError(f"{csv}: lists no frames")
        self.files = [self.cam_dir / "data" / n for n in names]
        for p in self.files:
            if not p.is_file():
                raise DatasetError(f"{p}: frame missing (listed in {csv})")
        self._intr, self.T_BS = parse_sensor(self.cam_dir / "sensor.yaml")

        self.poses: Optional[np.ndarray] = None
        gt_path = mav / "state_groundtruth_estimate0" / "data.csv"
        if gt_path.is_file():
            from pvslam_core.outputs.trajectory_io import matrix_to_pose

            gt_ns, T_wb = read_groundtruth(gt_path)
            self.poses = associate_poses(
                self.ts_ns * 1e-9, gt_ns * 1e-9, matrix_to_pose(T_wb @ self.T_BS), options.gt_max_diff
            )
            if self.poses is None:
                log.warning("%s: no ground-truth sample within %.3g s of any frame", gt_path, options.gt_max_diff)

    def _sequence_name(self) -> str:
        return f"euroc_{Path(self.cfg.path).expanduser().resolve().name}_{self.cfg.camera}"

    def _source(self) -> str:
        return str(self.cam_dir)


def detect(path: Path):  # type: ignore[no-untyped-def]
    """A sequence folder holding ``mav0/``, ``mav0`` itself, or ``mav0/cam0|cam1`` (with data.csv and sensor.yaml)."""
    from pvslam_core.datasets.detect import DatasetMatch

    p = path.resolve()
    camera, guessed = "cam0", ("camera",)
    if p.name in ("cam0", "cam1") and p.parent.name == "mav0":
        camera, mav, guessed = p.name, p.parent, ()
    elif p.name == "mav0":
        mav = p
    else:
        mav = p / "mav0"
    cam = mav / camera
    if not ((cam / "data.csv").is_file() and (cam / "sensor.yaml").is_file()):
        return None
    name = mav.parent.name if mav.name == "mav0" else mav.name
    return DatasetMatch(1.0, {"path": str(mav.parent), "camera": camera}, f"EuRoC MAV sequence {name} ({camera})",
                        guessed)


def make_reader(config: EurocConfig, context=None) -> EurocReader:  # type: ignore[no-untyped-def]
    return EurocReader(config)
