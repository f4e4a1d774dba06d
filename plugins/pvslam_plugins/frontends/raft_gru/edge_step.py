"""The per-edge pieces of one update step shared by the frontend and the trainer: the motion input of each variant,
PVO's dynamic mask (eq. 6 + segment vote), the confidences handed to the BA (eq. 4) and the panoptic ids they vote
over.

Shapes: ``E`` edges at 1/8 resolution ``h x w``, flow-like tensors channels-last ``(E, h, w, 2)`` (x, y) as
upstream; a leading batch dimension ``B`` where the network wants one.

Mask conventions.  PVO's mask logits ``raw_mask (E, h, w, 2)`` are *static* logits (``sigmoid >= 0.5`` = static,
its labels are 1 where the ground-truth flow equals the camera flow); pvslam's ``dynamic`` maps are **1 = moving**.
Everything leaving this module uses pvslam's convention; :func:`pvslam_core.slam.confidence.panoptic_aware_weight`
decides (``convention``) which of the two readings of eq. 4 is applied.
"""
from __future__ import annotations

from typing import Any, Optional, Sequence

import torch

from pvslam_core.slam.confidence import observed_flow_weight, panoptic_aware_weight, segment_vote
from pvslam_core.types import PanopticSegmentation

from .net import droid_motion, pvo_motion


def motion_input(
    variant: str,
    coords0: torch.Tensor,
    coords1: torch.Tensor,
    target: torch.Tensor,
    delta_dy: Optional[torch.Tensor] = None,
    raw_mask: Optional[torch.Tensor] = None,
    training: bool = False,
) -> torch.Tensor:
    """The update operator's motion input ``(B, E, 4 | 8, h, w)`` for the current reprojection ``coords1`` and the
    edges' previous ``target`` (all ``(B, E, h, w, 2)``; ``coords0`` the pixel grid ``(h, w, 2)``).

    DROID: ``[coords1 - coords0, target - coords1]``.  PVO: ``[cam, cam + delta_dy, target - coords1, raw_mask]``
    with ``cam = target - coords0`` at inference (PVO's ``factor_graph.update``) and ``coords1 - coords0`` in
    training (PVO's ``DroidNet.forward``); the fixture README notes the difference.
    """
    if variant == "droid":
        return droid_motion(coords0, coords1, target)
    if delta_dy is None or raw_mask is None:
        raise ValueError("variant 'pvo' needs the edges' delta_dy and raw_mask")
    cam = (coords1 if training else target) - coords0
    return pvo_motion(cam, delta_dy, target - coords1, raw_mask)


def pvo_dynamic(
    raw_mask: torch.Tensor,
    thresh: float = 0.5,
    seg: Optional[torch.Tensor] = None,
    thing_ids: Optional[Sequence[Optional[torch.Tensor]]] = None,
    vote_thresh: float = 0.8,
) -> tuple[torch.Tensor, torch.Tensor]:
    """PVO's binarised mask with its segment filter, in pvslam's convention.

    Args:
        raw_mask: ``(E, h, w, 2)`` static logits (PVO's ``raw_mask``, accumulated ``+= delta_m`` per update).
        thresh: a channel is static when ``sigmoid(raw_mask) >= thresh`` (PVO ``dy_thresh``).
        seg: optional ``(E, h, w)`` panoptic ids of each edge's source keyframe at this resolution.
        thing_ids: per edge, the segments of its source keyframe allowed to vote (None: every non-void segment, as
            PVO's segm_filter).
        vote_thresh: a segment whose fraction of dynamic pixels (either channel) exceeds this becomes dynamic in
            both channels (PVO: 0.8).

    Returns:
        ``dyn_c (E, h, w, 2)`` float 1 = dynamic per channel (what eq. 4 and ``delta_dy`` use, as PVO) and
        ``dynamic (E, h, w)`` float: the per-pixel dynamic probability ``1 - min_c sigmoid(raw_mask)``, set to 1 on
        voted segments (what the BA's ``EdgeObservations.dynamic`` reports).
    """
    static_p = torch.sigmoid(raw_mask.float())
    dyn_c = static_p < thresh
    prob = 1.0 - static_p.min(dim=-1).values
    if seg is not None:
        either = dyn_c.any(dim=-1)
        voted = segment_vote(either, seg, thresh=vote_thresh, batch_things=thing_ids)
        dyn_c = dyn_c | voted[..., None]
        prob = torch.where(voted, torch.ones_like(prob), prob)
    return dyn_c.float(), prob


def pvo_weight(w_logit: torch.Tensor, dyn_c: Optional[torch.Tensor], offset: float, convention: str) -> torch.Tensor:
    """Eq. 4 on PVO's raw weight logits ``(E, h, w, 2)``; ``dyn_c`` None = no pixel dynamic."""
    dyn = torch.zeros_like(w_logit) if dyn_c is None else dyn_c.to(w_logit.dtype)
    return panoptic_aware_weight(w_logit, dyn, offset=offset, convention=convention)


def residual_dynamic(
    residual: torch.Tensor,
    valid: torch.Tensor,
    abs_thresh: float,
    rel_thresh: float,
    max_fraction: float,
    seg: Optional[torch.Tensor] = None,
    thing_ids: Optional[Sequence[Optional[torch.Tensor]]] = None,
    vote_thresh: float = 0.5,
) -> torch.Tensor:
    """DROID-variant dynamic mask ``(E, h, w)`` float from ``|target - reprojection|`` ``residual (E, h, w)``.

    A pixel is dynamic when its residual exceeds ``max(abs_thresh, rel_thresh * median)`` of its edge (valid
    pixels only), thing segments vote (:func:`segment_vote`), and an edge with more than ``max_fraction`` dynamic
    pixels gets no mask at all (the estimate, not the scene, is off) - the rules of the ``flow`` frontend.
    """
    e = residual.shape[0]
    thr = torch.full((e,), float(abs_thresh), dtype=residual.dtype, device=residual.device)
    if rel_thresh > 0:
        med = torch.nanmedian(torch.where(valid, residual, torch.nan).reshape(e, -1), dim=1).values
        thr = torch.maximum(thr, torch.nan_to_num(med, nan=0.0) * rel_thresh)
    dyn = (residual > thr[:, None, None]) & valid
    if seg is not None:
        dyn = segment_vote(dyn, seg, thresh=vote_thresh, batch_things=thing_ids)
    frac = dyn.float().mean(dim=(1, 2))
    enough = valid.sum(dim=(1, 2)) >= 8
    keep = (frac <= max_fraction) & enough
    return (dyn & keep[:, None, None]).float()


def droid_weight(conf: torch.Tensor, dynamic: Optional[torch.Tensor], offset: float, convention: str) -> torch.Tensor:
    """Eq. 4 for DROID's sigmoid confidence ``conf (E, h, w, 2)``, whose targets are the *observed* flow.

    With the paper convention static pixels keep ``conf`` exactly and dynamic ones get ``sigmoid(logit(c) - eta)``
    (:func:`observed_flow_weight`); ``pvo_code`` applies that function everywhere.  ``dynamic (E, h, w)``.
    """
    if dynamic is None:
        return conf
    dyn = dynamic[..., None].expand_as(conf)
    if convention == "paper":
        out = conf.clone()
        m = dyn > 0
        if bool(m.any()):
            out[m] = observed_flow_weight(conf[m], dyn[m], offset=offset, convention="paper")
        return out
    return observed_flow_weight(conf, dyn, offset=offset, convention=convention)


def keyframe_segments(seg: Optional[PanopticSegmentation], h: int, w: int, stride: int, device: Any):
    """``(ids int64 [h, w], movable thing ids int64 [K])`` of a keyframe's segmentation at the feature resolution (the
    block centres of ``stride``), or Nones without one."""
    if seg is None or seg.ids is None:
        return None, None
    s = stride
    ids = seg.ids.to(torch.int64)[s // 2:: s, s // 2:: s][:h, :w].contiguous().to(device)  # block centres
    things = torch.tensor([x.id for x in seg.segments if x.isthing and x.movable], dtype=torch.int64)
    return ids, things.to(device)


def source_segments(srcs: list, h: int, w: int, things_only: bool, device: Any):
    """``(E, h, w)`` panoptic ids of the edges' source keyframes ``srcs`` (:class:`.frontend_state.KeyframeState`;
    zeros = void where a source has none) and, per source, the thing ids allowed to vote (None: every segment; per
    source because ids are unique only within one frame: ``segment_vote``'s ``batch_things``)."""
    if all(s.seg is None for s in srcs):
        return None, None
    zero = torch.zeros(h, w, dtype=torch.int64, device=device)
    seg = torch.stack([s.seg if s.seg is not None else zero for s in srcs])
    return seg, ([s.things for s in srcs] if things_only else None)
