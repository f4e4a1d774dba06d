"""Loop-closure detection precision / recall against ground-truth revisit pairs.

Definitions (frame indices; every pair is normalised to ``(newer, older) = (max, min)``; exact duplicates are
counted once):

* A detected pair ``(i, j)`` **matches** a GT pair ``(gi, gj)`` when ``|i - gi| <= tolerance`` and
  ``|j - gj| <= tolerance`` (Chebyshev distance in the (i, j) plane).
* **Precision** = detections that match some GT pair / detections (NaN when nothing was detected).
* **Revisit events**: GT pairs come in runs (the camera passes a place again for several frames, and each frame
  may revisit several older frames). Two GT pairs belong to the same event when they are within ``tolerance``
  of each other in both indices; an event is a connected component of that relation. A revisit of the same
  older place at two different times gives two events.
* **Recall** = events with at least one matching detection / events (NaN when the GT has no event).
  ``pair_recall`` = GT pairs with a matching detection within ``tolerance`` / GT pairs.
* ``f1`` = harmonic mean of precision and (event) recall (0 if either is 0, NaN if either is undefined).
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Iterable

import numpy as np

__all__ = ["loop_precision_recall", "revisit_events", "pair_array", "read_pairs_json", "pairs_json_text"]

# the "pairs" list of a revisit file, [[i, j], ...] of integers, is read without a Python object per pair: its opening,
# its end (the last pair's bracket and the list's) and the characters allowed between
_PAIRS_OPEN = re.compile(r'"pairs"\s*:\s*\[')
_PAIRS_END = re.compile(r"\]\s*\]")
_PAIRS_BODY = re.compile(r"[0-9\s,\[\]-]*")
_BRACKETS = str.maketrans("[],", "   ")
_WRITE_ROWS = 65536  # pairs formatted at once when writing
_LINK_CHUNK = 1 << 17  # pairs whose links to the next rows are looked up at once (revisit_events)


def pair_array(pairs: Any) -> np.ndarray:
    """Revisit pairs as one int64 ``[M, 2]`` array (as given, no normalisation): a long run's ground truth holds
    millions of pairs, which as Python tuples cost ~100 bytes each."""
    arr = np.asarray(pairs if len(pairs) else np.zeros((0, 2)), dtype=np.int64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"revisit pairs must be [i, j] rows, got an array of shape {arr.shape}")
    return arr


def read_pairs_json(path: str | Path) -> np.ndarray:
    """The ``pairs`` of a revisit file (``{"pairs": [[i, j], ...], ...}``) as an int64 ``[M, 2]`` array;
    :class:`ValueError` naming the file when it holds anything else."""
    from .run_eval import read_json_object

    try:
        fast = _fast_pairs(Path(path).read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        fast = None  # read_json_object names it
    if fast is not None:
        return fast
    pairs = read_json_object(path).get("pairs")  # an empty list, or a file to refuse with its reason
    ok = isinstance(pairs, list) and all(
        isinstance(p, list) and len(p) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in p)
        for p in pairs)
    if not ok:
        raise ValueError(f"{path}: expected {{\"pairs\": [[i, j], ...]}} with integer frame indices")
    return pair_array(pairs)


def _fast_pairs(text: str):
    """The pairs of a well-formed, non-empty revisit file's text as an array, or None to let the JSON parser
    decide."""
    m = _PAIRS_OPEN.search(text) if text.lstrip().startswith("{") else None
    end = _PAIRS_END.search(text, m.end()) if m is not None else None
    if end is None:
        return None
    body = text[m.end():end.start() + 1]  # [i, j], ... up to the last pair's bracket
    if not _PAIRS_BODY.fullmatch(body):
        return None
    nums = np.fromstring(body.translate(_BRACKETS), dtype=np.int64, sep=" ")
    n = body.count("[")
    if body.count("]") != n or len(nums) != 2 * n:
        return None
    return nums.reshape(-1, 2)


def pairs_json_text(pairs: Any, **extra: Any) -> str:
    """``{"pairs": [[i, j], ...], **extra}`` as one line of JSON, formatted in blocks of rows (no Python list per
    pair)."""
    arr = pair_array(pairs)
    blocks = (", ".join(f"[{i}, {j}]" for i, j in arr[k:k + _WRITE_ROWS].tolist())
              for k in range(0, len(arr), _WRITE_ROWS))
    rest = json.dumps(extra, allow_nan=False)[1:-1]
    return '{"pairs": [' + ", ".join(blocks) + "]" + (", " + rest if rest else "") + "}\n"


def _pairs(pairs: Iterable[Any]) -> np.ndarray:
    if isinstance(pairs, np.ndarray):  # sorted unique (newer, older) rows through one int64 key per pair
        arr = pair_array(pairs)
        if not len(arr):
            return arr
        lo = arr.min()
        newer, older = arr.max(1) - lo, arr.min(1) - lo
        width = int(older.max()) + 1
        key = np.unique(newer * width + older)
        return np.stack([key // width + lo, key % width + lo], 1)
    out = []
    for p in pairs:
        if hasattr(p, "frame_i") and hasattr(p, "frame_j"):  # LoopClosure (input-frame indices)
            a, b = int(p.frame_i), int(p.frame_j)
        elif hasattr(p, "i") and hasattr(p, "j"):
            a, b = int(p.i), int(p.j)
        else:
            a, b = (int(v) for v in p)
        out.append((max(a, b), min(a, b)))
    if not out:
        return np.zeros((0, 2), dtype=np.int64)
    return np.unique(np.array(out, dtype=np.int64), axis=0)


def revisit_events(gt_pairs: Iterable[Any], tolerance: int = 5) -> list[np.ndarray]:
    """Group GT pairs into revisit events (connected components, linked within ``tolerance`` in both indices), in
    the order of their first pair.

    The links are not listed (a repeated loop's millions of pairs have ~(2 tolerance + 1)^2 neighbours each): within
    one newer frame ``i`` consecutive older frames link when at most ``tolerance`` apart, and each pair links to the
    first and the last pair within ``tolerance`` of it in each of the next ``tolerance`` rows.  That is exact: in a
    window of ``2 tolerance + 1`` frames a row holds at most two runs of linked pairs, and those two cover them."""
    gt = _pairs(gt_pairs)  # unique, sorted by (i, j)
    n = len(gt)
    if n == 0:
        return []
    tol = int(tolerance)
    i, j = gt[:, 0] - gt[:, 0].min(), gt[:, 1] - gt[:, 1].min() + tol
    width = int(j.max()) + tol + 1
    key = i * width + j  # sorted, as gt
    same = np.flatnonzero((i[1:] == i[:-1]) & (j[1:] - j[:-1] <= tol))
    labels = _merge_labels(np.arange(n), same, same + 1)  # runs within a row
    for di in range(1, tol + 1):
        a, b = [], []
        for c0 in range(0, n, _LINK_CHUNK):  # in chunks of pairs: the temporaries stay small
            ic, jc = i[c0:c0 + _LINK_CHUNK] + di, j[c0:c0 + _LINK_CHUNK]
            for m in (np.searchsorted(key, ic * width + jc - tol, side="left"),
                      np.searchsorted(key, ic * width + jc + tol, side="right") - 1):
                mc = np.clip(m, 0, n - 1)
                ok = (m >= 0) & (m < n) & (i[mc] == ic) & (np.abs(j[mc] - jc) <= tol)
                la, lb = labels[np.flatnonzero(ok) + c0], labels[mc[ok]]
                pair = np.unique(la[la != lb] * n + lb[la != lb])  # links between components, once each
                a.append(pair // n)
                b.append(pair % n)
        labels = _merge_labels(labels, np.concatenate(a), np.concatenate(b))
    # events in the order of their first pair (gt is sorted by i, so that is also the order of their smallest i)
    first = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))
    event = first[labels]  # [n] each pair's event, named by its first pair
    order = np.argsort(event, kind="stable")  # within an event, the pairs in order
    return np.split(gt[order], np.flatnonzero(np.diff(event[order])) + 1)


def _merge_labels(labels: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Component labels ``[n]`` after also linking the components ``a[k]`` and ``b[k]``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(a) == 0:
        return labels
    m = int(labels.max()) + 1
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(m, m))
    _, merged = connected_components(graph, directed=False)
    return merged[labels].astype(np.int64)


def loop_precision_recall(detected: Iterable[Any], gt_pairs: Iterable[Any], tolerance: int = 5) -> dict:
    """Precision / recall of detected loop pairs (see the module docstring for the exact definitions).

    ``detected``: ``(i, j)`` frame-index tuples or :class:`~pvslam_core.types.LoopClosure` objects; ``gt_pairs``: ``(i, j)``.
    Returns ``precision, recall, pair_recall, f1, num_detected, num_tp, num_fp, num_gt_pairs, num_gt_events,
    num_events_detected, tolerance, false_positives`` (up to 100 unmatched detections, for debugging).
    """
    from scipy.spatial import cKDTree

    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    det = _pairs(detected)
    gt = _pairs(gt_pairs)
    events = revisit_events(gt, tolerance)
    tol = float(tolerance) + 1e-9

    if len(det) and len(gt):
        tree_gt = cKDTree(gt.astype(np.float64))
        d, _ = tree_gt.query(det.astype(np.float64), k=1, p=np.inf, distance_upper_bound=tol)
        det_ok = np.isfinite(d)
        tree_det = cKDTree(det.astype(np.float64))
        d2, _ = tree_det.query(gt.astype(np.float64), k=1, p=np.inf, distance_upper_bound=tol)
        gt_ok = np.isfinite(d2)
        ev_ok = []
        for ev in events:
            de, _ = tree_det.query(ev.astype(np.float64), k=1, p=np.inf, distance_upper_bound=tol)
            ev_ok.append(bool(np.isfinite(de).any()))
    else:
        det_ok = np.zeros(len(det), bool)
        gt_ok = np.zeros(len(gt), bool)
        ev_ok = [False] * len(events)

    num_tp = int(det_ok.sum())
    precision = num_tp / len(det) if len(det) else float("nan")
    recall = sum(ev_ok) / len(events) if events else float("nan")
    pair_recall = float(gt_ok.sum()) / len(gt) if len(gt) else float("nan")
    if math.isnan(precision) or math.isnan(recall):
        f1 = float("nan")
    elif precision + recall == 0:
        f1 = 0.0
    else:
        f1 = 2 * precision * recall / (precision + recall)
    return {
        "precision": float(precision),
        "recall": float(recall),
        "pair_recall": float(pair_recall),
        "f1": float(f1),
        "num_detected": int(len(det)),
        "num_tp": num_tp,
        "num_fp": int(len(det) - num_tp),
        "num_gt_pairs": int(len(gt)),
        "num_gt_events": len(events),
        "num_events_detected": int(sum(ev_ok)),
        "tolerance": int(tolerance),
        "false_positives": [tuple(int(v) for v in p) for p in det[~det_ok][:100]],
    }
