"""A folder of images with a calibration: the simplest way to run pvslam on your own data.

Images (``.png .jpg .jpeg .bmp .tif .tiff .ppm .pgm``) directly inside ``path`` are read in natural order.
Timestamps are ``index / fps`` or, with ``timestamps="filename"``, the numeric file stem (e.g. TUM's
``1305031102.175304.png``; stems above 1e15 are taken as nanoseconds, as EuRoC names them).  An optional TUM
``groundtruth`` file is associated by nearest timestamp.

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "images"
    path = "/data/my_run/frames"
    calib = [458.6, 457.3, 367.2, 248.4, -0.28, 0.07, 0.0002, 0.00002]   # or a file path
    fps = 20
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from pvslam_core.datasets.base import DatasetError, ImageFileReader
from pvslam_core.datasets.calib import calibration_from_option
from pvslam_core.datasets.io import associate_poses, check_timestamps, image_size, list_images

from .config import ImagesConfig


def timestamps_from_names(files: list[Path]) -> np.ndarray:
    ts = []
    for p in files:
        try:
            v = float(p.stem)
        except ValueError:
            raise DatasetError(f"{p}: timestamps='filename' needs numeric file names, got {p.stem!r}") from None
        ts.append(v * 1e-9 if v > 1e15 else v)
    arr = np.asarray(ts, dtype=np.float64)
    check_timestamps(arr, files[0].parent)
    return arr


class ImagesReader(ImageFileReader):
    def __init__(self, options: ImagesConfig):
        super().__init__(options)
        self.cfg = options
        self.folder = Path(options.path).expanduser()
        self.files = list_images(self.folder)
        if not self.files:
            raise DatasetError(f"{self.folder}: no images (png, jpg, ...) in the folder")
        if options.timestamps == "filename":
            self.timestamps = timestamps_from_names(self.files)
        else:
            self.timestamps = np.arange(len(self.files), dtype=np.float64) / options.fps
        w, h = image_size(self.files[0])
        self._intr = calibration_from_option(
            options.calib, w, h, search=(self.folder, self.folder.parent), owner=f"images reader ({self.folder})"
        )
        self.poses: Optional[np.ndarray] = None
        if options.groundtruth is not None:
            from pvslam_core.outputs.trajectory_io import read_tum

            gts, gposes = read_tum(Path(options.groundtruth).expanduser())
            self.poses = associate_poses(self.timestamps, gts, gposes, options.gt_max_diff)
            if self.poses is None:
                raise DatasetError(
                    f"{options.groundtruth}: no ground-truth timestamp within {options.gt_max_diff} s of any frame "
                    f"(frames span {self.timestamps[0]:.3f}..{self.timestamps[-1]:.3f} s; timestamps={options.timestamps!r})"
                )

    def _sequence_name(self) -> str:
        return f"images_{self.folder.resolve().name}"

    def _source(self) -> str:
        return str(self.folder)


def make_reader(config: ImagesConfig, context=None) -> ImagesReader:  # type: ignore[no-untyped-def]
    return ImagesReader(config)
