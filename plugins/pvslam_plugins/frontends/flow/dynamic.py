"""Geometric dynamic masks of the ``flow`` frontend: which pixels move on their own, without a segmenter.

A pixel is a *candidate* when its observed flow target disagrees with the reprojection under the current estimate
(ego-motion + the source keyframe's depth) by more than ``max(thresh, rel x the edge's median residual)`` BA px.
Candidates alone are noisy (occlusion edges, a few bad flow vectors); a moving vehicle is a *coherent region*.  So
candidates are grouped (:func:`group_regions`): 8-connected components of at least ``min_area`` BA pixels are kept
and grown by ``grow`` pixels (an object's border blocks mix it with the background), isolated pixels are left to
the robust kernel of the BA.  With a segmenter the segment vote (:func:`pvslam_core.slam.confidence.segment_vote`)
is OR-ed with these regions: either cue marks a pixel dynamic.

Per keyframe the frontend keeps one mask (:func:`keyframe_vote`: the pixels found dynamic on at least half of its
judged edges), used where an edge has no mask of its own yet (its first observation) and for the motion filter's
targets (the frames tracked against that keyframe), so a bus does not drag the non-keyframe poses either.  A new
keyframe starts from its reference keyframe's mask moved along the tracked flow (:func:`warp_mask`).  Every mask
reaches the weights through PV-SLAM eq. 4 (:func:`pvslam_core.slam.confidence.observed_flow_weight`), the same
path as a segmenter's (:mod:`.dynamic_masking`).

Masks are float32 ``[h, w]`` (or ``[N, h, w]``) at the BA resolution, 1 = dynamic.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np
import torch


def residual_candidates(res: torch.Tensor, valid: torch.Tensor, thresh: float, rel_thresh: float) -> torch.Tensor:
    """bool ``[N, h, w]``: valid pixels whose residual ``res [N, h, w]`` (BA px) exceeds ``max(thresh, rel_thresh
    x median residual of the edge)`` (``rel_thresh <= 0``: the absolute threshold only)."""
    N = res.shape[0]
    thr = torch.full((N,), float(thresh), dtype=res.dtype, device=res.device)
    if rel_thresh > 0 and N:
        med = torch.nanmedian(torch.where(valid, res, torch.nan).reshape(N, -1), dim=1).values
        thr = torch.maximum(thr, torch.nan_to_num(med, nan=0.0) * rel_thresh)
    return (res > thr[:, None, None]) & valid


def group_regions(cand: torch.Tensor, min_area: int = 4, grow: int = 1) -> torch.Tensor:
    """Coherent regions of candidate pixels: bool ``[N, h, w]`` keeping the 8-connected components of ``cand
    [N, h, w]`` with at least ``min_area`` pixels, dilated by ``grow`` pixels (a ``(2 grow + 1)^2`` square)."""
    out = torch.zeros_like(cand, dtype=torch.bool)
    c = cand.detach().cpu().numpy().astype(np.uint8)
    kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8) if grow > 0 else None
    for n in range(c.shape[0]):
        if not c[n].any():
            continue
        num, labels, stats, _ = cv2.connectedComponentsWithStats(c[n], connectivity=8)
        keep = np.zeros(num, bool)
        keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
        m = keep[labels].astype(np.uint8)
        if kernel is not None and m.any():
            m = cv2.dilate(m, kernel)
        out[n] = torch.from_numpy(m.astype(bool)).to(cand.device)
    return out


def keyframe_vote(masks: list[torch.Tensor], min_frac: float = 0.5) -> Optional[torch.Tensor]:
    """One keyframe's mask from the masks ``[h, w]`` of its edges: the pixels dynamic on at least ``min_frac`` of
    them (float32 0/1), None without masks."""
    if not masks:
        return None
    frac = torch.stack([m.float() for m in masks]).mean(0)
    return (frac >= min_frac - 1e-6).float()


def warp_mask(mask: torch.Tensor, target: torch.Tensor, grow: int = 1) -> torch.Tensor:
    """Move a source mask ``[h, w]`` into the target view along the flow ``target [2, h, w]`` (absolute (u, v)
    in target BA px of each source pixel): nearest-pixel splat of the dynamic pixels, dilated by ``grow``."""
    h, w = mask.shape[-2:]
    m = mask.detach().cpu() > 0.5
    out = np.zeros((h, w), np.uint8)
    if bool(m.any()):
        t = target.detach().cpu()
        u = torch.round(t[0][m]).long()
        v = torch.round(t[1][m]).long()
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & torch.isfinite(t[0][m]) & torch.isfinite(t[1][m])
        out[v[inside].numpy(), u[inside].numpy()] = 1
        if grow > 0 and out.any():
            out = cv2.dilate(out, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    return torch.from_numpy(out.astype(np.float32)).to(mask.device)
