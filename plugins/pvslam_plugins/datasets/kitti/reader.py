"""KITTI odometry benchmark reader.

Layout (the official ``data_odometry_*`` archives unpacked into one root)::

    <path>/sequences/NN/image_0/000000.png ...   (image_1 grey right, image_2/image_3 colour left/right)
    <path>/sequences/NN/calib.txt                 "P0: 12 numbers" ... (3x4 projection matrices, row-major)
    <path>/sequences/NN/times.txt                 one timestamp (s) per frame; optional, else 10 Hz
    <path>/poses/NN.txt                           3x4 row-major camera-to-world of camera 0, one line per frame

Images are rectified (no distortion).  Camera k's projection is ``P_k = K_k [I | t_k]`` in camera-0
coordinates, so ``t_k = K_k^-1 P_k[:, 3]`` and a point in camera 0 is ``X_k = X_0 + t_k``: the camera-k centre
sits at ``-t_k`` in camera 0 (for image_2, ``tx = -P2[0,3] / P2[0,0]`` ~ +0.06 m) and ``T_w,ck = T_w,c0 [I | -t_k]``.

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "kitti"
    path = "/data/kitti/odometry/dataset"   # holds sequences/ and poses/
    sequence = "06"
    camera = "image_2"
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import numpy as np

from pvslam_core.datasets.base import DatasetError, ImageFileReader
from pvslam_core.datasets.io import check_timestamps, image_size
from pvslam_core.types import Intrinsics

from .config import KittiConfig

log = logging.getLogger(__name__)


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """``calib.txt`` -> {"P0": 3x4, ..., "Tr": 3x4}; errors name the file, line and value count."""
    if not path.is_file():
        raise DatasetError(f"{path}: calibration file not found")
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        if ":" not in line:
            raise DatasetError(f"{path}:{lineno}: expected 'NAME: 12 numbers', got {line.strip()!r}")
        key, vals = line.split(":", 1)
        try:
            nums = [float(v) for v in vals.split()]
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: non-numeric value in {key.strip()}") from None
        if len(nums) != 12:
            raise DatasetError(f"{path}:{lineno}: {key.strip()} needs 12 values (3x4 matrix), found {len(nums)}")
        out[key.strip()] = np.asarray(nums, dtype=np.float64).reshape(3, 4)
    return out


def camera_offset(P: np.ndarray) -> np.ndarray:
    """``t`` with ``P = K [I | t]``: camera-k coordinates are camera-0 coordinates plus ``t``."""
    return np.linalg.solve(P[:, :3], P[:, 3])


def read_times(path: Path) -> np.ndarray:
    vals: list[float] = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        try:
            vals.append(float(s.split()[0]))
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not a timestamp: {s!r}") from None
    ts = np.asarray(vals, dtype=np.float64)
    check_timestamps(ts, path)
    return ts


class KittiReader(ImageFileReader):
    def __init__(self, options: KittiConfig):
        super().__init__(options)
        self.cfg = options
        root = Path(options.path).expanduser()
        seq = options.sequence
        self.seq_dir = root / "sequences" / seq
        if not self.seq_dir.is_dir():
            raise DatasetError(f"{self.seq_dir}: KITTI sequence folder not found (path={root}, sequence={seq!r})")
        self.image_dir = self.seq_dir / options.camera
        if not self.image_dir.is_dir():
            raise DatasetError(f"{self.image_dir}: image folder for camera {options.camera!r} not found")
        files = sorted(p.name for p in self.image_dir.glob("*.png"))
        if not files:
            raise DatasetError(f"{self.image_dir}: no PNG images")
        # frames are 000000.png .. N-1; a gap means a missing frame
        present = set(files)
        n = len(files)
        times_path = self.seq_dir / "times.txt"
        self.timestamps: Optional[np.ndarray] = None
        if times_path.is_file():
            self.timestamps = read_times(times_path)
            n = len(self.timestamps)
        self.files = [self.image_dir / f"{i:06d}.png" for i in range(n)]
        for p in self.files:
            if p.name not in present:
                listed = f" (listed in {times_path})" if self.timestamps is not None else ""
                raise DatasetError(f"{p}: frame missing{listed}")
        if self.timestamps is None:
            log.warning("%s: no times.txt; using %.3g Hz timestamps (KITTI's frame rate)", self.seq_dir, options.fps)
            self.timestamps = np.arange(n, dtype=np.float64) / options.fps

        calib = read_kitti_calib(self.seq_dir / "calib.txt")
        pname = "P" + options.camera[-1]
        if pname not in calib:
            raise DatasetError(f"{self.seq_dir / 'calib.txt'}: no {pname} for camera {options.camera!r}")
        self.P = calib[pname]
        w, h = image_size(self.files[0])
        try:
            self._intr = Intrinsics(
                float(self.P[0, 0]), float(self.P[1, 1]), float(self.P[0, 2]), float(self.P[1, 2]), w, h
            )
        except ValueError as exc:
            raise DatasetError(f"{self.seq_dir / 'calib.txt'}: {pname}: {exc}") from exc

        self.poses: Optional[np.ndarray] = None
        pose_path = root / "poses" / f"{seq}.txt"
        if pose_path.is_file():
            from pvslam_core.outputs.trajectory_io import matrix_to_pose, pose_to_matrix, read_kitti_poses

            p7 = read_kitti_poses(pose_path)
            if len(p7) < n:
                raise DatasetError(f"{pose_path}: {len(p7)} poses for {n} frames")
            if len(p7) > n:
                log.warning("%s: %d poses for %d frames; using the first %d", pose_path, len(p7), n, n)
                p7 = p7[:n]
            T_wc0 = pose_to_matrix(p7)
            if options.camera != "image_0":
                # X_k = X_0 + (t_k - t_0)  =>  T_c0,ck = [I | -(t_k - t_0)]   (t_0 = 0 in KITTI's calib files)
                T_c0ck = np.eye(4)
                T_c0ck[:3, 3] = -(camera_offset(self.P) - (camera_offset(calib["P0"]) if "P0" in calib else 0.0))
                T_wc0 = T_wc0 @ T_c0ck
            self.poses = matrix_to_pose(T_wc0)

    def _sequence_name(self) -> str:
        return f"kitti_{self.cfg.sequence}_{self.cfg.camera}"

    def _source(self) -> str:
        return str(self.seq_dir)


CAMERAS = ("image_0", "image_1", "image_2", "image_3")


def detect(path: Path):  # type: ignore[no-untyped-def]
    """``<root>/sequences/NN`` (or one of its image folders, or a root holding sequences/) with a P0..P3 calib.txt."""
    from pvslam_core.datasets.detect import DatasetMatch

    p = path.resolve()
    camera = None
    if p.name in CAMERAS and p.parent.parent.name == "sequences":
        camera, seq_dir = p.name, p.parent
    elif p.parent.name == "sequences":
        seq_dir = p
    elif (p / "sequences").is_dir():
        seqs = sorted(d for d in (p / "sequences").iterdir() if (d / "calib.txt").is_file())
        if not seqs:
            return None
        seq_dir = seqs[0]
    else:
        return None
    calib = seq_dir / "calib.txt"
    if not calib.is_file() or not any(line.startswith("P0:") for line in calib.read_text().splitlines()):
        return None
    if camera is None:
        camera = next((c for c in CAMERAS if any((seq_dir / c).glob("*.png"))), None)
        if camera is None:
            return None
    others = sorted(d.name for d in seq_dir.parent.iterdir() if (d / "calib.txt").is_file() and d != seq_dir)
    more = f"; other sequences there: {', '.join(others[:8])} (--set dataset.sequence=NN)" if others else ""
    return DatasetMatch(1.0, {"path": str(seq_dir.parent.parent), "sequence": seq_dir.name, "camera": camera},
                        f"KITTI odometry sequence {seq_dir.name} ({camera}){more}")


def make_reader(config: KittiConfig, context=None) -> KittiReader:  # type: ignore[no-untyped-def]
    return KittiReader(config)
