"""The ``fusion`` VPS head (PVO's VO-enhanced video panoptic segmentation, PV-SLAM Algorithm 1's last stage).

Per frame ``t`` (after the first):

1. the segmenter's FPN features of frame ``t-1`` (kept in the VPS state) are forward-warped into frame ``t`` per
   level with the VO's flow (static pixels optionally with the rigid flow of depth + poses, writes optionally
   z-ordered by depth), see :mod:`.feature_warp`;
2. ``fusion_conv1(cat(features_t, warped))`` per level (:mod:`.layer`);
3. the segmenter's own heads decode the fused pyramid (semantic head, RPN, box/mask heads, panoptic combine);
4. the fused segmentation's thing segments are matched to the previous frame's tracked ids warped by the flow
   (shared with ``warp_iou``: :mod:`pvslam_plugins.vps.matching`), then to remembered lost tracks; the rest get
   new ids.

On the first frame, or when the segmentation carries no features, step 1-3 are skipped (the segmenter's output is
tracked as is).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from pvslam_core.interfaces import MotionCue, VPSHead, VPSState
from pvslam_core.types import Frame, PanopticSegmentation, Segment

from ..matching import (
    FLOW_MAX_SIDE,
    FLOW_PRESET,
    IdAllocator,
    TrackMemory,
    WarpOptions,
    match_segments,
    previous_flow,
    relabel,
    segment_velocities,
    subsample,
    unique_ids,
    warp_previous_ids,
)
from .config import FusionConfig
from .feature_warp import warp_pyramid
from .layer import FeatureFusion, load_fusion

#: fusion weights trained here for the shipped reduced segmenter (``pvslam train vps --plugin fusion``)
SHIPPED_FUSION = Path(__file__).with_name("weights") / "fusion_reduced.pth"
#: sha256 of the shipped file: other bytes (a truncated copy, a Git LFS pointer) are refused, never loaded
SHIPPED_FUSION_SHA256 = "ca45f137999c5a26152d9a1cc5d6efde8391eee8826c9f90d8962ce1020bce6c"


def motion_field(prev_panoptic: PanopticSegmentation, cue: MotionCue, frame_hw: tuple[int, int],
                 rigid_static: bool) -> tuple[Optional[torch.Tensor], Optional[torch.Tensor]]:
    """The cue's flow in *frame* pixels ``[1, 2, hf, wf]`` (on the cue's grid), with the previous frame's stuff
    moved by the rigid flow of depth + poses when asked and available, and the depth ``[1, hf, wf]`` (or None)."""
    if cue.flow is None:
        return None, None
    from ..warp_iou.warp import rigid_flow

    H, W = frame_hw
    flow = cue.flow.detach().cpu().float().clone()  # [2, hf, wf] in cue pixels
    hf, wf = flow.shape[-2:]
    depth = cue.depth_prev.detach().cpu().float() if cue.depth_prev is not None else None
    if (rigid_static and depth is not None and tuple(depth.shape) == (hf, wf) and cue.pose_prev is not None
            and cue.pose_cur is not None and cue.intrinsics is not None):
        rflow, _, valid = rigid_flow(depth.numpy(), cue.pose_prev.detach().cpu().double().numpy(),
                                     cue.pose_cur.detach().cpu().double().numpy(),
                                     cue.intrinsics.detach().cpu().double().numpy())
        pids = subsample(prev_panoptic.ids.detach().cpu().numpy().astype(np.int64), hf, wf)
        things = np.array(sorted(s.id for s in prev_panoptic.segments if s.isthing), dtype=np.int64)
        static = torch.from_numpy(valid & (pids != 0) & ~np.isin(pids, things))
        flow = torch.where(static[None], torch.from_numpy(rflow), flow)
    flow[0] *= W / wf
    flow[1] *= H / hf
    return flow[None], (depth[None] if depth is not None else None)


class FusionHead(VPSHead):
    """See the module docstring.  ``model``: a loaded :class:`~pvslam_plugins.segmenters.panoptic_fpn.model.
    PanopticFPN` (else built from the config on first use); ``fusion``: a :class:`FeatureFusion`."""

    def __init__(self, config: Optional[FusionConfig] = None, model=None, fusion: Optional[FeatureFusion] = None
                 ) -> None:
        self.config = config or FusionConfig()
        self._model = model
        self._fusion = fusion
        self._ids = IdAllocator()
        self.memory = TrackMemory(self.config.memory_frames, self.config.memory_min_score)
        self.last_matches: list[tuple[int, int, float]] = []
        self.last_fused: Optional[PanopticSegmentation] = None  # the decoded fused segmentation (segmenter ids)

    # ------------------------------------------------------------------------------------------------- parts
    @property
    def model(self):
        if self._model is None:
            from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenterConfig, build_model

            c = self.config
            model = build_model(PanopticFPNSegmenterConfig(preset=c.preset, weights=c.segmenter_weights))
            # masks only for boxes the panoptic combine keeps (it drops scores below its confidence threshold
            # first): the same output for ~10 ms less per frame at 320x240 (this model is the head's own copy)
            m = model.cfg
            m.box_head.score_thresh_test = max(m.box_head.score_thresh_test, m.combine.instances_confidence_thresh)
            if c.proposals is not None:
                m.rpn.post_nms_topk_test = c.proposals
            self._model = model
        return self._model

    @property
    def fusion(self) -> FeatureFusion:
        if self._fusion is None:
            from pvslam_core.weights import check_shipped, resolve_weights

            layer = FeatureFusion(self.model.cfg.fpn.out_channels)
            c = self.config
            path = None
            if c.weights is not None:
                path = resolve_weights(c.weights)
            elif c.preset == "reduced" and c.segmenter_weights is None and SHIPPED_FUSION.is_file():
                path = SHIPPED_FUSION
            if path is not None and path.resolve() == SHIPPED_FUSION.resolve():
                check_shipped(SHIPPED_FUSION, SHIPPED_FUSION_SHA256, "vps fusion", "reinstall pvslam (the file is "
                              "package data of pvslam_plugins.vps.fusion) or set vps.weights", error=ValueError)
            if path is not None:
                load_fusion(layer, path)
            self._fusion = layer.eval()
        return self._fusion

    def reset(self) -> None:
        self._ids.reset()
        self.memory.reset()

    # ------------------------------------------------------------------------------------------------ fusion
    @torch.no_grad()
    def fuse(self, prev: VPSState, frame: Frame, seg: PanopticSegmentation, cue: MotionCue
             ) -> Optional[PanopticSegmentation]:
        """Decode frame ``t`` from its features fused with the warped features of ``prev`` (None when a part is
        missing: features or a flow)."""
        cur, old = seg.features, prev.panoptic.features
        if cur is None or old is None:
            return None
        H, W = frame.height, frame.width
        flow, depth = motion_field(prev.panoptic, cue, (H, W), self.config.rigid_static)
        if flow is None:
            if prev.image is None:
                return None
            from ..warp_iou.warp import dis_flow

            flow = torch.from_numpy(dis_flow(prev.image, frame.image, FLOW_PRESET, FLOW_MAX_SIDE))[None]
        model = self.model
        pyr = model.pyramid_for(cur.maps, (H, W))
        old_pyr = model.pyramid_for(old.maps, (H, W))
        warped = warp_pyramid(old_pyr.levels, pyr.strides, flow, (H, W), pyr.image_sizes[0],
                              depth if self.config.z_order else None)
        fused = {k: self.fusion(v, warped[k]) for k, v in pyr.levels.items()}
        out = model.decode(pyr.replace(fused))[0]
        movable = frozenset(model.categories.movable)
        segments = [Segment(s.id, s.category_id, s.isthing, s.score,
                            movable=bool(s.isthing and s.category_id in movable)) for s in out.segments]
        return PanopticSegmentation(out.ids.to("cpu", torch.int64), segments, cur)

    # ------------------------------------------------------------------------------------------------ update
    def update(self, prev: Optional[VPSState], frame: Frame, seg: PanopticSegmentation,
               cue: Optional[MotionCue] = None) -> VPSState:
        c = self.config
        cue = cue or MotionCue()
        if prev is None:
            self.memory.reset()
        fused = self.fuse(prev, frame, seg, cue) if (prev is not None and c.fuse) else None
        self.last_fused = fused
        src = fused if fused is not None else seg
        ids = src.ids.detach().cpu().numpy().astype(np.int64)
        h, w = ids.shape
        cur_segments = {s.id: s for s in src.segments if s.id != 0}
        present = set(unique_ids(ids).tolist()) - {0}
        cur_things = sorted(sid for sid in present if sid in cur_segments and cur_segments[sid].isthing)
        cur_cat = {g: cur_segments[g].category_id for g in cur_things}

        assign: dict[int, int] = {}
        self.last_matches = []
        if prev is not None:
            self._ids.reserve(prev.panoptic.segments)
            opts = WarpOptions(rigid_stuff=c.rigid_static)
            flow = previous_flow(prev, frame.image, cue, h, w, opts)
            prev_ids = prev.panoptic.ids.detach().cpu().numpy().astype(np.int64)
            prev_cat = {s.id: s.category_id for s in prev.panoptic.segments if s.isthing}
            if prev_ids.shape == (h, w):
                self.memory.set_velocities(segment_velocities(prev_ids, flow, sorted(prev_cat)))
            if cur_things:
                warped = warp_previous_ids(prev, frame.image, cue, h, w, opts, flow=flow)
                for g, p, score in match_segments(ids, warped, cur_things, cur_cat, prev_cat, c.match, c.min_score):
                    assign[g] = p
                    self.last_matches.append((g, p, score))
        if c.memory_frames > 0:
            rest = [g for g in cur_things if g not in assign]
            for g, p, score in self.memory.match(ids, rest, cur_cat, set(assign.values()), int(frame.index)):
                assign[g] = p
                self.last_matches.append((g, p, score))
        panoptic = relabel(src, ids, cur_segments, cur_things, present, assign, self._ids)
        panoptic.features = seg.features  # the next frame warps the segmenter's (unfused) features, as PVO
        if c.memory_frames > 0:
            self.memory.observe(panoptic.ids.numpy(), {s.id: s.category_id for s in panoptic.segments if s.isthing},
                                int(frame.index))
        return VPSState(frame_index=int(frame.index), panoptic=panoptic, image=frame.image)


def make_vps_head(config: FusionConfig, context: Any = None) -> FusionHead:
    return FusionHead(config)
