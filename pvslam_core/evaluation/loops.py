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
from typing import IO, Any, Iterable

import numpy as np

__all__ = ["loop_precision_recall", "revisit_events", "pair_array", "read_pairs_json", "write_pairs_json"]

# the "pairs" list of a revisit file, [[i, j], ...] of integers, is read without a Python object per pair: its opening,
# its end (the last pair's bracket and the list's) and the characters allowed between
_PAIRS_OPEN = re.compile(r'"pairs"\s*:\s*\[')
_PAIRS_END = re.compile(r"\]\s*\]")
_PAIRS_BODY = re.compile(r"[0-9\s,\[\]-]*")
_BRACKETS = str.maketrans("[],", "   ")
_WRITE_ROWS = 8192  # pairs formatted at once when writing
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


def write_pairs_json(f: IO[str], pairs: Any, **extra: Any) -> None:
    """Write ``{"pairs": [[i, j], ...], **extra}`` as one line of JSON to the text file ``f``, a block of rows at a
    time (no Python object per pair, and not the whole text at once)."""
    arr = pair_array(pairs)
    f.write('{"pairs": [')
    for k in range(0, len(arr), _WRITE_ROWS):
        f.write((", " if k else "") + ", ".join(f"[{i}, {j}]" for i, j in arr[k:k + _WRITE_ROWS].tolist()))
    rest = json.dumps(extra, allow_nan=False)[1:-1]
    f.write("]" + (", " + rest if rest else "") + "}\n")


def _pairs(pairs: Iterable[Any]) -> np.ndarray:
    if isinstance(pairs, np.ndarray):  # sorted unique (newer, older) rows through one int64 key per pair
        arr = pair_array(pairs)
        if not len(arr) or _normalised(arr):
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


def _normalised(arr: np.ndarray) -> bool:
    """True when the rows are already ``(newer, older)``, unique and sorted (a run's ground truth as written)."""
    di = np.diff(arr[:, 0])
    return bool((arr[:, 0] >= arr[:, 1]).all() and (di >= 0).all() and ((di > 0) | (np.diff(arr[:, 1]) > 0)).all())


def revisit_events(gt_pairs: Iterable[Any], tolerance: int = 5) -> list[np.ndarray]:
    """Group GT pairs into revisit events (connected components, linked within ``tolerance`` in both indices), in
    the order of their first pair (:func:`_event_labels`)."""
    gt = _pairs(gt_pairs)  # unique, sorted by (i, j)
    if len(gt) == 0:
        return []
    event = _event_labels(gt, int(tolerance))
    order = np.argsort(event, kind="stable")  # within an event, the pairs in order
    return np.split(gt[order], np.flatnonzero(np.diff(event[order])) + 1)


def _event_labels(gt: np.ndarray, tol: int) -> np.ndarray:
    """The revisit event of each pair of ``gt`` (unique, sorted by (i, j); see :func:`_pairs`) ``[n]``, numbered
    0, 1, ... in the order of each event's first pair.

    The links are not listed (a repeated loop's millions of pairs have ~(2 tolerance + 1)^2 neighbours each): within
    one newer frame ``i`` consecutive older frames link when at most ``tolerance`` apart, and each pair links to the
    first and the last pair within ``tolerance`` of it in each of the next ``tolerance`` rows.  That is exact: in a
    window of ``2 tolerance + 1`` frames a row holds at most two runs of linked pairs, and those two cover them."""
    n = len(gt)
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
    # gt is sorted by i: the order of each event's first pair is also that of its smallest i
    first = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))
    _, event = np.unique(first[labels], return_inverse=True)
    return event.reshape(-1)


def _near(a: np.ndarray, b: np.ndarray, tol: int) -> np.ndarray:
    """bool ``[len(a)]``: the pairs of ``a`` within ``tol`` of some pair of ``b`` in both indices (``b`` unique,
    sorted by (i, j)); one key lookup per row offset, in chunks of ``a``."""
    out = np.zeros(len(a), dtype=bool)
    if len(a) == 0 or len(b) == 0:
        return out
    i0 = min(int(a[:, 0].min()), int(b[:, 0].min()))
    j0 = min(int(a[:, 1].min()), int(b[:, 1].min()))
    width = max(int(a[:, 1].max()), int(b[:, 1].max())) - j0 + 2 * tol + 1  # j +- tol stays inside its row
    key = (b[:, 0] - i0) * width + (b[:, 1] - j0 + tol)  # sorted, as b
    for c0 in range(0, len(a), _LINK_CHUNK):
        ia, ja = a[c0:c0 + _LINK_CHUNK, 0] - i0, a[c0:c0 + _LINK_CHUNK, 1] - j0 + tol
        hit = out[c0:c0 + _LINK_CHUNK]
        for di in range(-tol, tol + 1):
            k = (ia + di) * width + ja
            hit |= np.searchsorted(key, k + tol, side="right") > np.searchsorted(key, k - tol)
    return out


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
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    tol = int(tolerance)
    det = _pairs(detected)
    gt = _pairs(gt_pairs)
    event = _event_labels(gt, tol) if len(gt) else np.zeros(0, dtype=np.int64)
    n_events = int(event.max()) + 1 if len(gt) else 0
    det_ok = _near(det, gt, tol)
    gt_ok = _near(gt, det, tol)
    ev_ok = np.zeros(n_events, dtype=bool)
    ev_ok[event[gt_ok]] = True  # an event is detected when one of its pairs is

    num_tp = int(det_ok.sum())
    precision = num_tp / len(det) if len(det) else float("nan")
    recall = float(ev_ok.sum()) / n_events if n_events else float("nan")
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
        "num_gt_events": n_events,
        "num_events_detected": int(ev_ok.sum()),
        "tolerance": int(tolerance),
        "false_positives": [tuple(int(v) for v in p) for p in det[~det_ok][:100]],
    }
