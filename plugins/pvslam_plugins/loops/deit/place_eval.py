"""Offline place-recognition metrics of global descriptors on a ground-truth sequence (validation and benchmarks).

The protocol imitates the detector in the pipeline: every ``stride``-th frame stands for a keyframe; each query
keyframe retrieves its most similar older keyframe outside the temporal exclusion (``exclude_recent`` keyframes
and ``min_time_gap`` seconds), and that top-1 candidate is what the loop policy would accept.

* candidates whose optical axes differ by more than ``max_rotation_deg`` are skipped (the loop policy's
  orientation check, ground-truth orientations standing in for the estimated ones);
* a top-1 ``(q, j)`` is **correct** when a ground-truth positive pair (centres within the sequence's revisit
  radius, optical axes within its angle) lies within ``tolerance`` frames of it in both indices (how the run
  evaluation, :mod:`pvslam_core.evaluation.loops`, matches detections);
* **revisit queries**: queries with at least one eligible ground-truth positive keyframe;
* ``recall_at_1``: revisit queries whose top-1 is correct (no threshold);
* at a threshold t: ``precision(t)`` = correct / top-1s scoring >= t (all queries), ``recall(t)`` = revisit
  queries with a correct top-1 scoring >= t;
* :func:`verified_top_one`: the same with geometric verification (``verify = true``): a query's detection is its
  best candidate above the threshold (of at most ``max_candidates``) that passes the verification;
* :func:`calibrate` pools sequences and returns a threshold with precision 1.00 (just above the best wrong top-1
  score, plus a relative margin) and the recall there.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch
import torch.nn.functional as F


@dataclass
class TopOne:
    """Per query keyframe (frame indices): best eligible match, its score, correctness; revisit flag."""

    query: torch.Tensor  # int64 [Q]
    match: torch.Tensor  # int64 [Q], -1 when nothing is eligible
    score: torch.Tensor  # float [Q], -inf when nothing is eligible
    correct: torch.Tensor  # bool [Q]
    revisit: torch.Tensor  # bool [Q]


def top_one(desc: torch.Tensor, pos: torch.Tensor, timestamps: torch.Tensor, stride: int = 3,
            exclude_recent: int = 20, min_time_gap: float = 10.0, tolerance: int = 5,
            axes: Optional[torch.Tensor] = None, max_rotation_deg: Optional[float] = 60.0) -> TopOne:
    """``desc`` unit descriptors ``[K, d]`` of the keyframes ``0, stride, 2 stride, ...`` of a sequence of N
    frames; ``pos`` bool ``[N, N]`` ground-truth positives, ``timestamps [N]``.  With the optical ``axes [N, 3]``,
    candidates whose axes differ by more than ``max_rotation_deg`` are skipped, as the loop policy's orientation
    check does (with the ground-truth orientations standing in for the estimated ones)."""
    kf, masked, ok = _eligible(desc, pos.shape[0], timestamps, stride, exclude_recent, min_time_gap, axes,
                               max_rotation_deg)
    score, col = masked.max(dim=1)
    match = torch.where(torch.isfinite(score), kf[col], torch.full_like(col, -1))
    return _judge(kf, match, score, pos, ok, tolerance)


def verified_top_one(desc: torch.Tensor, pos: torch.Tensor, timestamps: torch.Tensor, threshold: float,
                     verify: Callable[[int, int], bool], max_candidates: int = 3, stride: int = 3,
                     exclude_recent: int = 20, min_time_gap: float = 10.0, tolerance: int = 5,
                     axes: Optional[torch.Tensor] = None, max_rotation_deg: Optional[float] = 60.0) -> TopOne:
    """:func:`top_one` with geometric verification, as the detector with ``verify = true`` and the loop policy
    behave: each query's eligible candidates scoring ``>= threshold``, best first, at most ``max_candidates``,
    are checked by ``verify(query_frame, match_frame)``; the first that passes is the query's detection (its
    score), a query without one gets score -inf (no detection at any threshold ``>= threshold``)."""
    kf, masked, ok = _eligible(desc, pos.shape[0], timestamps, stride, exclude_recent, min_time_gap, axes,
                               max_rotation_deg)
    k = min(int(max_candidates), masked.shape[1])
    top, col = masked.topk(k, dim=1)  # [K, k] best first
    match = torch.full((len(kf),), -1, dtype=torch.long)
    score = torch.full((len(kf),), float("-inf"), dtype=masked.dtype)
    # the verification is per pair (ORB + RANSAC on images): a loop over the few candidates above threshold
    for q, c in torch.nonzero(top >= threshold).tolist():
        if match[q] < 0 and verify(int(kf[q]), int(kf[col[q, c]])):
            match[q], score[q] = kf[col[q, c]], top[q, c]
    return _judge(kf, match, score, pos, ok, tolerance)


def _eligible(desc: torch.Tensor, n_frames: int, timestamps: torch.Tensor, stride: int, exclude_recent: int,
              min_time_gap: float, axes: Optional[torch.Tensor], max_rotation_deg: Optional[float]
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Keyframe frame indices ``[K]``, similarities with ineligible pairs at -inf ``[K, K]``, eligibility mask."""
    kf = torch.arange(0, n_frames, stride)  # [K] frame index of each pseudo keyframe
    if desc.shape[0] != len(kf):
        raise ValueError(f"{desc.shape[0]} descriptors for {len(kf)} keyframes (every {stride}th of {n_frames})")
    d = desc.float()
    sims = d @ d.T  # [K, K]
    p = torch.arange(len(kf))
    ok = p[None, :] <= p[:, None] - 1 - exclude_recent
    t = timestamps[kf].double()
    ok &= (t[:, None] - t[None, :]) >= min_time_gap
    if axes is not None and max_rotation_deg is not None:
        a = axes[kf].double()
        ok &= (a @ a.T) >= math.cos(math.radians(max_rotation_deg))
    return kf, torch.where(ok, sims, torch.full_like(sims, float("-inf"))), ok


def _judge(kf: torch.Tensor, match: torch.Tensor, score: torch.Tensor, pos: torch.Tensor, ok: torch.Tensor,
           tolerance: int) -> TopOne:
    # a GT positive pair within `tolerance` frames of (query, match) in both indices, as the run evaluation counts
    dil = F.max_pool2d(pos.float()[None, None], 2 * tolerance + 1, 1, tolerance)[0, 0] > 0  # [N, N]
    correct = (match >= 0) & dil[kf, match.clamp_min(0)]
    revisit = (pos[kf][:, kf] & ok).any(dim=1)
    return TopOne(kf, match, score, correct, revisit)


def metrics_at(results: Sequence[TopOne], threshold: float) -> dict:
    correct = torch.cat([r.correct for r in results])
    score = torch.cat([r.score for r in results])
    revisit = torch.cat([r.revisit for r in results])
    above = score >= threshold
    n_above = int(above.sum())
    tp = int((above & correct).sum())
    n_rev = int(revisit.sum())
    return {
        "threshold": float(threshold),
        "precision": tp / n_above if n_above else float("nan"),
        "recall": int((above & correct & revisit).sum()) / n_rev if n_rev else float("nan"),
        "detections": n_above,
        "false": n_above - tp,
        "revisit_queries": n_rev,
        "recall_at_1": int((correct & revisit).sum()) / n_rev if n_rev else float("nan"),
    }


def calibrate(results: Sequence[TopOne], margin: float = 0.1) -> dict:
    """A threshold with precision 1.00 over all sequences, just above the best wrong top-1 score: ``best_wrong +
    margin * (1 - best_wrong)`` (relative, because the spread of cosine scores near 1 depends on the descriptor),
    and the metrics there; ``best_wrong`` and ``median_revisit`` (of the correct revisit scores) show the gap."""
    score = torch.cat([r.score for r in results])
    correct = torch.cat([r.correct for r in results])
    revisit = torch.cat([r.revisit for r in results])
    finite = torch.isfinite(score)
    wrong = score[finite & ~correct]
    best_wrong = float(wrong.max()) if len(wrong) else -1.0
    thr = min(1.0, best_wrong + margin * (1.0 - best_wrong))
    out = metrics_at(results, thr)
    good = score[finite & correct & revisit]
    out["best_wrong"] = best_wrong
    out["median_revisit"] = float(good.median()) if len(good) else float("nan")
    return out
