"""What the SLAM parts share, and the snapshot of it that the outputs and a viewer read.

:class:`MapState` holds the frame graph (keyframes and edges, :mod:`.graph`), every input frame's pose
(:mod:`.frame_poses`), the measured-depth masks (:mod:`.observed`), the map fragments (:mod:`.fragments`), the
current fragment's start and whether it is initialised, the keyframes' thumbnails for the point clouds, and the CPU
seconds per part of the mapping.  The parts of the mapper (keyframe policy, window BA, loop closer, bootstrap) each
get it explicitly; none of them reads another part's state.

A :class:`MapSnapshot` is what :meth:`.mapper.Mapper.snapshot` returns: plain values and tensors of the map at that
moment (views of the map's own storage: read them before the next frame, copy what you keep).  Poses are T_wc
``[t, q_xyzw]``; keyframes are named by stable id.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from time import thread_time
from typing import Optional

import torch

from ..adapt import ba_px_scale
from ..interfaces import GraphListener
from ..types import Frame, LoopClosure, PanopticSegmentation, SequenceInfo
from .fragments import Fragments
from .frame_poses import FramePoses
from .graph import FrameGraph
from . import observed as _observed
from .spill import SpillStore

# robust kernel ('none': least squares) and its scale (BA px) of the motion-only BA that places non-keyframes and
# guesses new keyframe poses
MOTION_ROBUST = "cauchy"
MOTION_ROBUST_SCALE = 1.0


@dataclass
class KeyframeSnapshot:
    """The map's keyframes at one moment (CPU tensors at the bundle-adjustment resolution ``h x w``)."""

    ids: torch.Tensor  # int64 [K] stable keyframe ids
    frame_index: torch.Tensor  # int64 [K] input-frame index of each keyframe
    poses: torch.Tensor  # float64 [K, 7] T_wc
    disps: torch.Tensor  # float32 [K, h, w] inverse depth (map units)
    intrinsics: torch.Tensor  # float32 [4] fx fy cx cy at the BA resolution
    images: dict[int, torch.Tensor]  # id -> uint8 [3, h, w] RGB
    segs: dict[int, Optional[PanopticSegmentation]]  # id -> ids [h, w] (None without a segmenter)
    initialized: bool = True
    timestamps: Optional[torch.Tensor] = None  # float64 [K] seconds


@dataclass
class MapSnapshot:
    """What a run writes of the map: its keyframes, accepted loops, and (when asked for) every frame's pose."""

    keyframes: KeyframeSnapshot
    loops: list[LoopClosure]
    frames: int  # input frames posed so far
    timestamps: Optional[torch.Tensor] = None  # float64 [T] of every frame (None: not asked for)
    poses: Optional[torch.Tensor] = None  # float64 [T, 7] T_wc of every frame


class MapState(GraphListener):
    """The shared SLAM state (see the module docstring); a GraphListener for the thumbnails and masks it keys by
    keyframe id."""

    def __init__(self, info: SequenceInfo, ba_downsample: int, device, spill_dir=None) -> None:
        ds = int(ba_downsample)
        # what only the end of the run reads again (retired edge observations, frame correspondences): on disk
        # under spill_dir (None: in memory)
        self.spill = SpillStore(spill_dir)
        self.ba_downsample = ds
        self.ba_shape = (info.intrinsics.height // ds, info.intrinsics.width // ds)  # (h, w) of the BA
        # this camera's BA px per reference BA px: the motion thresholds are angles (adapt.ba_px_scale)
        self.px_scale = ba_px_scale(info.intrinsics, ds)
        intr = info.intrinsics.scaled(1.0 / ds)
        self.graph = FrameGraph(self.ba_shape[0], self.ba_shape[1], intr.vector(torch.float32, device), device=device,
                                spill=self.spill)
        # a GraphListener of the graph
        self.frames = FramePoses(self.graph, MOTION_ROBUST, MOTION_ROBUST_SCALE, spill=self.spill)
        self.observed = _observed.ObservedMasks(_observed.UNOBSERVED_WEIGHT,
                                                _observed.OBSERVED_PARALLAX * self.px_scale,
                                                _observed.GUESS_MIN_MEASURED)
        self.fragments = Fragments()  # map fragments after re-initialisations, merged by loops
        self.fragment_start = 0  # graph index of the current fragment's first keyframe
        self.initialized = False  # whether the current fragment is initialised
        # per keyframe id, at BA resolution, for the point clouds
        self.images: dict[int, torch.Tensor] = {}  # uint8 [3, h, w]
        self.segs: dict[int, Optional[PanopticSegmentation]] = {}
        # CPU seconds of the mapping thread per part (track, pose_guess, edges, ba, loops, fill)
        self.cpu: dict[str, float] = defaultdict(float)

    # ----------------------------------------------------------------------------------- GraphListener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        self.images.pop(kf_id, None)
        self.segs.pop(kf_id, None)
        self.observed.forget(kf_id)

    def on_edges_retired(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        pass

    # ------------------------------------------------------------------------------------------- parts --
    def add_thumbnail(self, kf_id: int, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        """Keyframe ``kf_id``'s image (area-averaged) and segmentation (sampled) at the BA resolution."""
        h, w = self.ba_shape
        img = torch.nn.functional.interpolate(frame.image[None].float(), size=(h, w), mode="area")[0]
        small = None
        if seg is not None:
            s = self.ba_downsample
            small = PanopticSegmentation(seg.ids[s // 2 :: s, s // 2 :: s][:h, :w].clone(), list(seg.segments))
        self.images[kf_id], self.segs[kf_id] = img.round().clamp(0, 255).to(torch.uint8), small

    def place_frames(self, kf_id: int) -> None:
        """Motion-only BA of the non-keyframes anchored at keyframe ``kf_id`` (:meth:`.frame_poses.FramePoses.
        place_pending`, on the poses' worker thread)."""
        t0 = thread_time()
        if self.frames.place_pending(kf_id):
            self.cpu["fill"] += thread_time() - t0

    def keyframes(self) -> KeyframeSnapshot:
        g = self.graph
        return KeyframeSnapshot(ids=g.ids.cpu(), frame_index=g.frame_index.cpu(), poses=g.poses.double().cpu(),
                                disps=g.disps.float().cpu(), intrinsics=g.intrinsics.float().cpu(),
                                images=self.images, segs=self.segs, initialized=bool(self.initialized),
                                timestamps=g.timestamps.double().cpu())
