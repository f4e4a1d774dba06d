"""A folder of images with a calibration: the simplest way to run pvslam on your own data.

Images (``.png .jpg .jpeg .bmp .tif .tiff .ppm .pgm``) directly inside ``path`` are read in natural order.
Timestamps are ``index / fps`` or, with ``timestamps="filename"``, the numeric file stem (e.g. TUM's
``1305031102.175304.png``; stems above 1e15 are taken as nanoseconds, as EuRoC names them).  An optional TUM
``groundtruth`` file is associated by nearest timestamp.

With ``follow = true`` the folder may still be growing (a camera or another program writing frames): images are
read as they appear until none has appeared for ``wait_timeout`` seconds, so the length is unknown
(``SequenceInfo.num_frames`` None).  An image that cannot be decoded yet (still being written) is retried until
the timeout; one that appears with a name sorting before images already read is skipped with a warning.

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "images"
    path = "/data/my_run/frames"
    calib = [458.6, 457.3, 367.2, 248.4, -0.28, 0.07, 0.0002, 0.00002]   # or a file path
    fps = 20
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Iterator, Optional

import numpy as np
import torch

from pvslam_core.datasets.base import DatasetError, ImageFileReader
from pvslam_core.datasets.calib import calibration_from_option
from pvslam_core.datasets.calib_kitti import camera_from_folder
from pvslam_core.datasets.io import (associate_nearest, associate_poses, check_timestamps, image_size, list_images,
                                     natural_key, read_rgb)
from pvslam_core.types import Frame

from .config import ImagesConfig

log = logging.getLogger(__name__)
POLL_S = 0.05  # how often a followed folder is listed while no new image is pending


def _stem_time(p: Path) -> float:
    try:
        v = float(p.stem)
    except ValueError:
        raise DatasetError(f"{p}: timestamps='filename' needs numeric file names, got {p.stem!r}") from None
    return v * 1e-9 if v > 1e15 else v


def timestamps_from_names(files: list[Path]) -> np.ndarray:
    arr = np.asarray([_stem_time(p) for p in files], dtype=np.float64)
    check_timestamps(arr, files[0].parent)
    return arr


class ImagesReader(ImageFileReader):
    def __init__(self, options: ImagesConfig):
        super().__init__(options)
        self.cfg = options
        self.folder = Path(options.path).expanduser()
        self.files = list_images(self.folder)
        if not self.files and options.follow:
            self.files = self._wait_for_first()
        if not self.files:
            raise DatasetError(f"{self.folder}: no images (png, jpg, ...) in the folder")
        if options.follow:
            self.timestamps = np.zeros(0)  # computed per image as it arrives
        elif options.timestamps == "filename":
            self.timestamps = timestamps_from_names(self.files)
        else:
            self.timestamps = np.arange(len(self.files), dtype=np.float64) / options.fps
        w, h = image_size(self.files[0])
        self._intr = calibration_from_option(
            options.calib, w, h, search=(self.folder, self.folder.parent), owner=f"images reader ({self.folder})",
            camera=camera_from_folder(self.folder),  # a KITTI calib.txt: image_2 takes P2
        )
        self.poses: Optional[np.ndarray] = None
        self._gt: Optional[tuple[np.ndarray, np.ndarray]] = None
        if options.groundtruth is not None:
            from pvslam_core.outputs.trajectory_io import read_tum

            self._gt = read_tum(Path(options.groundtruth).expanduser())
            if not options.follow:
                self.poses = associate_poses(self.timestamps, *self._gt, options.gt_max_diff)
                if self.poses is None:
                    raise DatasetError(
                        f"{options.groundtruth}: no ground-truth timestamp within {options.gt_max_diff} s of any "
                        f"frame (frames span {self.timestamps[0]:.3f}..{self.timestamps[-1]:.3f} s; "
                        f"timestamps={options.timestamps!r})"
                    )

    def _sequence_name(self) -> str:
        return f"images_{self.folder.resolve().name}"

    def _source(self) -> str:
        return str(self.folder)

    # ----------------------------------------------------------------------------------- a growing folder --
    def _raw_count(self) -> Optional[int]:
        return None if self.cfg.follow else len(self.files)

    def _has_gt(self) -> tuple[bool, bool, bool]:
        return (self.poses is not None or (self.cfg.follow and self._gt is not None), False, False)

    def _wait_for_first(self) -> list[Path]:
        deadline = time.monotonic() + self.cfg.wait_timeout
        while time.monotonic() < deadline:
            files = list_images(self.folder)
            if files:
                return files
            time.sleep(POLL_S)
        raise DatasetError(f"{self.folder}: no image appeared within wait_timeout={self.cfg.wait_timeout} s")

    def _read_complete(self, path: Path) -> Frame:
        """Decode ``path``, retrying while it is still being written (until ``wait_timeout``)."""
        deadline = time.monotonic() + self.cfg.wait_timeout
        while True:
            try:
                return Frame(index=0, timestamp=0.0, image=read_rgb(path), intrinsics=self._intr, name=path.name)
            except DatasetError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(POLL_S)

    def _stream(self, start: int, stride: int) -> Iterator[Frame]:
        seen: set[str] = set()
        pending: list[Path] = []
        last: Optional[list] = None  # natural sort key of the last image taken
        idx, prev_t = 0, -np.inf
        idle_since = time.monotonic()
        while True:
            if not pending:
                new = [p for p in list_images(self.folder) if p.name not in seen]
                late = [p for p in new if last is not None and natural_key(p.name) < last]
                for p in late:
                    log.warning("%s: %s appeared after later images were read; skipped", self.folder, p.name)
                    seen.add(p.name)
                pending = [p for p in new if p not in late]
                if not pending:
                    if time.monotonic() - idle_since > self.cfg.wait_timeout:
                        log.info("%s: no new image for %.3g s; the sequence ends after %d images", self.folder,
                                 self.cfg.wait_timeout, idx)
                        return
                    time.sleep(POLL_S)
                    continue
            path = pending.pop(0)
            seen.add(path.name)
            last = natural_key(path.name)
            if idx >= start and (idx - start) % stride == 0:
                frame = self._read_complete(path)
                t = _stem_time(path) if self.cfg.timestamps == "filename" else idx / self.cfg.fps
                if t <= prev_t:
                    raise DatasetError(f"{path}: timestamp {t!r} does not increase (previous image: {prev_t!r})")
                prev_t = t
                frame.index, frame.timestamp = idx, t
                if self._gt is not None:
                    j = int(associate_nearest(np.array([t]), self._gt[0], self.cfg.gt_max_diff)[0])
                    frame.gt_pose = None if j < 0 else torch.from_numpy(self._gt[1][j].copy())
                yield frame
            idx += 1
            idle_since = time.monotonic()


def detect(path: Path):  # type: ignore[no-untyped-def]
    """A folder with images directly inside; numeric names that look like times (TUM/EuRoC style, above 1e8)
    become the timestamps."""
    from pvslam_core.datasets.detect import DatasetMatch

    if not path.is_dir():
        return None
    files = list_images(path)
    if not files:
        return None
    options: dict = {"path": str(path)}
    try:
        ts = timestamps_from_names(files)
        if len(files) > 1 and ts[0] > 1e8:
            options["timestamps"] = "filename"
    except DatasetError:
        pass
    return DatasetMatch(0.5, options, f"folder of {len(files)} images", guessed=("timestamps",))


def make_reader(config: ImagesConfig, context=None) -> ImagesReader:  # type: ignore[no-untyped-def]
    return ImagesReader(config)
