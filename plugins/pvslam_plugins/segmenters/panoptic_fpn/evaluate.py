"""Panoptic quality of a PanopticFPN on labelled samples (the core's COCO PQ definition, per category).

Besides the standard PQ, :func:`evaluate` can report PQ with ground-truth segments smaller than ``min_gt_area``
pixels turned into void (``pq_min_area``): a predicted segment lying mostly on such pixels is then ignored and the
tiny segment is no false negative.  Distant parked cars of a few pixels dominate the synthetic scenes' thing
counts; the second number shows how much of the gap to 1 they make.  Both are reported, neither replaces the other.
"""
from __future__ import annotations

import time
from typing import Sequence

import torch

from pvslam_core.evaluation.panoptic import pq
from pvslam_core.types import PanopticSegmentation

from .data import Sample
from .model import PanopticFPN

__all__ = ["evaluate", "predict", "void_small_segments", "format_table"]


def predict(model: PanopticFPN, samples: Sequence[Sample]) -> tuple[list[PanopticSegmentation], float]:
    """Inference on each sample's image -> panoptic segmentations (no features) and mean seconds per frame."""
    model.eval()
    preds = []
    t0 = time.perf_counter()
    with torch.no_grad():
        for s in samples:
            preds.append(model.segment(s.image).to_panoptic(with_features=False))
    return preds, (time.perf_counter() - t0) / max(len(samples), 1)


def void_small_segments(sample: Sample, min_area: int) -> PanopticSegmentation:
    """The sample's ground truth with segments under ``min_area`` pixels set to void (id 0)."""
    ids = sample.ids.long()
    uniq, inv, counts = torch.unique(ids, return_inverse=True, return_counts=True)
    small = counts < min_area
    out = torch.where(small[inv], torch.zeros_like(ids), ids)
    kept = set(uniq[~small].tolist())
    return PanopticSegmentation(out, [s for s in sample.segments if s.id in kept])


def evaluate(model: PanopticFPN, samples: Sequence[Sample], min_gt_area: int = 64) -> dict:
    """PQ/SQ/RQ (all, things, stuff, per category) of ``model`` on ``samples``; ``pq_min_area`` with ground-truth
    segments under ``min_gt_area`` pixels as void."""
    preds, sec = predict(model, samples)
    cats = list(model.categories.categories)
    gts = [PanopticSegmentation(s.ids.long(), list(s.segments)) for s in samples]
    out = {"pq": pq(preds, gts, cats), "seconds_per_frame": sec, "num_frames": len(samples)}
    if min_gt_area > 0:
        out["pq_min_area"] = pq(preds, [void_small_segments(s, min_gt_area) for s in samples], cats)
        out["min_gt_area"] = int(min_gt_area)
    return out


def format_table(result: dict) -> str:
    """Markdown table: overall / things / stuff rows, then one row per category that occurs."""
    r = result["pq"]
    lines = ["| | PQ | SQ | RQ | TP | FP | FN |", "|---|---|---|---|---|---|---|"]
    for group in ("all", "things", "stuff"):
        g = r[group]
        lines.append(f"| **{group}** ({g['n']} classes) | {100 * g['pq']:.1f} | {100 * g['sq']:.1f} | "
                     f"{100 * g['rq']:.1f} | | | |")
    for cid, c in sorted(r["per_category"].items()):
        if c["tp"] + c["fp"] + c["fn"] == 0:
            continue
        kind = "thing" if c["isthing"] else "stuff"
        lines.append(f"| {c['name']} ({kind}) | {100 * c['pq']:.1f} | {100 * c['sq']:.1f} | {100 * c['rq']:.1f} | "
                     f"{c['tp']} | {c['fp']} | {c['fn']} |")
    return "\n".join(lines)
