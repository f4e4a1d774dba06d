"""The common base of every dataset reader: frame selection, undistortion, resizing and cropping.

A concrete reader implements a handful of ``_raw_*`` methods that describe the sequence at its native
resolution; :class:`BaseReader` turns them into the :class:`~pvslam_core.interfaces.DatasetReader` interface:

* frame selection ``range(start, end, stride)`` over the raw frames (output ``Frame.index`` counts 0..N-1);
* optional undistortion with the calibration's distortion coefficients.  The undistorted image keeps the
  camera matrix ``K`` (the DROID-SLAM / ``cv2.undistort`` convention), so only the distortion is dropped from the
  intrinsics; the remap tables come from ``cv2.initUndistortRectifyMap`` and are computed once;
* a resize to ``resize = (width, height)`` or, without one, to at most ``max_pixels`` of area, aspect kept (never
  enlarged): the work and the keyframe rate follow the processing size, not the camera's pixel count (images: area
  when shrinking, linear when enlarging; depth, panoptic ids and dynamic masks: exact nearest neighbour) with
  ``Intrinsics.scaled`` (pixel centres at integers);
* a centre crop to multiples of ``crop_multiple`` with ``Intrinsics.cropped``.

Sources whose length is not known up front (a camera, a folder that is still being written) return None from
``_raw_count`` and yield their frames from ``_stream``; ``SequenceInfo.num_frames`` is then None and ``len()``
raises TypeError.  A reader that must decode sequentially (a video: a container's frame count is only a claim)
sets ``sequential = True`` and iterates through ``_stream`` too, so a wrong count ends the run gracefully.

The same geometric transform is applied to the image, the ground-truth depth, panoptic ids and dynamic mask,
and to the intrinsics, so a 3D point projects onto the same image content before and after.
"""
from __future__ import annotations

import math
from abc import abstractmethod
from dataclasses import dataclass, replace
from typing import Iterator, Optional

import numpy as np
import torch
from pydantic import Field, field_validator, model_validator

from ..config_base import PluginConfig
from ..evaluation.loops import pair_array
from ..interfaces import DatasetReader
from ..types import Category, Frame, Intrinsics, PanopticSegmentation, SequenceInfo


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or inconsistent; the message names the file and the problem."""


# the processing area of a larger input (pixels): DROID-SLAM's 384 x 512, chosen on KITTI 00 (docs/decisions.md:
# dataset.max_pixels)
MAX_PIXELS = 384 * 512
MIN_PIXELS = 64 * 64  # a smaller max_pixels leaves too few BA pixels to track anything


class ReaderOptions(PluginConfig):
    """Options every reader config shares (subclass it and add the dataset's own fields)."""

    stride: int = Field(1, ge=1, description="use every stride-th raw frame")
    start: int = Field(0, ge=0, description="first raw frame")
    end: Optional[int] = Field(None, description="exclusive raw end frame; None = to the end")
    resize: Optional[tuple[int, int]] = Field(None, description="(width, height) to resize to before cropping")
    max_pixels: Optional[int] = Field(
        MAX_PIXELS, description="without resize, a larger input is shrunk to this area (pixels, aspect kept) so the "
        "work and keyframe rate do not grow with the camera's pixel count; null: the native size")
    crop_multiple: int = Field(8, ge=1, description="centre-crop so width and height are multiples of this (1 = off)")
    undistort: bool = Field(True, description="undistort with the calibration's distortion coefficients")

    @field_validator("resize")
    @classmethod
    def _positive_size(cls, v: Optional[tuple[int, int]]) -> Optional[tuple[int, int]]:
        if v is not None and (v[0] <= 0 or v[1] <= 0):
            raise ValueError(f"resize must be a positive (width, height), got {v}")
        return v

    @field_validator("max_pixels")
    @classmethod
    def _sensible_area(cls, v: Optional[int]) -> Optional[int]:
        if v is not None and v < MIN_PIXELS:
            raise ValueError(f"max_pixels must be at least {MIN_PIXELS} (64x64 pixels), or null for the native "
                             "size")
        return v

    @model_validator(mode="after")
    def _end_after_start(self) -> "ReaderOptions":
        if self.end is not None and self.end <= self.start:
            raise ValueError(f"end ({self.end}) must be greater than start ({self.start})")
        return self


@dataclass(frozen=True)
class ReaderGeometry:
    """The image transform of a reader, fixed once the raw intrinsics are known."""

    raw: Intrinsics  # native, with distortion
    undist_maps: Optional[tuple[np.ndarray, np.ndarray]]  # cv2.remap tables, or None
    resize: Optional[tuple[int, int]]  # (w, h) or None
    crop: Optional[tuple[int, int, int, int]]  # left, top, width, height (in the resized image), or None
    out: Intrinsics  # of the yielded frames

    @property
    def input(self) -> Intrinsics:
        """The input's own camera: native size, without the distortion when the frames are undistorted."""
        return replace(self.raw, dist=()) if self.undist_maps is not None or not self.raw.has_distortion else self.raw

    @property
    def input_if_other(self) -> Optional[Intrinsics]:
        """:attr:`input` when the yielded frames are resized or cropped from it (``SequenceInfo.input_intrinsics``),
        else None."""
        return self.input if (self.resize or self.crop) else None


def processing_size(width: int, height: int, options: ReaderOptions) -> tuple[int, int]:
    """``(width, height)`` to resize a ``width x height`` image to, before the crop: ``resize`` when set, else the
    largest size of the same aspect within ``max_pixels`` (never larger than the input)."""
    if options.resize is not None:
        return int(options.resize[0]), int(options.resize[1])
    if options.max_pixels is None or width * height <= options.max_pixels:
        return width, height
    s = math.sqrt(options.max_pixels / (width * height))
    return max(1, int(width * s)), max(1, int(height * s))


def compute_geometry(raw: Intrinsics, options: ReaderOptions) -> ReaderGeometry:
    """Intrinsics after undistort -> resize -> crop, plus what is needed to apply the same to pixels."""
    import cv2

    k = raw
    maps = None
    if options.undistort and raw.has_distortion:
        kmat = k.matrix().numpy()
        maps = cv2.initUndistortRectifyMap(
            kmat, np.asarray(raw.dist, dtype=np.float64), None, kmat, (raw.width, raw.height), cv2.CV_32FC1
        )
        k = replace(k, dist=())
    elif not raw.has_distortion:
        k = replace(k, dist=())  # no coefficients, or all zero
    size = None
    w, h = processing_size(k.width, k.height, options)
    if (w, h) != (k.width, k.height):
        size = (w, h)
        k = replace(k.scaled(w / k.width, h / k.height), width=w, height=h)
    crop = None
    m = options.crop_multiple
    if m > 1:
        cw, ch = (k.width // m) * m, (k.height // m) * m
        if cw == 0 or ch == 0:
            raise DatasetError(
                f"image of {k.width}x{k.height} pixels is smaller than crop_multiple={m}; lower crop_multiple"
            )
        if (cw, ch) != (k.width, k.height):
            crop = ((k.width - cw) // 2, (k.height - ch) // 2, cw, ch)
            k = k.cropped(*crop)
    return ReaderGeometry(raw=raw, undist_maps=maps, resize=size, crop=crop, out=k)


def _apply(arr: np.ndarray, geo: ReaderGeometry, nearest: bool) -> np.ndarray:
    """Apply undistort -> resize -> crop to an ``[H, W]`` or ``[H, W, C]`` array."""
    import cv2

    if geo.undist_maps is not None:
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        arr = cv2.remap(arr, geo.undist_maps[0], geo.undist_maps[1], interp, borderMode=cv2.BORDER_CONSTANT)
    if geo.resize is not None:
        if nearest:
            interp = cv2.INTER_NEAREST_EXACT
        else:
            shrink = geo.resize[0] < arr.shape[1] and geo.resize[1] < arr.shape[0]
            interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        arr = cv2.resize(arr, geo.resize, interpolation=interp)
    if geo.crop is not None:
        left, top, w, h = geo.crop
        arr = arr[top : top + h, left : left + w]
    return np.ascontiguousarray(arr)


def _apply_int(arr: np.ndarray, geo: ReaderGeometry) -> np.ndarray:
    """Nearest-neighbour transform of an integer label map (OpenCV cannot remap int64)."""
    if arr.dtype in (np.uint8, np.uint16, np.int16, np.int32, np.float32):
        return _apply(arr, geo, nearest=True)
    lo, hi = (int(arr.min()), int(arr.max())) if arr.size else (0, 0)
    if lo >= np.iinfo(np.int32).min and hi <= np.iinfo(np.int32).max:
        return _apply(arr.astype(np.int32), geo, nearest=True).astype(arr.dtype)
    # very large ids: transform a dense index map instead of the values
    values, inverse = np.unique(arr, return_inverse=True)
    idx = _apply(inverse.reshape(arr.shape).astype(np.int32), geo, nearest=True)
    return values[idx]


def _apply_planes(chw: np.ndarray, geo: ReaderGeometry) -> np.ndarray:
    """:func:`_apply` per plane of a ``[C, H, W]`` image (no HWC <-> CHW transposes of full frames); a gray source
    replicated to three equal planes (KITTI, EuRoC) is transformed once: the same pixels at a third of the cost."""
    if len(chw) == 3 and np.array_equal(chw[0], chw[1]) and np.array_equal(chw[1], chw[2]):
        one = _apply(np.ascontiguousarray(chw[0]), geo, nearest=False)
        return np.repeat(one[None], 3, axis=0)
    return np.stack([_apply(np.ascontiguousarray(c), geo, nearest=False) for c in chw])


def transform_frame(frame: Frame, geo: ReaderGeometry, index: int) -> Frame:
    """The frame as yielded: pixels and ground-truth maps transformed, intrinsics replaced, index renumbered."""
    raw = geo.raw
    if frame.height != raw.height or frame.width != raw.width:
        raise DatasetError(
            f"frame {frame.name or frame.index}: image is {frame.width}x{frame.height} pixels but the "
            f"calibration says {raw.width}x{raw.height}"
        )
    for what, arr in (("depth", frame.gt_depth), ("dynamic mask", frame.gt_dynamic),
                      ("panoptic", None if frame.gt_panoptic is None else frame.gt_panoptic.ids)):
        if arr is not None and tuple(arr.shape[-2:]) != (frame.height, frame.width):
            raise DatasetError(
                f"frame {frame.name or frame.index}: {what} map is {arr.shape[-1]}x{arr.shape[-2]} pixels but the "
                f"image is {frame.width}x{frame.height}"
            )
    identity = geo.undist_maps is None and geo.resize is None and geo.crop is None
    if identity:
        return replace(frame, index=index, intrinsics=geo.out)
    img = _apply_planes(frame.image.numpy(), geo)
    out = replace(frame, index=index, intrinsics=geo.out, image=torch.from_numpy(img))
    if frame.gt_depth is not None:
        d = _apply(frame.gt_depth.numpy().astype(np.float32), geo, nearest=True)
        out.gt_depth = torch.from_numpy(d)
    if frame.gt_dynamic is not None:
        m = _apply(frame.gt_dynamic.numpy().astype(np.uint8), geo, nearest=True)
        out.gt_dynamic = torch.from_numpy(m.astype(bool))
    if frame.gt_panoptic is not None:
        ids = torch.from_numpy(_apply_int(frame.gt_panoptic.ids.numpy(), geo)).to(torch.int64)
        present = set(torch.unique(ids).tolist())
        segs = [s for s in frame.gt_panoptic.segments if s.id in present]
        out.gt_panoptic = PanopticSegmentation(ids=ids, segments=segs, features=None)
    return out


class BaseReader(DatasetReader):
    """Frame selection and geometric preprocessing shared by every reader.

    Subclasses call ``super().__init__(options)`` and implement ``_raw_count``, ``_raw_intrinsics``, ``_load``
    and ``_sequence_name``; ``_categories``, ``_loop_pairs`` and ``_has_gt`` are optional.  Sources of unknown
    length (``_raw_count`` None) and ``sequential`` readers implement ``_stream`` instead of (or besides) ``_load``.
    """

    sequential = False  # iterate through _stream (sequential decoding) even when the count is known

    def __init__(self, options: ReaderOptions):
        self.options = options
        self._geo: Optional[ReaderGeometry] = None
        self._range: Optional[range] = None
        self._info: Optional[SequenceInfo] = None

    # ---- to implement ------------------------------------------------------------------------------------
    @abstractmethod
    def _raw_count(self) -> Optional[int]:
        """Number of raw frames, or None when it is not known until the source ends (a camera, a growing folder)."""

    @abstractmethod
    def _raw_intrinsics(self) -> Intrinsics:
        """Native-resolution intrinsics, with distortion."""

    @abstractmethod
    def _load(self, raw_index: int) -> Frame:
        """Native-resolution frame ``raw_index`` (``Frame.index = raw_index``), with any ground truth."""

    @abstractmethod
    def _sequence_name(self) -> str:
        """A short name for messages and output folders."""

    def _categories(self) -> list[Category]:
        return []

    def _loop_pairs(self) -> Optional[np.ndarray | list[tuple[int, int]]]:
        """Ground-truth revisit pairs in raw indices (``[M, 2]`` rows), if known."""
        return None

    def _stream(self, start: int, stride: int) -> Iterator[Frame]:
        """Native-resolution frames ``start, start + stride, ...`` (``Frame.index`` = raw index) until the source
        ends; needed when ``_raw_count`` is None or ``sequential`` is set."""
        raise NotImplementedError(f"{type(self).__name__} does not stream")

    def _has_gt(self) -> tuple[bool, bool, bool]:
        """(pose, depth, panoptic); by default found out by loading the first selected frame (none for streams)."""
        if self._count() is None:
            return (False, False, False)
        f = self._load(self.frame_range()[0])
        return (f.gt_pose is not None, f.gt_depth is not None, f.gt_panoptic is not None)

    def _source(self) -> str:
        """Where the data comes from (a path), for messages."""
        return str(getattr(self.options, "path", "") or "")

    # ---- provided ------------------------------------------------------------------------------------------
    def _count(self) -> Optional[int]:
        if not hasattr(self, "_count_cache"):
            n = self._raw_count()
            self._count_cache = None if n is None else int(n)
        return self._count_cache

    def frame_range(self) -> range:
        """The raw indices yielded, in order (TypeError for a source of unknown length)."""
        if self._range is None:
            n = self._count()
            where = self._source() or self._sequence_name()
            if n is None:
                raise TypeError(f"{where}: the number of frames is not known until the source ends")
            if n <= 0:
                raise DatasetError(f"{where}: the sequence has no frames")
            o = self.options
            end = n if o.end is None else o.end
            if o.start >= n:
                raise DatasetError(f"{where}: start={o.start} is out of range: the sequence has {n} frames")
            if end > n:
                raise DatasetError(f"{where}: end={end} is out of range: the sequence has {n} frames")
            self._range = range(o.start, end, o.stride)
        return self._range

    def geometry(self) -> ReaderGeometry:
        if self._geo is None:
            self._geo = compute_geometry(self._raw_intrinsics(), self.options)
        return self._geo

    def _output_pairs(self, raw: np.ndarray) -> np.ndarray:
        """Revisit pairs ``[M, 2]`` in raw indices -> the distinct pairs of distinct output indices (first
        occurrences, in order); each index goes to the selected frame nearest to it, pairs with an index outside
        start..end are dropped."""
        if self._count() is None or not len(raw):
            return np.zeros((0, 2), dtype=np.int64)
        r = self.frame_range()
        k = raw - r.start
        if r.step != 1:
            k = np.rint(k / r.step).astype(np.int64)  # the nearest; half to even
        np.clip(k, 0, len(r) - 1, out=k)
        k = k[((raw >= r.start) & (raw < r.stop)).all(1) & (k[:, 0] != k[:, 1])]
        _, first = np.unique(k[:, 0] * len(r) + k[:, 1], return_index=True)  # one key per pair
        return k[np.sort(first)]

    def info(self) -> SequenceInfo:
        if self._info is None:
            num = None if self._count() is None else len(self.frame_range())
            pose, depth, pan = self._has_gt()
            loops = self._loop_pairs()
            mapped = None if loops is None else self._output_pairs(pair_array(loops))
            geo = self.geometry()
            self._info = SequenceInfo(
                name=self._sequence_name(),
                num_frames=num,
                intrinsics=geo.out,
                input_intrinsics=geo.input_if_other,
                categories=tuple(self._categories()),
                has_gt_pose=pose,
                has_gt_depth=depth,
                has_gt_panoptic=pan,
                loop_pairs=mapped,
                source=self._source(),
            )
        return self._info

    def __len__(self) -> int:
        return len(self.frame_range())

    def __getitem__(self, index: int) -> Frame:
        r = self.frame_range()
        if index < 0:
            index += len(r)
        if not 0 <= index < len(r):
            raise IndexError(f"frame index {index} out of range for {len(r)} frames")
        return transform_frame(self._load(r[index]), self.geometry(), index)

    def __iter__(self) -> Iterator[Frame]:
        geo = self.geometry()
        if self.sequential or self._count() is None:
            yield from self._iter_stream(geo)
            return
        for i, raw in enumerate(self.frame_range()):
            yield transform_frame(self._load(raw), geo, i)

    def _iter_stream(self, geo: ReaderGeometry) -> Iterator[Frame]:
        o = self.options
        i = 0
        for frame in self._stream(o.start, o.stride):
            if o.end is not None and frame.index >= o.end:
                break
            yield transform_frame(frame, geo, i)
            i += 1
        if i == 0:
            where = self._source() or self._sequence_name()
            raise DatasetError(f"{where}: the sequence has no frames" + (f" from start={o.start}" if o.start else ""))


class ImageFileReader(BaseReader):
    """A reader whose raw frames are image files with timestamps and optional ground-truth poses.

    Subclasses set ``self.files`` (paths), ``self.timestamps`` (float64 seconds, one per file), ``self.poses``
    (float64 ``[N, 7]`` T_wc or None) and ``self._intr`` before calling ``BaseReader.__init__``, and implement
    ``_sequence_name`` and ``_source``.
    """

    files: list
    timestamps: np.ndarray
    poses: Optional[np.ndarray] = None
    _intr: Intrinsics

    def _raw_count(self) -> int:
        return len(self.files)

    def _raw_intrinsics(self) -> Intrinsics:
        return self._intr

    def _has_gt(self) -> tuple[bool, bool, bool]:
        return (self.poses is not None, False, False)

    def _load(self, raw_index: int) -> Frame:
        from .io import pose_at, read_rgb

        path = self.files[raw_index]
        return Frame(index=raw_index, timestamp=float(self.timestamps[raw_index]), image=read_rgb(path),
                     intrinsics=self._intr, gt_pose=pose_at(self.poses, raw_index), name=path.name)
