"""KITTI odometry benchmark reader.

Layout (the official ``data_odometry_*`` archives unpacked into one root)::

    <path>/sequences/NN/image_0/000000.png ...   (image_1 grey right, image_2/image_3 colour left/right)
    <path>/sequences/NN/calib.txt                 "P0: 12 numbers" ... (3x4 projection matrices, row-major)
    <path>/sequences/NN/times.txt                 one timestamp (s) per frame; optional, else 10 Hz
    <path>/poses/NN.txt                           3x4 row-major camera-to-world of camera 0, one line per frame

``path`` may also be a sequence folder itself, wherever it is and whatever its name (``image_0`` ... beside
``calib.txt``; ``calib`` names another calibration file).  A times.txt with more rows than images (an excerpt
of a sequence) is cut to the images, with a warning; fewer rows than images is an error.

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
import os
from pathlib import Path
from typing import Optional

import numpy as np

from pvslam_core.datasets.base import DatasetError, ImageFileReader
from pvslam_core.datasets.calib_kitti import (FORMAT, intrinsics_from_projection, is_projection_text,
                                              read_projection_matrices)
from pvslam_core.datasets.io import check_timestamps, image_size

from .config import KittiConfig

log = logging.getLogger(__name__)


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
        root = Path(os.path.abspath(Path(options.path).expanduser()))  # not resolved: a symlink keeps its name
        self.seq_dir, self.seq_name, pose_path = locate_sequence(root, options.sequence)
        self.image_dir = self.seq_dir / options.camera
        if not self.image_dir.is_dir():
            raise DatasetError(f"{self.image_dir}: image folder for camera {options.camera!r} not found")
        self.timestamps: Optional[np.ndarray] = None
        times_path = self.seq_dir / "times.txt"
        if times_path.is_file():
            self.timestamps = read_times(times_path)
        self.files = frame_files(self.image_dir, times_path if self.timestamps is not None else None,
                                 None if self.timestamps is None else len(self.timestamps))
        n = len(self.files)
        if self.timestamps is None:
            log.warning("%s: no times.txt; using %.3g Hz timestamps (KITTI's frame rate)", self.seq_dir, options.fps)
            self.timestamps = np.arange(n, dtype=np.float64) / options.fps
        self.timestamps = self.timestamps[:n]

        calib_path = Path(options.calib).expanduser() if options.calib else self.seq_dir / "calib.txt"
        if not calib_path.is_file():
            more = "" if options.calib else " (KITTI ships it in data_odometry_calib; or give --calib FILE)"
            raise DatasetError(f"{calib_path}: calibration file not found{more}")
        calib = read_projection_matrices(calib_path)
        k = options.camera[-1]
        pname = next((name for name in (f"P{k}", f"P_rect_0{k}") if name in calib), f"P{k}")
        if pname not in calib:
            raise DatasetError(f"{calib_path}: no {pname} for camera {options.camera!r} (the file has: "
                               f"{', '.join(calib) or 'nothing'}); expected {FORMAT}")
        self.P = calib[pname]
        w, h = image_size(self.files[0])
        self._intr = intrinsics_from_projection(self.P, w, h, f"{calib_path}: {pname}")
        log.info("%s: intrinsics from projection row %s (camera %s)", calib_path, pname, options.camera)

        self.poses: Optional[np.ndarray] = None
        if pose_path is not None and pose_path.is_file():
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
                P0 = calib.get("P0", calib.get("P_rect_00"))
                T_c0ck[:3, 3] = -(camera_offset(self.P) - (camera_offset(P0) if P0 is not None else 0.0))
                T_wc0 = T_wc0 @ T_c0ck
            self.poses = matrix_to_pose(T_wc0)

    def _sequence_name(self) -> str:
        return f"kitti_{self.seq_name}_{self.cfg.camera}"

    def _source(self) -> str:
        return str(self.seq_dir)


CAMERAS = ("image_0", "image_1", "image_2", "image_3")


def is_sequence_folder(d: Path) -> bool:
    """A KITTI sequence folder, by its content: an image_0..image_3 folder starting at 000000.png beside a
    calib.txt of projection rows (P0: 12 numbers ...) or a times.txt."""
    if not any((d / c / "000000.png").is_file() for c in CAMERAS):
        return False
    calib = d / "calib.txt"
    return (calib.is_file() and is_projection_text(calib.read_text())) or (d / "times.txt").is_file()


def locate_sequence(root: Path, sequence: str) -> tuple[Path, str, Optional[Path]]:
    """(sequence folder, its name, where its ground-truth poses would be): ``root/sequences/<sequence>`` under a
    dataset root, or ``root`` itself when it holds image folders (poses only in the official layout:
    ``<root>/../../poses/<name>.txt`` when the parent is named ``sequences``, a symlink included)."""
    if (root / "sequences").is_dir():
        seq_dir = root / "sequences" / sequence
        if not seq_dir.is_dir():
            raise DatasetError(f"{seq_dir}: KITTI sequence folder not found (path={root}, sequence={sequence!r})")
        return seq_dir, sequence, root / "poses" / f"{sequence}.txt"
    if any((root / c).is_dir() for c in CAMERAS):
        poses = root.parent.parent / "poses" / f"{root.name}.txt" if root.parent.name == "sequences" else None
        return root, root.name, poses
    raise DatasetError(f"{root / 'sequences' / sequence}: KITTI sequence folder not found (path={root}, sequence="
                       f"{sequence!r}; path may also be a sequence folder holding image_0|image_2 and calib.txt)")


def frame_files(image_dir: Path, times_path: Optional[Path], n_times: Optional[int]) -> list[Path]:
    """``000000.png`` .. ``N-1`` of ``image_dir`` (a gap is a missing frame).  A times.txt with more rows than
    images: its first N rows are used (a warning); with fewer rows: an error naming both counts."""
    files = sorted(p.name for p in image_dir.glob("*.png"))
    if not files:
        raise DatasetError(f"{image_dir}: no PNG images")
    present, n = set(files), len(files)
    if n_times is not None and n_times < n:
        raise DatasetError(f"{times_path}: {n_times} timestamps for {n} images in {image_dir}; it needs one row per "
                           "frame")
    out = [image_dir / f"{i:06d}.png" for i in range(n)]
    for p in out:
        if p.name not in present:
            listed = f" (listed in {times_path})" if times_path is not None else ""
            raise DatasetError(f"{p}: frame missing{listed}")
    if n_times is not None and n_times > n:
        log.warning("%s: %d timestamps for %d images in %s; using the first %d", times_path, n_times, n, image_dir, n)
    return out


def detect(path: Path):  # type: ignore[no-untyped-def]
    """A KITTI sequence folder recognised by its content wherever it is (see :func:`is_sequence_folder`; the
    path is not resolved, so a symlink keeps its name), one of its image folders, or a root holding sequences/."""
    from pvslam_core.datasets.detect import DatasetMatch

    p = Path(os.path.abspath(path))
    camera, guessed = None, []
    if p.name in CAMERAS and is_sequence_folder(p.parent):
        camera, seq_dir = p.name, p.parent
    elif is_sequence_folder(p):
        seq_dir = p
    elif (p / "sequences").is_dir():
        seqs = sorted(d for d in (p / "sequences").iterdir() if is_sequence_folder(d))
        if not seqs:
            return None
        seq_dir = seqs[0]
        guessed.append("sequence")
    else:
        return None
    if camera is None:
        camera = next(c for c in CAMERAS if (seq_dir / c / "000000.png").is_file())
        guessed.append("camera")
    more = ""
    if seq_dir.parent.name == "sequences":  # the official layout: ground truth in <root>/poses/NN.txt
        options = {"path": str(seq_dir.parent.parent), "sequence": seq_dir.name, "camera": camera}
        others = sorted(d.name for d in seq_dir.parent.iterdir() if d != seq_dir and is_sequence_folder(d))
        more = f"; other sequences there: {', '.join(others[:8])} (--set dataset.sequence=NN)" if others else ""
    else:
        options = {"path": str(seq_dir), "sequence": seq_dir.name, "camera": camera}
    return DatasetMatch(1.0, options, f"KITTI odometry sequence {seq_dir.name} ({camera}){more}", tuple(guessed))


def make_reader(config: KittiConfig, context=None) -> KittiReader:  # type: ignore[no-untyped-def]
    return KittiReader(config)
