"""``forward_warp`` against a brute-force per-target reference (many collisions, equal depths, unknown depths), and
the head's working resolution (``warp_max_side``) against full resolution."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pvslam_core.interfaces import MotionCue
from pvslam_core.types import Frame, Intrinsics, PanopticSegmentation, Segment
from pvslam_plugins.vps.warp_iou.config import WarpIoUConfig
from pvslam_plugins.vps.warp_iou.head import WarpIoUHead
from pvslam_plugins.vps.warp_iou.warp import forward_warp


def reference_warp(ids, flow, depth, mask, splat):
    """The documented rule, one source at a time: each source claims its rounded target (bilinear: then its other
    integer neighbours, only where no source's own rounded target landed); per target the nearest depth wins
    (unknown depth = farthest), ties and no depth go to raster order (first source with depth, last without)."""
    h, w = ids.shape
    cand = {}  # target -> list of (key, value), lower key wins
    own = set()
    srcs = [(y, x) for y in range(h) for x in range(w) if ids[y, x] != 0 and (mask is None or mask[y, x])]
    n = len(srcs)
    for k, (y, x) in enumerate(srcs):
        tx, ty = x + float(flow[0, y, x]), y + float(flow[1, y, x])
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


def _frame(ids: np.ndarray, index: int) -> tuple[Frame, PanopticSegmentation]:
    h, w = ids.shape
    k = Intrinsics(fx=100.0, fy=100.0, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)
    img = torch.zeros(3, h, w, dtype=torch.uint8)
    segs = [Segment(int(s), int(s) // 1000, int(s) // 1000 == 3) for s in np.unique(ids) if s]
    return Frame(index=index, timestamp=0.1 * index, image=img, intrinsics=k), PanopticSegmentation(
        torch.from_numpy(ids), segs)


def test_working_resolution_keeps_ids_of_moving_things():
    """Two cars drive right by 6 px a frame; at half the working resolution they keep their ids as at full
    resolution, output ids stay full size, and last_warped is reported at full size."""
    h, w = 60, 80
    heads = {side: WarpIoUHead(WarpIoUConfig(warp_max_side=side)) for side in (None, 40)}
    states = {side: None for side in heads}
    for t in range(5):
        ids = np.full((h, w), 1000, np.int64)
        ids[20:36, 4 + 6 * t: 20 + 6 * t] = 3001 + t  # segmenter ids change every frame
        ids[40:52, 30 + 6 * t: 40 + 6 * t] = 3101 - t
        fr, seg = _frame(ids, t)
        flow = torch.zeros(2, 15, 20)
        flow[0] = 6.0 / 4  # the cue's flow at 1/4 resolution (pixels of that resolution)
        for side, head in heads.items():
            states[side] = head.update(states[side], fr, seg, MotionCue(flow=flow) if t else MotionCue())
        full, half = states[None].panoptic.ids, states[40].panoptic.ids
        assert full.shape == half.shape == (h, w)
        assert bool((full == half).all())
        assert heads[40].last_warped is None if t == 0 else heads[40].last_warped.shape == (h, w)
    assert len({int(v) for v in torch.unique(states[40].panoptic.ids)}) == 3  # road + two tracked cars
