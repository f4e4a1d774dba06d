"""Panoptic-aware confidence (PV-SLAM eq. 4) and segment-level voting of dynamic masks.

Shared by every frontend (the classical ``flow`` and the learned ``raft_gru``), whose settings of it are one model,
``frontend.dynamic`` (:class:`pvslam_core.slam.dynamic_config.DynamicMaskingConfig`).

Eq. 4 of the PV-SLAM paper::

    w_p = sigmoid(w + (1 - M_d) * eta),      eta = 10,   M_d = 1 on *dynamic* pixels

(``eta`` is called ``offset`` in the code, to keep it apart from the BA's depth damping, also ``eta`` in DROID.)

The mask convention matters, and the paper and PVO's public code disagree:

* **paper** (default here): ``M_d = 1`` marks dynamic pixels, so static pixels get ``+eta`` on their logit and
  dynamic pixels keep the raw logit ``w``.  Relative to static pixels, dynamic pixels are down-weighted by a
  factor of about ``e^-eta``.
* **pvo_code**: PVO's ``DynamicUpdateModule`` computes ``sigmoid(w + (1 - bin) * 10)`` where ``bin = 1`` marks
  *static* pixels (its labels are 1 where the ground-truth flow equals the camera-induced flow).  Written with our
  dynamic mask ``M_d`` that is ``sigmoid(w + M_d * eta)``: the *dynamic* pixels get ``+eta``.

Decision (and why): pvslam's frames carry ``dynamic`` masks with **1 = moving independently** everywhere, and
every caller passes that mask; ``convention`` only chooses which of the two formulas is applied.  The default is
``"paper"``.  In PVO the target fed to BA for dynamic pixels is the network's *camera-only* flow (the object's
own motion is split off into ``delta_dy``), so raising those pixels' weight can be defended there.  A frontend
whose targets are the *observed* (full) flow, like the classical DIS frontend, must **down-weight** dynamic
pixels, because their targets contain motion the camera model cannot explain.  With the paper convention that
frontend feeds ``w_logit = logit(c) - eta`` (see :func:`observed_flow_weight`): static pixels end up with
``c`` and dynamic pixels with ``sigmoid(logit(c) - eta) ~= c * e^-eta`` (at most ~4.5e-3 with ``c`` capped at 0.99).  With ``"pvo_code"`` the same
inputs would give dynamic pixels ``c`` and static pixels ``~ c * e^-eta`` (tests show both).
"""
from __future__ import annotations

from typing import Optional, Sequence, Union

import torch

CONVENTIONS = ("paper", "pvo_code")

__all__ = [
    "CONVENTIONS",
    "logit",
    "panoptic_aware_weight",
    "observed_flow_weight",
    "segment_vote",
]


def logit(p: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """``log(p / (1 - p))`` with ``p`` clamped to ``[eps, 1 - eps]`` (finite for p = 0 or 1)."""
    p = p.clamp(eps, 1.0 - eps)
    return torch.log(p) - torch.log1p(-p)


def panoptic_aware_weight(
    w_logit: torch.Tensor,
    dynamic: torch.Tensor,
    offset: float = 10.0,
    convention: str = "paper",
) -> torch.Tensor:
    """PV-SLAM eq. 4: the confidence of each pixel given its raw logit and its dynamic mask.

    Args:
        w_logit: raw confidence logits ``w`` (any shape).
        dynamic: probability / mask that the pixel moves independently, **1 = dynamic** (broadcastable to
            ``w_logit``; bool or float in [0, 1]).  This is pvslam's convention whatever ``convention`` says.
        offset: the logit offset ``eta`` of eq. 4 (10 in the paper and in PVO).
        convention: ``"paper"`` -> ``sigmoid(w + (1 - M_d) * eta)``;  ``"pvo_code"`` -> PVO's code, whose mask
            is the *static* mask ``M_s = 1 - M_d``: ``sigmoid(w + (1 - M_s) * eta) = sigmoid(w + M_d * eta)``.
            See the module docstring for why "paper" is the default.

    Returns:
        weights in (0, 1), same shape as the broadcast inputs, dtype of ``w_logit``.
    """
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    m_d = dynamic.to(dtype=w_logit.dtype if w_logit.is_floating_point() else torch.float32)
    if convention == "paper":
        return torch.sigmoid(w_logit + (1.0 - m_d) * offset)
    m_s = 1.0 - m_d  # PVO's mask: 1 = static
    return torch.sigmoid(w_logit + (1.0 - m_s) * offset)


def observed_flow_weight(
    confidence: torch.Tensor,
    dynamic: Optional[torch.Tensor],
    offset: float = 10.0,
    convention: str = "paper",
    max_conf: float = 0.99,
) -> torch.Tensor:
    """Weights for targets that are the *observed* (full) flow, from a confidence ``c`` in [0, 1].

    Feeds ``w_logit = logit(min(c, max_conf)) - offset`` (``offset`` = eq. 4's ``eta``) to :func:`panoptic_aware_weight`, so with the paper
    convention static pixels keep their confidence (capped at ``max_conf``) and dynamic pixels get
    ``sigmoid(logit(c) - eta) = c e^-eta / (1 - c + c e^-eta)``, i.e. ``~ c e^-eta`` for small ``c`` and at most
    ``~ 4.5e-3`` for ``c <= 0.99`` and ``eta = 10``.  The cap matters: a perfectly consistent pixel (``c = 1``,
    e.g. a car that keeps its place in the image while the camera moves) would otherwise have an unbounded logit
    and keep a weight near 1 however dynamic it is.  ``dynamic=None`` returns ``c`` unchanged.
    """
    if dynamic is None:
        return confidence
    c = confidence.clamp(max=max_conf)
    return panoptic_aware_weight(logit(c) - offset, dynamic, offset=offset, convention=convention)


def _thing_lookup(
    uniq: torch.Tensor, thing_mask: Union[torch.Tensor, Sequence[int]]
) -> torch.Tensor:
    """bool [K]: whether each id in ``uniq`` is a thing."""
    if isinstance(thing_mask, torch.Tensor) and thing_mask.dtype == torch.bool:
        lut = thing_mask.to(uniq.device)
        inside = (uniq >= 0) & (uniq < lut.numel())
        out = torch.zeros_like(uniq, dtype=torch.bool)
        out[inside] = lut[uniq[inside]]
        return out
    ids = torch.as_tensor(list(thing_mask) if not isinstance(thing_mask, torch.Tensor) else thing_mask,
                          dtype=torch.int64, device=uniq.device).reshape(-1)
    return torch.isin(uniq, ids)


def segment_vote(
    dynamic_prob: torch.Tensor,
    seg_ids: torch.Tensor,
    thresh: float = 0.5,
    thing_mask: Optional[Union[torch.Tensor, Sequence[int]]] = None,
    pixel_thresh: float = 0.5,
    valid: Optional[torch.Tensor] = None,
    keep_pixels: bool = True,
    batch_things: Optional[Sequence[Optional[torch.Tensor]]] = None,
) -> torch.Tensor:
    """Mark a whole panoptic segment dynamic when more than ``thresh`` of its pixels are dynamic.

    Args:
        dynamic_prob: ``[..., h, w]`` per-pixel dynamic probability (or bool mask); a pixel counts as dynamic
            when its probability is ``> pixel_thresh``.
        seg_ids: int ``[h, w]`` segment ids, or ``[..., h, w]`` matching ``dynamic_prob``'s leading dims (one id map
            per batch element, e.g. the source keyframe of each edge).  Id 0 (void) never votes.
        thresh: fraction of a segment's pixels that must be dynamic for the whole segment to become dynamic
            (PVO's segm_filter uses 0.8).
        thing_mask: if given, only these segments vote: a bool lookup table indexed by id, or a sequence/tensor
            of the ids that are things.  ``None``: every non-void segment votes.
        pixel_thresh: per-pixel binarisation threshold.
        valid: optional bool ``[..., h, w]`` (like ``dynamic_prob``): only these pixels count in a segment's
            fraction (pixels that cannot be judged, e.g. ones that leave the other view, neither vote for nor
            against); a segment without valid pixels never votes.  ``None``: every pixel counts.
        keep_pixels: True (PVO's segm_filter): the result is the per-pixel mask OR the voted segments; False: only
            the voted segments (for callers that bring their own per-pixel evidence, e.g. grouped regions).
        batch_things: per batch element (the flattened leading dims of ``dynamic_prob``, e.g. each edge's source
            keyframe), the int ids allowed to vote in that element's id map (None or empty: none votes).  Segment
            ids are unique only within one frame (a learned segmenter numbers its segments 1, 2, ... in every
            frame), so the movable ids of several keyframes must not be pooled into one ``thing_mask``: one
            keyframe's car id is another's road id, and a road flagged by flow errors then voted dynamic whole.
            Combines with ``thing_mask`` (both must allow a segment).

    Returns:
        bool ``[..., h, w]``: the per-pixel mask OR the voted segments (pixels of segments that did not vote keep
        their own value, as PVO's segm_filter does), or only the voted segments with ``keep_pixels=False``.
        Vectorised: one scatter-add over (batch, segment).
    """
    dyn = dynamic_prob > pixel_thresh if dynamic_prob.dtype != torch.bool else dynamic_prob
    if dyn.dim() < 2:
        raise ValueError(f"dynamic_prob must be [..., h, w], got shape {tuple(dynamic_prob.shape)}")
    h, w = dyn.shape[-2:]
    if tuple(seg_ids.shape[-2:]) != (h, w):
        raise ValueError(f"seg_ids {tuple(seg_ids.shape)} does not match dynamic_prob {tuple(dyn.shape)}")
    batch = int(dyn.numel() // (h * w)) if dyn.numel() else 0
    if batch == 0:
        return dyn.clone()
    # compact ids on the (usually un-batched) id map itself, then broadcast the compact index
    uniq, inv = torch.unique(seg_ids.to(device=dyn.device, dtype=torch.int64), return_inverse=True)
    flat_dyn = dyn.reshape(batch, h * w)
    flat_seg = inv.expand(dyn.shape).reshape(batch, h * w)
    k = int(uniq.numel())
    key = flat_seg + (torch.arange(batch, device=dyn.device) * k)[:, None]
    key = key.reshape(-1)
    # index_add_ rather than torch.bincount: the latter is ~50x slower on CPU in recent torch builds
    if valid is None:
        ones = torch.ones(key.numel(), dtype=torch.float32, device=dyn.device)
    else:
        if tuple(valid.shape) != tuple(dyn.shape):
            raise ValueError(f"valid {tuple(valid.shape)} does not match dynamic_prob {tuple(dyn.shape)}")
        ones = valid.to(device=dyn.device, dtype=torch.float32).reshape(-1)
    counts = torch.zeros(batch * k, dtype=torch.float32, device=dyn.device).index_add_(0, key, ones)
    dyn_counts = torch.zeros(batch * k, dtype=torch.float32, device=dyn.device).index_add_(
        0, key, flat_dyn.reshape(-1).to(torch.float32) * ones)
    frac = dyn_counts / counts.clamp(min=1)
    eligible = uniq != 0
    if thing_mask is not None:
        eligible = eligible & _thing_lookup(uniq, thing_mask)
    seg_dyn = (frac > thresh).reshape(batch, k) & (counts > 0).reshape(batch, k) & eligible[None, :]
    if batch_things is not None:
        if len(batch_things) != batch:
            raise ValueError(f"batch_things has {len(batch_things)} entries for {batch} id maps")
        allowed = torch.zeros(batch, k, dtype=torch.bool, device=dyn.device)
        for b, ids in enumerate(batch_things):  # batch = edges of one call (tens); one isin over K ids each
            if ids is not None and ids.numel():
                allowed[b] = torch.isin(uniq, ids.to(device=uniq.device, dtype=torch.int64).reshape(-1))
        seg_dyn = seg_dyn & allowed
    voted = seg_dyn.reshape(-1)[key].reshape(batch, h * w)
    return ((flat_dyn | voted) if keep_pixels else voted).reshape(dyn.shape)
