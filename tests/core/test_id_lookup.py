"""pvslam_core/id_lookup.py against the general formulas its fast paths skip: ``unique_ids`` (a bincount for small
non-negative ids) equals ``np.unique``; ``lut`` (a table for small unique keys) equals the sorted binary search."""
import numpy as np
import pytest

from pvslam_core.id_lookup import lut, unique_ids


def ref_lut(keys, values, query, default):
    if len(keys) == 0:
        return np.full(query.shape, default, dtype=values.dtype if len(values) else np.int64)
    order = np.argsort(keys)
    k, v = keys[order], values[order]
    pos = np.searchsorted(k, query).clip(max=len(k) - 1)
    return np.where(k[pos] == query, v[pos], default)


def test_lut_equals_binary_search():
    rng = np.random.default_rng(0)
    for _ in range(200):
        K = int(rng.integers(0, 12))
        low = -3 if rng.random() < 0.2 else 0  # negative keys: the binary-search path
        high = 10**8 if rng.random() < 0.1 else 9000  # huge keys too
        keys = rng.choice(np.arange(low, 9000), K, replace=False).astype(np.int64)
        if high > 9000 and K:
            keys[0] = high
        values = rng.integers(-5, 10**6, K).astype(np.int64)
        q = rng.integers(-10, 9100, (37, 5))
        q[0, :min(K, 5)] = keys[:5]  # hits
        for default in (-1, 0):
            got, ref = lut(keys, values, q, default), ref_lut(keys, values, q, default)
            assert np.array_equal(got, ref) and got.dtype == ref.dtype


@pytest.mark.parametrize("case", ["small", "negative", "huge", "empty", "int32", "constant"])
def test_unique_ids_equals_np_unique(case):
    rng = np.random.default_rng(0)
    a = {
        "small": rng.integers(0, 9000, (48, 64)),
        "negative": rng.integers(-5, 50, (7, 9)),
        "huge": rng.integers(0, 10**9, (5, 5)),  # beyond the bincount range: np.unique
        "empty": np.zeros((0, 3), np.int64),
        "int32": rng.integers(0, 5, (4, 4)).astype(np.int32),
        "constant": np.full((3, 3), 7000, np.int64),
    }[case]
    got, ref = unique_ids(a), np.unique(a)
    assert np.array_equal(got, ref) and got.dtype == ref.dtype
