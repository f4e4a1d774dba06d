"""A video file, or a live camera, read with ``cv2.VideoCapture``.

Nothing is decoded when the reader is built: the frame count is the container's (``CAP_PROP_FRAME_COUNT``), and
the frames are decoded sequentially as the run iterates (``sequential``).  Containers often round or omit the
count, so it is only a claim: iteration goes on until decoding stops, and a count that turns out wrong is logged
at the end instead of failing the run.  A container without a count, and a camera, have an unknown length
(``SequenceInfo.num_frames`` None): the run ends when the source does, at ``run.max_frames``, or on Ctrl-C.

Timestamps: ``msec`` takes each frame's container time (``CAP_PROP_POS_MSEC``; a camera's: the wall clock since
its first frame); a time that does not increase falls back to ``index / fps`` from then on.  ``fps``: index / fps.
Random access (``reader[i]``) re-opens the file for a backwards jump and grabs through skipped frames (exact for
every codec, unlike seeking).

``path`` is a file, or a camera index (``"0"``: the first camera, when no file of that name exists).

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "video"
    path = "/data/my_run/clip.mp4"
    calib = "/data/my_run/calib.txt"
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Iterator, Optional

from pvslam_core.datasets.base import BaseReader, DatasetError
from pvslam_core.datasets.calib import calibration_from_option
from pvslam_core.datasets.io import to_chw_rgb
from pvslam_core.types import Frame, Intrinsics

from .config import VideoConfig

log = logging.getLogger(__name__)


def camera_index(path: str) -> Optional[int]:
    """``path`` as a camera index ("0", "1", ...) when it is one and no such file exists, else None."""
    s = str(path).strip()
    if s.isdigit() and not Path(s).exists():
        return int(s)
    return None


class VideoReader(BaseReader):
    sequential = True

    def __init__(self, options: VideoConfig):
        import cv2

        super().__init__(options)
        self.cfg = options
        self.camera = camera_index(options.path)
        self.file = Path(options.path).expanduser() if self.camera is None else None
        if self.file is not None and not self.file.is_file():
            raise DatasetError(f"{self.file}: video file not found")
        self._label = str(self.file) if self.file is not None else f"camera {self.camera}"
        cap = self._open()
        self._first = None  # a camera's first frame, read to learn its size, is the first frame yielded
        try:
            claimed = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)) if self.file is not None else 0
            self.container_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
            w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            if w <= 0 or h <= 0:  # some backends know the size only after a frame: decode exactly one
                ok, bgr = cap.read()
                if not ok or bgr is None:
                    raise DatasetError(f"{self._label}: no decodable frames (unsupported codec or corrupt file)")
                h, w = bgr.shape[:2]
                self._first = (time.monotonic(), bgr) if self.camera is not None else None
        except BaseException:
            cap.release()
            raise
        if self.camera is None:
            cap.release()
        self._live = cap if self.camera is not None else None  # a camera is opened once
        self._cap: Optional[Any] = None  # random-access capture (files)
        self._next = 0  # index of the frame the random-access capture returns next
        self._claimed = claimed if claimed > 0 else None
        self.fps = options.fps or (self.container_fps if self.container_fps > 0 else None)
        if options.timestamps == "fps" and not self.fps:
            raise DatasetError(f"{self._label}: timestamps='fps' but the source gives no frame rate; set 'fps'")
        search = (self.file.parent,) if self.file is not None else ()
        self._intr = calibration_from_option(options.calib, w, h, search=search, owner=f"video reader ({self._label})")
        self._warned_time = False

    def _open(self) -> Any:
        import cv2

        cap = cv2.VideoCapture(str(self.file) if self.file is not None else self.camera)
        if not cap.isOpened():
            what = "the video (unsupported container or codec)" if self.file is not None else "the camera"
            raise DatasetError(f"{self._label}: OpenCV cannot open {what}")
        return cap

    # ---------------------------------------------------------------------------------------- BaseReader --
    def _raw_count(self) -> Optional[int]:
        return None if self.camera is not None else self._claimed

    def _raw_intrinsics(self) -> Intrinsics:
        return self._intr

    def _sequence_name(self) -> str:
        return f"video_{self.file.stem}" if self.file is not None else f"camera_{self.camera}"

    def _source(self) -> str:
        return self._label

    def _has_gt(self) -> tuple[bool, bool, bool]:
        return (False, False, False)

    def _timestamp(self, index: int, msec: float, prev: float) -> float:
        """The frame's time in seconds: the container's when it increases, else ``index / fps`` (warned once)."""
        if self.cfg.timestamps == "fps":
            return index / self.fps
        t = msec * 1e-3
        if math.isfinite(t) and t > prev:
            return t
        if not self.fps:
            raise DatasetError(f"{self._label}: frame {index}: the container's time does not increase and it gives "
                               "no frame rate; set 'fps' (and timestamps = 'fps')")
        if not self._warned_time:
            log.warning("%s: container frame times stop increasing at frame %d; using index / %.6g fps",
                        self._label, index, self.fps)
            self._warned_time = True
        return max(index / self.fps, prev + 1e-6)

    def _frame(self, index: int, bgr, t: float) -> Frame:
        name = f"{self.file.name}#{index}" if self.file is not None else f"camera{self.camera}#{index}"
        return Frame(index=index, timestamp=t, image=to_chw_rgb(bgr, f"{self._label}#{index}"),
                     intrinsics=self._intr, name=name)

    def _stream(self, start: int, stride: int) -> Iterator[Frame]:
        import cv2

        if self.camera is not None:
            yield from self._stream_camera(start, stride)
            return
        cap = self._open()
        idx, prev = 0, -math.inf
        try:
            while cap.grab():
                if idx >= start and (idx - start) % stride == 0:
                    msec = float(cap.get(cv2.CAP_PROP_POS_MSEC))
                    ok, bgr = cap.retrieve()
                    if not ok or bgr is None:
                        log.warning("%s: frame %d could not be decoded; the video ends there", self._label, idx)
                        break
                    prev = self._timestamp(idx, msec, prev)
                    yield self._frame(idx, bgr, prev)
                idx += 1
        finally:
            cap.release()
        if self._claimed is not None and idx != self._claimed:
            log.warning("%s: the container claims %d frames, %d were decoded", self._label, self._claimed, idx)
        if idx == 0:
            raise DatasetError(f"{self._label}: no decodable frames (unsupported codec or corrupt file)")

    def _stream_camera(self, start: int, stride: int) -> Iterator[Frame]:
        cap = self._live if self._live is not None else self._open()
        self._live = None
        t0: Optional[float] = None
        idx, prev = 0, -math.inf
        try:
            while True:
                if self._first is not None:
                    now, bgr = self._first
                    self._first = None
                else:
                    ok, bgr = cap.read()
                    now = time.monotonic()
                    if not ok or bgr is None:
                        break
                t0 = now if t0 is None else t0
                if idx >= start and (idx - start) % stride == 0:
                    # a camera has no container time: the wall clock since its first frame
                    prev = (idx / self.fps) if self.cfg.timestamps == "fps" else max(now - t0, prev + 1e-6)
                    yield self._frame(idx, bgr, prev)
                idx += 1
        finally:
            cap.release()
        log.info("%s: the camera stopped after %d frames", self._label, idx)

    def _load(self, raw_index: int) -> Frame:
        import cv2

        if self.camera is not None:
            raise DatasetError(f"{self._label}: a camera has no random access; iterate over the reader")
        if self._cap is None or raw_index < self._next:
            if self._cap is not None:
                self._cap.release()
            self._cap, self._next = self._open(), 0
        while self._next < raw_index:
            if not self._cap.grab():
                raise DatasetError(f"{self._label}: frame {self._next} could not be decoded")
            self._next += 1
        if not self._cap.grab():
            raise DatasetError(f"{self._label}: frame {raw_index} could not be decoded")
        msec = float(self._cap.get(cv2.CAP_PROP_POS_MSEC))
        ok, bgr = self._cap.retrieve()
        if not ok or bgr is None:
            raise DatasetError(f"{self._label}: frame {raw_index} could not be decoded")
        self._next += 1
        if self.cfg.timestamps == "fps" or (raw_index > 0 and msec <= 0 and self.fps):
            t = raw_index / self.fps
        else:
            t = msec * 1e-3
        return self._frame(raw_index, bgr, t)

    def close(self) -> None:
        for attr in ("_cap", "_live"):
            cap = getattr(self, attr, None)
            if cap is not None:
                cap.release()
                setattr(self, attr, None)

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts", ".mts",
                    ".m2ts", ".3gp", ".ogv", ".mjpeg", ".mjpg", ".h264", ".hevc")


def detect(path: Path):  # type: ignore[no-untyped-def]
    """A video file (by extension: nothing is decoded) or a camera index."""
    from pvslam_core.datasets.detect import DatasetMatch

    if camera_index(str(path)) is not None:
        return DatasetMatch(0.9, {"path": str(path)}, f"camera {path}")
    if path.is_file() and path.suffix.lower() in VIDEO_EXTENSIONS:
        return DatasetMatch(0.9, {"path": str(path)}, f"video file {path.name}")
    return None


def make_reader(config: VideoConfig, context=None) -> VideoReader:  # type: ignore[no-untyped-def]
    return VideoReader(config)
