"""A video file read with ``cv2.VideoCapture``.

The frame count is read from the container (``CAP_PROP_FRAME_COUNT``) and verified by one pass of ``grab()``
over the file when the reader is built (containers often round or omit it); that pass also records each
frame's presentation time (``CAP_PROP_POS_MSEC``).  Frames are then decoded sequentially; a backwards jump
re-opens the file, a forwards jump grabs through the skipped frames (exact for every codec, unlike seeking).

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "video"
    path = "/data/my_run/clip.mp4"
    calib = "/data/my_run/calib.txt"
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

import numpy as np

from pvslam_core.datasets.base import BaseReader, DatasetError
from pvslam_core.datasets.calib import calibration_from_option
from pvslam_core.datasets.io import to_chw_rgb
from pvslam_core.types import Frame, Intrinsics

from .config import VideoConfig

log = logging.getLogger(__name__)


class VideoReader(BaseReader):
    def __init__(self, options: VideoConfig):
        super().__init__(options)
        self.cfg = options
        self.file = Path(options.path).expanduser()
        if not self.file.is_file():
            raise DatasetError(f"{self.file}: video file not found")
        cap = self._open()
        import cv2

        claimed = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        container_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        msec: list[float] = []
        while cap.grab():
            msec.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
        cap.release()
        n = len(msec)
        if n == 0:
            raise DatasetError(f"{self.file}: no decodable frames (unsupported codec or corrupt file)")
        if claimed != n:
            log.warning("%s: container says %d frames, %d could be decoded; using %d", self.file, claimed, n, n)
        fps = options.fps or container_fps
        ts = np.asarray(msec, dtype=np.float64) * 1e-3
        if options.timestamps == "fps" or not np.all(np.diff(ts) > 0):
            if not fps or fps <= 0:
                raise DatasetError(f"{self.file}: the container gives no usable frame times or fps; set 'fps'")
            if options.timestamps == "msec":
                log.warning("%s: container frame times are not increasing; using index / %.6g fps", self.file, fps)
            ts = np.arange(n, dtype=np.float64) / fps
        self.ts = ts
        self._n = n
        self._intr = calibration_from_option(
            options.calib, w, h, search=(self.file.parent,), owner=f"video reader ({self.file})"
        )
        self._cap: Optional[Any] = None
        self._next = 0  # index of the frame the open capture returns next

    def _open(self) -> Any:
        import cv2

        cap = cv2.VideoCapture(str(self.file))
        if not cap.isOpened():
            raise DatasetError(f"{self.file}: OpenCV cannot open the video (unsupported container or codec)")
        return cap

    def _raw_count(self) -> int:
        return self._n

    def _raw_intrinsics(self) -> Intrinsics:
        return self._intr

    def _sequence_name(self) -> str:
        return f"video_{self.file.stem}"

    def _source(self) -> str:
        return str(self.file)

    def _has_gt(self) -> tuple[bool, bool, bool]:
        return (False, False, False)

    def _load(self, raw_index: int) -> Frame:
        if self._cap is None or raw_index < self._next:
            if self._cap is not None:
                self._cap.release()
            self._cap, self._next = self._open(), 0
        while self._next < raw_index:
            if not self._cap.grab():
                raise DatasetError(f"{self.file}: frame {self._next} could not be decoded")
            self._next += 1
        ok, bgr = self._cap.read()
        if not ok or bgr is None:
            raise DatasetError(f"{self.file}: frame {raw_index} could not be decoded")
        self._next += 1
        return Frame(
            index=raw_index,
            timestamp=float(self.ts[raw_index]),
            image=to_chw_rgb(bgr, f"{self.file}#{raw_index}"),
            intrinsics=self._intr,
            name=f"{self.file.name}#{raw_index}",
        )

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def make_reader(config: VideoConfig, context=None) -> VideoReader:  # type: ignore[no-untyped-def]
    return VideoReader(config)
