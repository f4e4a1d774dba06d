"""Panoptic quality (PQ, Kirillov et al. 2019, COCO panopticapi definition) and video panoptic quality
(VPQ, Kim et al. 2020 "VPSNet"; the metric PVO reports).

PQ, per category c, accumulated over all frames::

    TP: (gt segment, predicted segment) of category c with IoU > 0.5  (such a match is unique)
    IoU = |g ∩ p| / (|g| + |p| - |g ∩ p| - |p ∩ void|)      (void pixels of the GT do not count)
    FN: GT segment without a match;  FP: predicted segment without a match, unless more than half of it lies
        on void GT pixels (then it is ignored)
    PQ_c = sum_TP IoU / (TP + FP/2 + FN/2) = SQ_c * RQ_c,  SQ_c = sum_TP IoU / TP,  RQ_c = TP / (TP + FP/2 + FN/2)

PQ over all / thing / stuff categories is the mean of PQ_c over the categories of that group that occur
(TP + FP + FN > 0), exactly as ``panopticapi.evaluation.pq_compute`` does.

VPQ^k: every window of k+1 consecutive frames (stride 1) is treated as one image (the frames side by side);
a segment is then a spatio-temporal *tube*: all pixels carrying the same id in the window. PQ statistics of the
tubes are accumulated over all windows of the sequence and averaged over categories as above. VPQ is the mean of
VPQ^k over ``ks`` (VPSNet uses k = 0, 5, 10, 15; k = 0 is the image PQ). A tracking identity switch splits a
predicted tube and lowers VPQ^k for k >= 1 while leaving PQ unchanged. Windows are only formed when the
sequence has at least k+1 frames; a k without any window is reported with ``num_windows = 0`` and left out of
the mean.

Window conventions differ between published evaluations; ``ks`` lists window sizes minus one:

* VPSNet on Cityscapes-VPS (GT every 5th frame): windows of 1..4 *annotated* frames, spanning k = 0, 5, 10, 15
  video frames. On every-frame GT, ``ks=(0, 5, 10, 15)`` (the default) takes 1, 6, 11, 16 consecutive frames.
* PVO's ``VPS_Module/tools/4_eval_vpq.py`` (Virtual KITTI 2, every frame annotated) uses windows of
  ``nframes`` in (1, 5, 10, 15, 20) consecutive frames, stride 1, and averages the five: ``ks=PVO_VKITTI_KS``
  = (0, 4, 9, 14, 19) reproduces it.

Inputs: a list of frames, each a :class:`~pvslam_core.types.PanopticSegmentation` or a tuple
``(ids [H, W], segments)`` where ``segments`` is a list of :class:`~pvslam_core.types.Segment`, of COCO
``segments_info`` dicts (``{"id", "category_id"}``) or a dict ``{id: category_id}``. ``void_id`` pixels are
void in both GT and prediction. A predicted id without a segment is an error; ground-truth pixels whose id has
no segment are skipped in matching, as in panopticapi (they are neither a segment nor void).
Categories: :class:`~pvslam_core.types.Category` objects or COCO dicts (``{"id", "isthing", "name"}``).

Implementation: the (gt id, predicted id) pixel-pair counts of each frame are computed once; a window's
statistics are the sums of its frames' tables, so VPQ costs little more than PQ.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import numpy as np

__all__ = ["pq", "vpq", "PQStat", "frame_table", "VPSNET_KS", "PVO_VKITTI_KS"]

VPSNET_KS = (0, 5, 10, 15)
PVO_VKITTI_KS = (0, 4, 9, 14, 19)  # window sizes 1, 5, 10, 15, 20 frames (PVO 4_eval_vpq.py)


# ----------------------------------------------------------------------------------------------------------------
# input normalisation
# ----------------------------------------------------------------------------------------------------------------
def _ids_np(ids: Any) -> np.ndarray:
    if hasattr(ids, "detach"):
        ids = ids.detach().cpu().numpy()
    a = np.asarray(ids)
    if a.ndim != 2:
        raise ValueError(f"panoptic ids must be [H, W], got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"panoptic ids must be integers, got {a.dtype}")
    return a.astype(np.int64, copy=False)


def _segment_map(segments: Any) -> dict[int, int]:
    """``{segment id: category id}`` from Segment objects, COCO dicts or a plain dict."""
    if segments is None:
        return {}
    if isinstance(segments, dict):
        return {int(k): int(v) for k, v in segments.items()}
    out: dict[int, int] = {}
    for s in segments:
        if isinstance(s, dict):
            out[int(s["id"])] = int(s["category_id"])
        else:
            out[int(s.id)] = int(s.category_id)
    return out


def _frame(x: Any) -> tuple[np.ndarray, dict[int, int]]:
    if hasattr(x, "ids") and hasattr(x, "segments"):
        return _ids_np(x.ids), _segment_map(x.segments)
    if isinstance(x, (tuple, list)) and len(x) == 2:
        return _ids_np(x[0]), _segment_map(x[1])
    raise TypeError(f"expected PanopticSegmentation or (ids, segments), got {type(x).__name__}")


def _categories(categories: Any) -> dict[int, tuple[bool, str]]:
    """``{category id: (isthing, name)}``."""
    out: dict[int, tuple[bool, str]] = {}
    if isinstance(categories, dict):
        categories = list(categories.values())
    for c in categories:
        if isinstance(c, dict):
            cid, isthing, name = int(c["id"]), bool(c.get("isthing", False)), str(c.get("name", c["id"]))
        else:
            cid, isthing, name = int(c.id), bool(c.isthing), str(getattr(c, "name", c.id))
        out[cid] = (isthing, name)
    if not out:
        raise ValueError("no categories given")
    return out


# ----------------------------------------------------------------------------------------------------------------
# per-frame pixel-pair tables
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class _Table:
    gt: np.ndarray  # int64 [P] gt id of each pixel pair (void_id = void)
    pred: np.ndarray  # int64 [P] predicted id
    count: np.ndarray  # int64 [P] number of pixels
    gt_cat: dict[int, int]
    pred_cat: dict[int, int]


def frame_table(pred: Any, gt: Any, void_id: int = 0) -> _Table:
    """(gt id, pred id, pixel count) for every pair of ids that overlap in one frame, plus the id->category maps."""
    p_ids, p_map = _frame(pred)
    g_ids, g_map = _frame(gt)
    if p_ids.shape != g_ids.shape:
        raise ValueError(f"prediction {p_ids.shape} and ground truth {g_ids.shape} differ in size")
    if p_ids.size and (p_ids.min() < 0 or g_ids.min() < 0):
        raise ValueError("panoptic ids must be non-negative")
    g = g_ids.reshape(-1)
    p = p_ids.reshape(-1)
    base = int(p.max()) + 1 if p.size else 1
    key = g * base + p
    uniq, counts = np.unique(key, return_counts=True)
    tg, tp = uniq // base, uniq % base
    # Every non-void predicted id must have a segment (a category), as panopticapi requires. Ground-truth ids
    # without a segment are skipped in matching like panopticapi does (neither a segment nor void).
    missing = [int(i) for i in np.unique(tp) if i != void_id and int(i) not in p_map]
    if missing:
        raise ValueError(f"prediction: ids {missing[:10]} appear in the id map but have no segment/category")
    return _Table(tg, tp, counts.astype(np.int64), g_map, p_map)


# ----------------------------------------------------------------------------------------------------------------
# statistics
# ----------------------------------------------------------------------------------------------------------------
class PQStat:
    """Per-category accumulators ``iou, tp, fp, fn`` (as in panopticapi's PQStat)."""

    def __init__(self) -> None:
        self.iou: dict[int, float] = {}
        self.tp: dict[int, int] = {}
        self.fp: dict[int, int] = {}
        self.fn: dict[int, int] = {}

    def _add(self, d: dict, c: int, v) -> None:
        d[c] = d.get(c, 0) + v

    def __iadd__(self, other: "PQStat") -> "PQStat":
        for name in ("iou", "tp", "fp", "fn"):
            mine = getattr(self, name)
            for c, v in getattr(other, name).items():
                self._add(mine, c, v)
        return self

    def add_window(self, tables: Sequence[_Table], categories: dict[int, tuple[bool, str]], void_id: int) -> None:
        """Accumulate the PQ statistics of the segments (tubes) of the concatenation of ``tables``' frames."""
        gt = np.concatenate([t.gt for t in tables])
        pr = np.concatenate([t.pred for t in tables])
        cnt = np.concatenate([t.count for t in tables])
        # Merge equal (gt, pred) pairs across frames.
        pairs, inv = np.unique(np.stack([gt, pr], axis=1), axis=0, return_inverse=True)
        inter = np.bincount(inv.reshape(-1), weights=cnt, minlength=len(pairs)).astype(np.int64)
        g, p = pairs[:, 0], pairs[:, 1]
        gt_cat: dict[int, int] = {}
        pred_cat: dict[int, int] = {}
        for t in tables:  # first frame's category wins for an id (ids should keep their category)
            for k, v in t.gt_cat.items():
                gt_cat.setdefault(k, v)
            for k, v in t.pred_cat.items():
                pred_cat.setdefault(k, v)

        gt_area: dict[int, int] = {}
        pred_area: dict[int, int] = {}
        pred_void: dict[int, int] = {}
        for gi, pi, n in zip(g.tolist(), p.tolist(), inter.tolist()):
            if gi != void_id and gi in gt_cat:
                gt_area[gi] = gt_area.get(gi, 0) + n
            if pi != void_id:
                pred_area[pi] = pred_area.get(pi, 0) + n
                if gi == void_id:
                    pred_void[pi] = pred_void.get(pi, 0) + n
        for pi in pred_area:
            if pred_cat[pi] not in categories:
                raise ValueError(f"predicted segment {pi} has category {pred_cat[pi]} that is not in categories")
        for gi in gt_area:
            if gt_cat[gi] not in categories:
                raise ValueError(f"ground-truth segment {gi} has category {gt_cat[gi]} that is not in categories")

        gt_matched: set[int] = set()
        pred_matched: set[int] = set()
        for gi, pi, n in zip(g.tolist(), p.tolist(), inter.tolist()):
            if gi == void_id or pi == void_id or gi not in gt_cat:
                continue
            if gt_cat[gi] != pred_cat[pi]:
                continue
            union = pred_area[pi] + gt_area[gi] - n - pred_void.get(pi, 0)
            iou = n / union
            if iou > 0.5:
                c = gt_cat[gi]
                self._add(self.tp, c, 1)
                self._add(self.iou, c, iou)
                gt_matched.add(gi)
                pred_matched.add(pi)
        for gi in gt_area:
            if gi not in gt_matched:
                self._add(self.fn, gt_cat[gi], 1)
        for pi, area in pred_area.items():
            if pi in pred_matched:
                continue
            if pred_void.get(pi, 0) / area > 0.5:  # mostly on unlabelled pixels: not counted
                continue
            self._add(self.fp, pred_cat[pi], 1)

    def summary(self, categories: dict[int, tuple[bool, str]]) -> dict:
        """``{"pq", "sq", "rq", "all", "things", "stuff", "per_category"}`` (fractions in [0, 1])."""
        per: dict[int, dict] = {}
        for cid, (isthing, name) in categories.items():
            tp, fp, fn = self.tp.get(cid, 0), self.fp.get(cid, 0), self.fn.get(cid, 0)
            iou = float(self.iou.get(cid, 0.0))
            denom = tp + 0.5 * fp + 0.5 * fn
            per[cid] = {
                "name": name,
                "isthing": isthing,
                "pq": iou / denom if denom > 0 else float("nan"),
                "sq": iou / tp if tp > 0 else (0.0 if denom > 0 else float("nan")),
                "rq": tp / denom if denom > 0 else float("nan"),
                "tp": tp,
                "fp": fp,
                "fn": fn,
                "iou_sum": iou,
            }

        def average(select) -> dict:
            vals = [v for v in per.values() if select(v) and (v["tp"] + v["fp"] + v["fn"]) > 0]
            if not vals:
                return {"pq": float("nan"), "sq": float("nan"), "rq": float("nan"), "n": 0}
            return {
                "pq": float(np.mean([v["pq"] for v in vals])),
                "sq": float(np.mean([v["sq"] for v in vals])),
                "rq": float(np.mean([v["rq"] for v in vals])),
                "n": len(vals),
            }

        out_all = average(lambda v: True)
        return {
            "pq": out_all["pq"],
            "sq": out_all["sq"],
            "rq": out_all["rq"],
            "all": out_all,
            "things": average(lambda v: v["isthing"]),
            "stuff": average(lambda v: not v["isthing"]),
            "per_category": per,
        }


# ----------------------------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------------------------
def _tables(preds: Sequence[Any], gts: Sequence[Any], void_id: int) -> list[_Table]:
    preds, gts = list(preds), list(gts)
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predicted frames but {len(gts)} ground-truth frames")
    return [frame_table(p, g, void_id) for p, g in zip(preds, gts)]


def pq(preds: Sequence[Any], gts: Sequence[Any], categories: Any, void_id: int = 0) -> dict:
    """Panoptic quality accumulated over frames (each frame evaluated as its own image).

    Returns ``pq, sq, rq`` (over all categories that occur), ``all`` / ``things`` / ``stuff``
    (``{pq, sq, rq, n}``), ``per_category`` (``{category id: {name, isthing, pq, sq, rq, tp, fp, fn, iou_sum}}``)
    and ``num_frames``. Undefined averages (no category occurs) are NaN.
    """
    if hasattr(preds, "ids") or (isinstance(preds, tuple) and len(preds) == 2 and hasattr(preds[0], "shape")):
        preds, gts = [preds], [gts]  # a single frame
    cats = _categories(categories)
    stat = PQStat()
    tables = _tables(preds, gts, void_id)
    for t in tables:
        stat.add_window([t], cats, void_id)
    out = stat.summary(cats)
    out["num_frames"] = len(tables)
    return out


def vpq(
    pred_seq: Sequence[Any],
    gt_seq: Sequence[Any],
    categories: Any,
    ks: Iterable[int] = VPSNET_KS,
    void_id: int = 0,
) -> dict:
    """Video panoptic quality (VPSNet / PVO): PQ of spatio-temporal tubes over windows of k+1 frames.

    Returns ``vpq``, ``vpq_things``, ``vpq_stuff`` (means over the ks that have at least one window; NaN if
    none), ``ks`` and ``per_k`` (``{k: {pq, sq, rq, all, things, stuff, per_category, num_windows}}``).
    """
    cats = _categories(categories)
    tables = _tables(pred_seq, gt_seq, void_id)
    n = len(tables)
    per_k: dict[int, dict] = {}
    for k in ks:
        k = int(k)
        if k < 0:
            raise ValueError(f"k must be >= 0, got {k}")
        stat = PQStat()
        num_windows = max(0, n - k)
        for i in range(num_windows):
            stat.add_window(tables[i : i + k + 1], cats, void_id)
        summary = stat.summary(cats)
        summary["num_windows"] = num_windows
        per_k[k] = summary

    def mean_over_k(group: str) -> float:
        vals = [
            per_k[k][group]["pq"] for k in per_k if per_k[k]["num_windows"] > 0 and not math.isnan(per_k[k][group]["pq"])
        ]
        return float(np.mean(vals)) if vals else float("nan")

    return {
        "vpq": mean_over_k("all"),
        "vpq_things": mean_over_k("things"),
        "vpq_stuff": mean_over_k("stuff"),
        "ks": [int(k) for k in per_k],
        "per_k": per_k,
        "num_frames": n,
    }
