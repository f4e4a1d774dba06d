"""TUM RGB-D benchmark reader.

::

    <path>/rgb.txt            "timestamp rgb/<t>.png" lines ('#' comments)
    <path>/depth.txt          "timestamp depth/<t>.png" (16-bit PNG, value / 5000 = metres, 0 = invalid); optional
    <path>/groundtruth.txt    TUM trajectory "timestamp tx ty tz qx qy qz qw" (T_wc); optional
    <path>/calib.txt          "fx fy cx cy [k1 k2 p1 p2 [k3]]" (or any format --calib reads); optional

Every rgb frame is yielded; depth and ground truth are attached by nearest timestamp within ``max_diff``
(0.02 s, as TUM's associate.py).  Intrinsics, in increasing precedence: the freiburg preset chosen from the
folder name (``rgbd_dataset_freiburg1_*`` ...), ``calib.txt`` beside the data, the config's ``calib``.
Presets are TUM's published calibrations of the colour cameras, for 640x480 images
(https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats, "Intrinsic Camera Calibration of the Kinect";
DROID-SLAM's TUM reader uses the same values).

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "tum"
    path = "/data/tum/rgbd_dataset_freiburg1_xyz"
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Optional

import numpy as np

from pvslam_core.datasets.base import BaseReader, DatasetError
from pvslam_core.datasets.calib import calibration_from_option, intrinsics_from_values, read_calibration
from pvslam_core.datasets.io import (
    associate_nearest,
    associate_poses,
    image_size,
    pose_at,
    read_depth_png,
    read_file_list,
    read_rgb,
)
from pvslam_core.types import Frame, Intrinsics

from .config import TumConfig

log = logging.getLogger(__name__)

#: fx fy cx cy k1 k2 p1 p2 k3 of the colour camera per freiburg sensor
PRESETS: dict[str, tuple[float, ...]] = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "freiburg2": (520.9, 521.0, 325.1, 249.7, 0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}


def preset_for(folder: Path) -> Optional[str]:
    m = re.search(r"freiburg([123])", folder.resolve().name)
    return f"freiburg{m.group(1)}" if m else None


class TumReader(BaseReader):
    def __init__(self, options: TumConfig):
        super().__init__(options)
        self.cfg = options
        self.root = Path(options.path).expanduser()
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: TUM sequence folder not found")
        rgb_list = self.root / "rgb.txt"
        self.ts, names = read_file_list(rgb_list)
        if len(names) == 0:
            raise DatasetError(f"{rgb_list}: lists no frames")
        self.files = [self.root / n for n in names]
        for p in self.files:
            if not p.is_file():
                raise DatasetError(f"{p}: frame missing (listed in {rgb_list})")

        self.depth_files: Optional[list[Optional[Path]]] = None
        depth_list = self.root / "depth.txt"
        if depth_list.is_file():
            dts, dnames = read_file_list(depth_list)
            idx = associate_nearest(self.ts, dts, options.max_diff)
            self.depth_files = [self.root / dnames[i] if i >= 0 else None for i in idx]
            for p in self.depth_files:
                if p is not None and not p.is_file():
                    raise DatasetError(f"{p}: depth image missing (listed in {depth_list})")
            if all(p is None for p in self.depth_files):
                self.depth_files = None

        self.poses: Optional[np.ndarray] = None
        gt_path = self.root / "groundtruth.txt"
        if gt_path.is_file():
            from pvslam_core.outputs.trajectory_io import read_tum

            gts, gposes = read_tum(gt_path)
            self.poses = associate_poses(self.ts, gts, gposes, options.max_diff)

        w, h = image_size(self.files[0])
        self._intr = self._intrinsics(w, h)

    def _intrinsics(self, w: int, h: int) -> Intrinsics:
        if self.cfg.calib is not None:
            return calibration_from_option(self.cfg.calib, w, h, owner="tum reader")
        calib_txt = self.root / "calib.txt"
        if calib_txt.is_file():
            return read_calibration(calib_txt, w, h)
        preset = preset_for(self.root)
        if preset is None:
            raise DatasetError(
                f"{self.root}: no intrinsics: the folder name names no freiburg camera, there is no calib.txt "
                "and the config has no 'calib' (fx fy cx cy [k1 k2 p1 p2 [k3]])"
            )
        vals = PRESETS[preset]
        if (w, h) != (640, 480):
            raise DatasetError(f"{self.files[0]}: {preset} preset is for 640x480 images, found {w}x{h}")
        return intrinsics_from_values(vals, w, h, source=f"TUM {preset} preset")

    def _raw_count(self) -> int:
        return len(self.files)

    def _raw_intrinsics(self) -> Intrinsics:
        return self._intr

    def _sequence_name(self) -> str:
        return f"tum_{self.root.resolve().name}"

    def _source(self) -> str:
        return str(self.root)

    def _has_gt(self) -> tuple[bool, bool, bool]:
        return (self.poses is not None, self.depth_files is not None, False)

    def _load(self, raw_index: int) -> Frame:
        path = self.files[raw_index]
        depth = None
        if self.depth_files is not None and self.depth_files[raw_index] is not None:
            depth = read_depth_png(self.depth_files[raw_index], self.cfg.depth_scale)
        return Frame(
            index=raw_index,
            timestamp=float(self.ts[raw_index]),
            image=read_rgb(path),
            intrinsics=self._intr,
            gt_pose=pose_at(self.poses, raw_index),
            gt_depth=depth,
            name=path.name,
        )


def detect(path: Path):  # type: ignore[no-untyped-def]
    """A folder with TUM's ``rgb.txt``."""
    from pvslam_core.datasets.detect import DatasetMatch

    if not (path.is_dir() and (path / "rgb.txt").is_file()):
        return None
    return DatasetMatch(0.9, {"path": str(path)}, f"TUM RGB-D sequence {path.resolve().name}")


def make_reader(config: TumConfig, context=None) -> TumReader:  # type: ignore[no-untyped-def]
    return TumReader(config)
