"""``forward_warp`` against a brute-force per-target reference (many collisions, equal depths, unknown depths)."""
from __future__ import annotations

import numpy as np
import pytest

from pvslam_plugins.vps.warp_iou.warp import forward_warp


def reference_warp(ids, flow, depth, mask, splat):
    """The documented rule, one source at a time: each source claims its rounded target (bilinear: then its other
    integer neighbours, only where no source's own rounded target landed); per target the nearest depth wins
    (unknown depth = farthest), ties and no depth go to raster order (first source with depth, last without); a source
    whose target is not finite writes nothing."""
    h, w = ids.shape
    cand = {}  # target -> list of (key, value), lower key wins
    own = set()
    srcs = [(y, x) for y in range(h) for x in range(w) if ids[y, x] != 0 and (mask is None or mask[y, x])]
    n = len(srcs)
    for k, (y, x) in enumerate(srcs):
        tx, ty = x + float(flow[0, y, x]), y + float(flow[1, y, x])
        if not (np.isfinite(tx) and np.isfinite(ty)):
            continue
        if depth is not None:
            z = float(depth[y, x]) if depth[y, x] > 0 else np.inf
            key = (z, k)
        else:
            key = (0.0, n - 1 - k)
        rx, ry = int(np.rint(tx)), int(np.rint(ty))
        if 0 <= rx < w and 0 <= ry < h:
            cand.setdefault((ry, rx), []).append((key, ids[y, x]))
            own.add((ry, rx))
    out = np.zeros((h, w), ids.dtype)
    for t, lst in cand.items():
        out[t] = min(lst)[1]
    if splat == "bilinear":
        spill = {}
        for k, (y, x) in enumerate(srcs):
            tx, ty = x + float(flow[0, y, x]), y + float(flow[1, y, x])
            if not (np.isfinite(tx) and np.isfinite(ty)):
                continue
            key = (float(depth[y, x]) if depth[y, x] > 0 else np.inf, k) if depth is not None else (0.0, n - 1 - k)
            rx, ry = int(np.rint(tx)), int(np.rint(ty))
            x0, y0 = int(np.floor(tx)), int(np.floor(ty))
            for qx, qy in ((x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1)):
                if (qx, qy) == (rx, ry) or not (0 <= qx < w and 0 <= qy < h) or (qy, qx) in own:
                    continue
                spill.setdefault((qy, qx), []).append((key, ids[y, x]))
        for t, lst in spill.items():
            out[t] = min(lst)[1]
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("splat", ["nearest", "bilinear"])
@pytest.mark.parametrize("with_depth", [False, True])
def test_forward_warp_matches_brute_force(seed, splat, with_depth):
    rng = np.random.default_rng(seed)
    h, w = 9, 11
    ids = rng.integers(0, 4, (h, w)).astype(np.int64) * 1000 + rng.integers(0, 3, (h, w))
    flow = rng.normal(0, 2.0, (2, h, w)).astype(np.float32)
    flow[:, ::3, ::2] = np.round(flow[:, ::3, ::2])  # many exact collisions
    depth = None
    if with_depth:
        depth = rng.choice([0.0, 1.0, 2.0, 2.0, 3.5], (h, w)).astype(np.float32)  # ties and unknown depth
    mask = rng.random((h, w)) > 0.2
    got = forward_warp(ids, flow, depth, mask, splat=splat)
    np.testing.assert_array_equal(got, reference_warp(ids, flow, depth, mask, splat))


@pytest.mark.parametrize("splat", ["nearest", "bilinear"])
@pytest.mark.parametrize("depth_dtype", [np.float32, np.float64, None])
def test_every_source_written_and_odd_inputs(splat, depth_dtype):
    """No void and no mask (every pixel a source), a flow that leaves the image and holds NaN / inf, negative
    depths, float64 depths: still the brute-force rule."""
    rng = np.random.default_rng(7)
    h, w = 12, 10
    ids = 1000 + rng.integers(1, 4, (h, w)).astype(np.int64)
    flow = rng.normal(0, 4.0, (2, h, w)).astype(np.float32)
    flow[0, 0, :3] = np.nan
    flow[1, 5, 2] = np.inf
    depth = None if depth_dtype is None else rng.choice([-1.0, 0.0, 1.0, 2.0, 2.0], (h, w)).astype(depth_dtype)
    got = forward_warp(ids, flow, depth, None, splat=splat)
    np.testing.assert_array_equal(got, reference_warp(ids, flow, depth, None, splat))
