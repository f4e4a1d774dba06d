"""Look-ups over integer segment-id maps (numpy), shared by the panoptic outputs and the VPS heads.

Segment ids are small non-negative numbers (``category * 1000 + n``), so a table indexed by the id (or a
bincount) answers in one pass where the general route sorts or binary-searches every pixel; both functions take
that route only when it is cheaper and give exactly the general answer otherwise.
"""
from __future__ import annotations

import numpy as np

__all__ = ["lut", "unique_ids"]


def lut(keys: np.ndarray, values: np.ndarray, query: np.ndarray, default: int) -> np.ndarray:
    """values[keys == q] for each q in ``query`` (``default`` where absent)."""
    if len(keys) == 0:
        return np.full(query.shape, default, dtype=values.dtype if len(values) else np.int64)
    lo, hi = int(keys.min()), int(keys.max())
    if lo >= 0 and hi < 4 * query.size + 65536 and query.dtype.kind in "iu" and len(np.unique(keys)) == len(keys):
        # small unique non-negative keys (segment ids; the table costs less than the search up to a few entries
        # per query): a table lookup per pixel instead of a binary search (the last slot holds the default;
        # out-of-range queries are clipped onto it, -1 indexes it too)
        table = np.full(hi + 2, default, dtype=values.dtype)
        table[keys] = values
        return table[np.clip(query, -1, hi + 1)]
    order = np.argsort(keys)
    k, v = keys[order], values[order]
    pos = np.searchsorted(k, query).clip(max=len(k) - 1)
    return np.where(k[pos] == query, v[pos], default)


def unique_ids(ids: np.ndarray) -> np.ndarray:
    """``np.unique(ids)`` of an int id map: a bincount when the ids are small non-negative numbers (the usual
    ``category * 1000 + n``; 0.1 vs 1 ms at 320x240), else ``np.unique``."""
    flat = ids.reshape(-1)
    if flat.size and flat.dtype.kind in "iu":
        lo, hi = int(flat.min()), int(flat.max())
        if lo >= 0 and hi < 4 * flat.size + 65536:  # (a bincount longer than that costs more than the sort)
            return np.flatnonzero(np.bincount(flat, minlength=hi + 1)).astype(flat.dtype)
    return np.unique(flat)
