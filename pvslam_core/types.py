"""Data passed between pvslam components.

Conventions (stated once, used everywhere)
------------------------------------------
* **Pose**: a rigid transform is a float tensor ``[..., 7]`` laid out ``[tx, ty, tz, qx, qy, qz, qw]``
  (Hamilton quaternion, scalar last, unit norm).  Every pose that crosses a module boundary in pvslam is
  **camera-to-world** ``T_wc``: it maps a point from the camera frame into the world frame
  (``X_w = R X_c + t``), so ``t`` is the camera centre in world coordinates.  TUM trajectory files use the
  same layout.  Code that prefers world-to-camera (the dense BA, as DROID-SLAM writes it) inverts on entry and
  exit of that function; evo's wxyz quaternion order is produced in exactly one place
  (``pvslam_core.evaluation.trajectory.to_evo``).
* **Camera frame**: x right, y down, z forward (OpenCV).
* **Images**: ``torch.uint8 [3, H, W]`` RGB, on the CPU as read.  Grayscale sources are replicated to 3 channels.
* **Depth**: z-depth in metres, ``float32 [H, W]``, 0 where invalid.  The SLAM state keeps *inverse* depth
  ("disparity", ``1/z``) at the bundle-adjustment resolution.
* **Intrinsics**: pinhole ``fx, fy, cx, cy`` in pixels of the image they belong to, with OpenCV distortion
  coefficients ``(k1, k2, p1, p2[, k3])``; pixel centres are at integer coordinates.
* **Panoptic**: ``ids`` is ``int64 [H, W]``; 0 is void/unlabelled; every other id has a :class:`Segment`
  with its category.  Ids are opaque positive integers; a VPS head keeps the id of a thing instance stable
  over time.
* **Flow targets**: for an edge ``(i, j)`` of the frame graph, ``target[e, :, y, x]`` is the ``(u, v)``
  pixel position in keyframe ``j`` (at the BA resolution) that pixel ``(x, y)`` of keyframe ``i``
  corresponds to; ``weight[e]`` is the per-coordinate confidence in ``[0, 1]``.
* **Keyframes** have two numbers: a graph *index* (position in the frame graph, ``0..n-1``; it shifts down when an
  older keyframe is removed, and is what the BA's edge lists ``ii``/``jj`` hold) and a stable *id* (assigned once,
  never reused, never shifted).  Plugins key their own state by id (``graph.ids[ii]``) and hear of removals and
  retired edges through :class:`~pvslam_core.interfaces.GraphListener`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional, Sequence

import numpy as np
import torch

POSE_LAYOUT = "[tx, ty, tz, qx, qy, qz, qw], camera-to-world (T_wc)"


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with optional OpenCV distortion, for an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = ()  # OpenCV order (k1, k2, p1, p2[, k3]); empty = no distortion

    def __post_init__(self) -> None:
        import math

        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"{name}={v} is not a finite number")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        # A principal point beyond half an image from the border is a wrong calibration (pixels vs normalised
        # units, swapped values, another resolution), not a shift lens: refuse it here instead of failing later.
        for name, v, size in (("cx", self.cx, self.width), ("cy", self.cy, self.height)):
            if not -0.5 * size <= v <= 1.5 * size:
                raise ValueError(f"{name}={v} lies far outside the {self.width}x{self.height} image "
                                 f"(allowed {-0.5 * size:g}..{1.5 * size:g})")
        if len(self.dist) not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"distortion must have 0, 4, 5, 8, 12 or 14 coefficients, got {len(self.dist)}")
        names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")
        for name, v in zip(names, self.dist):
            if not math.isfinite(v):
                raise ValueError(f"distortion coefficient {name}={v} is not a finite number")

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.dist)

    def vector(self, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu") -> torch.Tensor:
        """``[fx, fy, cx, cy]`` as a tensor."""
        return torch.tensor([self.fx, self.fy, self.cx, self.cy], dtype=dtype, device=device)

    def matrix(self) -> "torch.Tensor":
        """3x3 camera matrix K (float64)."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float64
        )

    def scaled(self, sx: float, sy: Optional[float] = None) -> "Intrinsics":
        """Intrinsics of the image resized by ``(sx, sy)`` (pixel centres at integers: c' = (c + 0.5) s - 0.5)."""
        sy = sx if sy is None else sy
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=int(round(self.width * sx)),
            height=int(round(self.height * sy)),
        )

    def cropped(self, left: int, top: int, width: int, height: int) -> "Intrinsics":
        return replace(self, cx=self.cx - left, cy=self.cy - top, width=width, height=height)


@dataclass(frozen=True)
class Category:
    """A panoptic category: ``isthing`` categories have instances, stuff categories do not."""

    id: int
    name: str
    isthing: bool
    color: tuple[int, int, int] = (128, 128, 128)


@dataclass(frozen=True)
class Segment:
    """One segment of a panoptic id map.  ``movable``: whether its category can move on its own (a car, a person;
    not a building, nor furniture).  Only movable thing segments vote in dynamic masking (PV-SLAM eq. 4); a
    segmenter that knows which of its categories move says so here, the default keeps every thing a candidate."""

    id: int
    category_id: int
    isthing: bool
    score: float = 1.0
    movable: bool = True


@dataclass
class FeaturePyramid:
    """Named multi-scale feature maps of one image (e.g. a segmenter's FPN levels ``p2..p6``), for a VPS head.

    ``maps[name]`` is float ``[C, ceil(H / strides[name]), ceil(W / strides[name])]`` for an ``H x W`` image (padding
    to a size divisibility may add rows/columns at the bottom/right); ``strides[name]`` is its stride in input
    pixels.  Names are the producer's (detectron2 uses ``p2``..``p6``)."""

    maps: dict[str, torch.Tensor]
    strides: dict[str, int]

    def __post_init__(self) -> None:
        if set(self.maps) != set(self.strides):
            raise ValueError(f"FeaturePyramid: levels {sorted(self.maps)} and strides {sorted(self.strides)} differ")

    @property
    def names(self) -> list[str]:
        """Level names, finest (smallest stride) first."""
        return sorted(self.maps, key=lambda n: self.strides[n])


@dataclass
class PanopticSegmentation:
    """Per-pixel segment ids plus one :class:`Segment` per id present (0 = void)."""

    ids: torch.Tensor  # int64 [H, W]
    segments: list[Segment]
    features: Optional[FeaturePyramid] = None  # the segmenter's multi-scale features, for a feature-level VPS head

    def segment(self, sid: int) -> Optional[Segment]:
        for s in self.segments:
            if s.id == sid:
                return s
        return None

    def category_map(self) -> torch.Tensor:
        """int64 [H, W] category id per pixel, -1 for void."""
        lut_ids = torch.tensor([0] + [s.id for s in self.segments], dtype=torch.int64)
        lut_cat = torch.tensor([-1] + [s.category_id for s in self.segments], dtype=torch.int64)
        order = torch.argsort(lut_ids)
        lut_ids, lut_cat = lut_ids[order], lut_cat[order]
        pos = torch.searchsorted(lut_ids, self.ids.reshape(-1)).clamp(max=len(lut_ids) - 1)
        found = lut_ids[pos] == self.ids.reshape(-1)
        out = torch.where(found, lut_cat[pos], torch.full_like(pos, -1))
        return out.reshape(self.ids.shape)


@dataclass
class Frame:
    """One input frame, as every :class:`~pvslam_core.interfaces.DatasetReader` yields it."""

    index: int  # position in the (strided, cropped) input stream, 0-based
    timestamp: float  # seconds
    image: torch.Tensor  # uint8 [3, H, W] RGB
    intrinsics: Intrinsics
    gt_pose: Optional[torch.Tensor] = None  # float64 [7] T_wc
    gt_depth: Optional[torch.Tensor] = None  # float32 [H, W] metres, 0 = invalid
    gt_panoptic: Optional[PanopticSegmentation] = None
    gt_dynamic: Optional[torch.Tensor] = None  # bool [H, W], True where the scene moves independently
    name: str = ""  # source file name or similar, for messages and output file names

    @property
    def height(self) -> int:
        return int(self.image.shape[-2])

    @property
    def width(self) -> int:
        return int(self.image.shape[-1])

    def image_hwc(self):
        """The image as a contiguous numpy ``uint8 [H, W, 3]`` RGB array (for OpenCV)."""
        import numpy as np

        return np.ascontiguousarray(self.image.numpy().transpose(1, 2, 0))  # numpy is ~10x faster than torch here

    def gray(self):
        """numpy ``uint8 [H, W]`` luminance."""
        from .imaging import to_gray

        return to_gray(self.image)


@dataclass
class SequenceInfo:
    """What a reader knows about a sequence before iterating it."""

    name: str
    num_frames: Optional[int]  # None: not known until the source ends (a camera, a folder still being written)
    intrinsics: Intrinsics  # of the frames as yielded (after resize/crop/undistort)
    # the input's own camera (native size; undistorted when the frames are) when the frames were resized or cropped
    input_intrinsics: Optional[Intrinsics] = None
    categories: Sequence[Category] = ()
    has_gt_pose: bool = False
    has_gt_depth: bool = False
    has_gt_panoptic: bool = False
    loop_pairs: Optional[np.ndarray] = None  # int64 [M, 2]: ground-truth revisits (frame indices), if known
    source: str = ""


@dataclass
class TrackResult:
    """What :meth:`Frontend.track` says about a new frame."""

    is_keyframe: bool
    mean_flow: float  # mean optical-flow magnitude to the last keyframe, in BA-resolution pixels
    # Flow from the last keyframe to this frame at the BA resolution, for pose filling of non-keyframes:
    target: Optional[torch.Tensor] = None  # float [2, h, w] positions in this frame of last-keyframe pixels
    weight: Optional[torch.Tensor] = None  # float [2, h, w]
    failed: bool = False  # tracking failure (black frame, no texture, flow inconsistent); reason in `message`
    message: str = ""


@dataclass
class EdgeObservations:
    """Frontend output for a set of frame-graph edges, at the BA resolution ``(h, w)``."""

    ii: torch.Tensor  # int64 [E] source keyframe index
    jj: torch.Tensor  # int64 [E] target keyframe index
    target: torch.Tensor  # float32 [E, 2, h, w] (u, v) in keyframe jj of each pixel of keyframe ii
    weight: torch.Tensor  # float32 [E, 2, h, w] confidence in [0, 1]
    dynamic: Optional[torch.Tensor] = None  # float32 [E, h, w] probability the pixel moves independently
    # float32 [n, h, w]: per-keyframe inverse-depth damping for the BA, one map per graph keyframe (learned
    # frontends: DROID's eta); None -> the optimizer's configured constant
    depth_damping: Optional[torch.Tensor] = None
    # priors a frontend adds for the BA (the mapper asks for them: Frontend.depth_prior / distance_prior)
    disp_prior: Optional["DepthPrior"] = None
    dist_prior: Optional["DistancePrior"] = None

    def __post_init__(self) -> None:
        e = int(self.ii.shape[0])
        if self.jj.shape[0] != e or self.target.shape[0] != e or self.weight.shape[0] != e:
            raise ValueError(
                f"EdgeObservations: inconsistent edge counts ii={tuple(self.ii.shape)} jj={tuple(self.jj.shape)} "
                f"target={tuple(self.target.shape)} weight={tuple(self.weight.shape)}"
            )


@dataclass
class DepthPrior:
    """A prior on the inverse depth of graph keyframes ``ids`` (DROID-SLAM's ``disps_sens`` with its ``alpha``: a
    depth sensor's, or a frontend's own, such as the road plane's).  The BA adds ``weight (d - disp)^2`` per pixel
    of the keyframes whose depth it optimises (:mod:`pvslam_core.geometry.ba`)."""

    ids: torch.Tensor  # int64 [m] graph indices of the keyframes
    disp: torch.Tensor  # float32 [m, h, w] inverse depth
    weight: torch.Tensor  # float32 [m, h, w] alpha >= 0 (0: no prior at that pixel)

    def __post_init__(self) -> None:
        if not (self.disp.dim() == 3 and tuple(self.disp.shape) == tuple(self.weight.shape)
                and tuple(self.ids.shape) == (self.disp.shape[0],)):
            raise ValueError(f"DepthPrior: ids {tuple(self.ids.shape)}, disp {tuple(self.disp.shape)} and weight "
                             f"{tuple(self.weight.shape)} must be [m], [m, h, w], [m, h, w]")


@dataclass
class DistancePrior:
    """A prior on the distance between the camera centres of graph keyframes ``ii[m]`` and ``jj[m]`` (the flow
    frontend's road motion in camera heights times the camera height); the BA adds ``weight`` times the squared
    relative error (:mod:`pvslam_core.geometry.ba_distance`)."""

    ii: torch.Tensor  # int64 [m] graph indices
    jj: torch.Tensor  # int64 [m] graph indices
    dist: torch.Tensor  # float64 [m] map units, > 0
    weight: torch.Tensor  # float64 [m] alpha in flow-cost units of the relative error

    def __post_init__(self) -> None:
        if not (self.dist.dim() == 1 and self.ii.shape == self.jj.shape == self.dist.shape == self.weight.shape):
            raise ValueError(f"DistancePrior: ii {tuple(self.ii.shape)}, jj {tuple(self.jj.shape)}, dist "
                             f"{tuple(self.dist.shape)} and weight {tuple(self.weight.shape)} must each be [m]")


@dataclass
class LoopCandidate:
    """A loop proposed by a :class:`~pvslam_core.interfaces.LoopDetector` (keyframes by stable id)."""

    i: int  # stable id of the newer keyframe
    j: int  # stable id of the older keyframe it revisits
    score: float  # similarity (cosine) in [-1, 1]
    # geometric verification: True passed, False failed, None not checked (a retrieval-only detector); the
    # mapper's loop policy accepts True always, None only when configured to (loop_closure.accept_unverified)
    verified: Optional[bool] = None
    inliers: int = 0


@dataclass
class LoopClosure:
    """A loop the pipeline accepted: input-frame indices (for outputs and evaluation) and keyframe ids."""

    frame_i: int  # input-frame index of the newer keyframe
    frame_j: int  # input-frame index of the older keyframe
    kf_i: int  # stable keyframe ids
    kf_j: int
    score: float
    verified: Optional[bool] = None
    inliers: int = 0
    loop_ba: bool = False  # whether this closure ran a loop BA (else its edges only joined the window BA)


@dataclass
class FrameResult:
    """What the mapper says about one input frame (and the pipeline turns into the VPS head's motion cue).

    Geometry is at the BA resolution ``(h, w)``.  The *reference* is the keyframe this frame was tracked against
    (the newest keyframe when the frame arrived): ``ref_target`` are the positions in this frame of the reference's
    pixels, ``ref_disp``/``ref_pose`` the reference's inverse depth and pose.  Two frames tracked against the same
    reference (or a frame and the reference itself) therefore share the pixels from which the flow between them
    follows (:func:`pvslam_core.slam.motion_cue.motion_cue`).
    """

    frame_index: int
    timestamp: float
    pose: torch.Tensor  # float64 [7] T_wc, the estimate at the time this frame was processed
    initialized: bool  # whether the map was initialised (before that poses and depths are placeholders)
    keyframe_id: Optional[int] = None  # stable id when this frame became a keyframe
    ref_id: Optional[int] = None  # stable id of the reference keyframe (None for the first keyframe)
    ref_pose: Optional[torch.Tensor] = None  # float64 [7] T_wc of the reference
    ref_target: Optional[torch.Tensor] = None  # float32 [2, h, w] reference pixel -> (u, v) in this frame
    ref_weight: Optional[torch.Tensor] = None  # float32 [2, h, w] confidence of ref_target
    ref_disp: Optional[torch.Tensor] = None  # float32 [h, w] inverse depth of the reference
    intrinsics: Optional[torch.Tensor] = None  # float32 [4] fx fy cx cy at the BA resolution
    failed: bool = False  # tracking failed on this frame (its pose is a prediction)
    message: str = ""

    @property
    def is_keyframe(self) -> bool:
        return self.keyframe_id is not None


@dataclass
class OptimizerReport:
    """What one optimizer call did: iterations run, cost before and after, and any problem it caught."""

    iterations: int = 0
    cost_before: float = float("nan")
    cost_after: float = float("nan")
    num_edges: int = 0
    num_free_poses: int = 0
    rejected: bool = False  # a degenerate or non-finite update was detected and the previous estimate kept
    message: str = ""


@dataclass
class RunResult:
    """What :func:`pvslam_core.pipeline.run` returns."""

    run_dir: Optional[str]
    timestamps: torch.Tensor  # float64 [T]
    poses: torch.Tensor  # float64 [T, 7] T_wc, one per input frame
    keyframe_indices: torch.Tensor  # int64 [K] input-frame index of each keyframe
    keyframe_poses: torch.Tensor  # float64 [K, 7] T_wc
    metrics: dict = field(default_factory=dict)
    loops: list[LoopClosure] = field(default_factory=list)
    frame_seconds: list[float] = field(default_factory=list)  # wall time spent on each input frame
