"""Forward warping of FPN features, against a per-cell Python reference."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.vps.fusion.feature_warp import forward_warp_features, sample_to_level, warp_pyramid


def _reference(feat, flow, depth):
    """Loop over sources in raster order; a later source overwrites unless a known smaller depth holds the cell."""
    B, C, h, w = feat.shape
    out = torch.zeros_like(feat)
    best = torch.full((B, h, w), float("inf"))
    hit = torch.zeros(B, h, w, dtype=torch.bool)
    for b in range(B):
        for y in range(h):
            for x in range(w):
                tx = int(torch.round(x + flow[b, 0, y, x]))
                ty = int(torch.round(y + flow[b, 1, y, x]))
                if not (0 <= tx < w and 0 <= ty < h):
                    continue
                z = float("inf") if depth is None or depth[b, y, x] <= 0 else float(depth[b, y, x])
                if depth is None or z <= best[b, ty, tx]:
                    best[b, ty, tx] = z
                    out[b, :, ty, tx] = feat[b, :, y, x]
                    hit[b, ty, tx] = True
    return out, hit


@pytest.mark.parametrize("with_depth", [False, True])
def test_forward_warp_matches_reference(with_depth):
    g = torch.Generator().manual_seed(1)
    feat = torch.randn(2, 3, 6, 7, generator=g)
    flow = torch.randn(2, 2, 6, 7, generator=g) * 2.0
    depth = None
    if with_depth:
        depth = torch.randint(0, 4, (2, 6, 7), generator=g).float()  # many ties, some unknown (0)
    got, hit = forward_warp_features(feat, flow, depth)
    ref, ref_hit = _reference(feat, flow, depth)
    assert torch.equal(hit, ref_hit)
    assert torch.equal(got, ref)


def test_pyramid_translation_moves_each_level_by_its_own_cells():
    # a frame of 64x32 (no resize), a uniform flow of +8 px in x: 2 cells at stride 4, 1 at stride 8
    H, W = 32, 64
    levels = {"p2": torch.randn(1, 4, 8, 16), "p3": torch.randn(1, 4, 4, 8)}
    flow = torch.zeros(1, 2, 4, 8)  # at 1/8 resolution, in frame pixels
    flow[:, 0] = 8.0
    out = warp_pyramid(levels, {"p2": 4, "p3": 8}, flow, (H, W), (H, W))
    assert torch.equal(out["p2"][..., 2:], levels["p2"][..., :-2])
    assert torch.equal(out["p2"][..., :2], torch.zeros(1, 4, 8, 2))
    assert torch.equal(out["p3"][..., 1:], levels["p3"][..., :-1])


def test_sample_to_level_hits_cell_centres():
    # a field that is its own x coordinate (frame pixels) sampled at the cell centres of a stride-4 level
    H, W = 16, 32
    xs = torch.arange(W, dtype=torch.float32).expand(H, W)[None, None]
    got = sample_to_level(xs, (4, 8), (4.0, 4.0), (H, W))
    assert torch.allclose(got[0, 0, 0], torch.arange(8) * 4 + 1.5)


def test_motion_field_moves_static_pixels_rigidly():
    """Stuff follows depth + poses, things keep the VO flow; vectors come back in frame pixels."""
    from pvslam_core.interfaces import MotionCue
    from pvslam_core.types import PanopticSegmentation, Segment
    from pvslam_plugins.vps.fusion.head import motion_field

    hf, wf, H, W = 6, 8, 24, 32  # cue at 1/4 of the frame
    ids = torch.full((H, W), 7000, dtype=torch.int64)  # stuff
    ids[8:16, 8:16] = 1001  # a thing
    prev = PanopticSegmentation(ids, [Segment(7000, 7, False), Segment(1001, 1, True)])
    fx = 5.0
    # camera moves 0.5 m along +x (T_wc translation): static points move by -fx * 0.5 / z cue pixels in x
    cue = MotionCue(flow=torch.full((2, hf, wf), 0.25), depth_prev=torch.full((hf, wf), 2.0),
                    pose_prev=torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64),
                    pose_cur=torch.tensor([0.5, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64),
                    intrinsics=torch.tensor([fx, fx, (wf - 1) / 2, (hf - 1) / 2]))
    flow, depth = motion_field(prev, cue, (H, W), rigid_static=True)
    assert flow.shape == (1, 2, hf, wf) and depth.shape == (1, hf, wf)
    thing = torch.zeros(hf, wf, dtype=torch.bool)
    thing[2:4, 2:4] = True  # the thing's cells at 1/4 resolution
    assert torch.allclose(flow[0, 0][~thing], torch.tensor(-fx * 0.5 / 2.0 * 4))  # rigid, x4 to frame pixels
    assert torch.allclose(flow[0, 1][~thing], torch.tensor(0.0), atol=1e-5)
    assert torch.allclose(flow[0, :, thing], torch.tensor(0.25 * 4))  # VO flow
    off, _ = motion_field(prev, cue, (H, W), rigid_static=False)
    assert torch.allclose(off, torch.tensor(1.0))
