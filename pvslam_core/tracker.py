"""Streaming API: feed frames one at a time (a camera loop, a robot's callback) and get each pose back.

    from pvslam_core.api import Tracker

    with Tracker(intrinsics=[500, 500, 319.5, 239.5], run_dir="runs/live") as tracker:
        for image, t in camera:                       # numpy HxWx3 uint8 RGB (bgr=True for OpenCV's order)
            pose, result = tracker.track(image, t)    # pose: float64 [7] T_wc [tx ty tz qx qy qz qw]
    run = tracker.result                              # the RunResult: final poses after the global BA, metrics

It is the same pipeline as ``pvslam run`` (:class:`~pvslam_core.pipeline.Pipeline` ``start`` / ``step`` /
``finish``) with a dataset that only describes the fed frames.  The pose returned for a frame is the estimate at
the time it was processed (placeholders until the map initialises: ``result.initialized``); later optimisation
(window BA, loop closure, the final BA) refines it, and :meth:`Tracker.close` returns every final pose.  Frames go
through the readers' transform (undistortion, the processing size: ``resize`` or at most ``max_pixels`` of area, a
centre crop to a multiple of the BA downsampling), so the intrinsics are those of the images as given.  The
config's ``[dataset]`` table is not used; the run directory's config.json records ``dataset.plugin = "none"``
(frames fed by the caller).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, NamedTuple, Optional, Sequence, Union

import numpy as np
import torch

from .config import DISABLED, Component, ResolvedConfig, load_config
from .datasets.base import MAX_PIXELS
from .interfaces import DatasetReader
from .types import Frame, FrameResult, Intrinsics, RunResult, SequenceInfo

LOG = logging.getLogger("pvslam")

IntrinsicsLike = Union[Intrinsics, Sequence[float], str, Path]


class TrackedFrame(NamedTuple):
    pose: torch.Tensor  # float64 [7] T_wc of the frame, as estimated when it was processed
    result: FrameResult  # the mapper's result (keyframe id, initialized, failed, message, ...)


class FedFrames(DatasetReader):
    """The dataset of a :class:`Tracker`: it describes the frames the caller feeds and cannot be iterated."""

    def __init__(self, info: SequenceInfo):
        self._info = info

    def info(self) -> SequenceInfo:
        return self._info

    def __iter__(self):
        raise TypeError("the frames of a Tracker are fed through Tracker.track(); there is nothing to iterate")


def _chw(image: Any, bgr: bool) -> torch.Tensor:
    """numpy ``[H, W, 3]`` / ``[H, W]`` uint8 or torch ``uint8 [3, H, W]`` -> ``uint8 [3, H, W]`` RGB."""
    if isinstance(image, torch.Tensor):
        if image.dtype != torch.uint8 or image.ndim != 3 or image.shape[0] != 3:
            raise ValueError(f"a tensor image must be uint8 [3, H, W] RGB, got {image.dtype} {tuple(image.shape)}")
        return image.cpu()
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise ValueError(f"images must be uint8, got {arr.dtype}")
    if arr.ndim == 2:
        return torch.from_numpy(np.repeat(arr[None], 3, axis=0))
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ValueError(f"expected an image [H, W, 3] (or [H, W], [H, W, 4]), got shape {arr.shape}")
    order = [2, 1, 0] if bgr else [0, 1, 2]
    return torch.from_numpy(np.ascontiguousarray(arr[:, :, order].transpose(2, 0, 1)))


class Tracker:
    """Track frames as they come; see the module doc.

    ``intrinsics``: an :class:`Intrinsics` for the images' size, ``[fx, fy, cx, cy, (k1, k2, p1, p2, (k3))]``, or a
    calibration file (values, ORB-SLAM or OpenCV YAML).  ``config``: as :func:`pvslam_core.api.run_config` takes it
    (None: the default pipeline).  ``run_dir``: None (nothing written), a folder, or True (a new run directory under
    ``run.output_dir``).  ``observer``: a :class:`~pvslam_core.observer.RunObserver` (e.g. the rerun viewer).
    """

    def __init__(self, intrinsics: IntrinsicsLike, config: Any = None, overrides=None,
                 run_dir: Union[None, bool, str, Path] = None, registry=None, observer=None, bgr: bool = False,
                 resize: Optional[tuple[int, int]] = None, undistort: bool = True, name: str = "tracker",
                 max_pixels: Optional[int] = MAX_PIXELS):
        from .registry import get_registry

        self.registry = registry or get_registry()
        resolved = config if isinstance(config, ResolvedConfig) else load_config(config, overrides, self.registry)
        pcfg = resolved.pipeline.model_copy(deep=True)
        pcfg.dataset = Component(plugin=DISABLED)  # frames come from track()
        self.config = ResolvedConfig(pcfg, {**resolved.models, "dataset": None}, resolved.source)
        self.intrinsics_spec = intrinsics
        self.bgr, self.resize, self.undistort, self.name = bgr, resize, undistort, name
        self.max_pixels = max_pixels
        self.observer = observer
        from .config import _normalise_overrides

        self.overrides = _normalise_overrides(overrides) if not isinstance(config, ResolvedConfig) else {}
        if run_dir is True:
            from .rundir import make_run_dir

            run_dir = make_run_dir(pcfg.run.output_dir, pcfg.run.name)
        self.run_dir: Optional[Path] = Path(run_dir) if run_dir not in (None, False) else None
        self.pipeline = None
        self.result: Optional[RunResult] = None
        self._log = None
        self._n = 0
        self._t0: Optional[float] = None
        self._last_t = -float("inf")

    # ---------------------------------------------------------------------------------------------- setup --
    def _intrinsics(self, width: int, height: int) -> Intrinsics:
        spec = self.intrinsics_spec
        if isinstance(spec, Intrinsics):
            if (spec.width, spec.height) != (width, height):
                raise ValueError(f"the intrinsics are for {spec.width}x{spec.height} images but the first image is "
                                 f"{width}x{height}")
            return spec
        from .datasets.calib import calibration_from_option

        return calibration_from_option(spec if isinstance(spec, (str, Path)) else list(spec), width, height,
                                       owner="Tracker")

    def _start(self, width: int, height: int) -> None:
        from .datasets.base import ReaderOptions, compute_geometry
        from .pipeline import Pipeline
        from .rundir import RunLog, init_run_dir

        pcfg = self.config.pipeline
        opts = ReaderOptions(resize=self.resize, max_pixels=self.max_pixels, crop_multiple=pcfg.graph.ba_downsample,
                             undistort=self.undistort)
        self.geometry = compute_geometry(self._intrinsics(width, height), opts)
        info = SequenceInfo(name=self.name, num_frames=None, intrinsics=self.geometry.out,
                            input_intrinsics=self.geometry.input_if_other,
                            source="frames fed through the streaming API (Tracker)")
        if self.run_dir is not None:
            init_run_dir(self.run_dir, self.config, self.registry, self.overrides)
            self._log = RunLog(self.run_dir, pcfg.run.log_level).__enter__()
        try:
            self.pipeline = Pipeline(self.config, self.run_dir, self.registry, dataset=FedFrames(info),
                                     observer=self.observer)
            if self.pipeline.notes and self.run_dir is not None:
                init_run_dir(self.run_dir, self.pipeline.cfg, self.registry, self.overrides)
            self.pipeline.start()
        except BaseException:
            self._close_log()
            raise

    def _close_log(self) -> None:
        if self._log is not None:
            self._log.__exit__(None, None, None)
            self._log = None

    # ---------------------------------------------------------------------------------------------- frames --
    def track(self, image: Any, timestamp: Optional[float] = None) -> TrackedFrame:
        """Process one image (numpy ``[H, W, 3]`` uint8 RGB, or BGR with ``bgr=True``; or a ``uint8 [3, H, W]``
        tensor); ``timestamp`` in seconds, increasing (None: the wall clock since the first frame)."""
        if self.result is not None:
            raise RuntimeError("this Tracker is closed")
        img = _chw(image, self.bgr)
        h, w = int(img.shape[1]), int(img.shape[2])
        if self.pipeline is None:
            self._start(w, h)
        raw = self.geometry.raw
        if (w, h) != (raw.width, raw.height):
            raise ValueError(f"frame {self._n}: image is {w}x{h} but the first image was {raw.width}x{raw.height}")
        now = time.monotonic()
        self._t0 = now if self._t0 is None else self._t0
        t = float(timestamp) if timestamp is not None else now - self._t0
        if not t > self._last_t:
            raise ValueError(f"frame {self._n}: timestamp {t} does not increase (previous {self._last_t})")
        self._last_t = t
        from .datasets.base import transform_frame

        frame = transform_frame(Frame(index=self._n, timestamp=t, image=img, intrinsics=raw, name=f"frame{self._n}"),
                                self.geometry, self._n)
        result = self.pipeline.step(frame)
        self._n += 1
        return TrackedFrame(result.pose, result)

    def close(self) -> RunResult:
        """Final optimisation, outputs and evaluation; returns the :class:`RunResult` (also in ``.result``)."""
        if self.result is not None:
            return self.result
        if self.pipeline is None:
            raise RuntimeError("no frame was tracked")
        try:
            self.result = self.pipeline.finish()
        finally:
            self._close_log()
        return self.result

    def __enter__(self) -> "Tracker":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc is None:
            if self.pipeline is not None:
                self.close()
            return False
        if self.pipeline is not None and self.pipeline.mapper is not None:
            self.pipeline.abort(exc)  # keep the trajectory so far and a partial metrics.json
        self._close_log()
        return False
