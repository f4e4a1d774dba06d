"""Clean point clouds: relative far filter, depth edges, multi-view consistency, sky, voxel downsampling."""
from __future__ import annotations

import logging

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from pvslam_core.outputs.cloud import (CloudFilter, category_mask, clean_mask, consistency_count, edge_mask,
                                       far_mask, voxel_downsample)
from pvslam_core.types import Category, PanopticSegmentation, Segment

H, W = 24, 32
INTR = torch.tensor([20.0, 20.0, 15.5, 11.5], dtype=torch.float64)


def _scene_depth(pose_wc: np.ndarray) -> np.ndarray:
    """Exact z-depth [H, W] of a camera looking at the plane z_w = 10 (a wall) with a box face z_w = 6 in front
    of it for x_w in [-1, 1] (brute-force ray casting in numpy, independent of pvslam's projection code)."""
    R = Rotation.from_quat(pose_wc[3:]).as_matrix()
    t = pose_wc[:3]
    fx, fy, cx, cy = INTR.numpy()
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    rays_c = np.stack([(xs - cx) / fx, (ys - cy) / fy, np.ones_like(xs)], -1)  # z_c = 1 on each ray
    rays_w = rays_c @ R.T
    depth = np.full((H, W), np.inf)
    for zw, xlim in ((10.0, None), (6.0, (-1.0, 1.0))):
        s = (zw - t[2]) / rays_w[..., 2]  # scale along the ray = z-depth (rays have z_c = 1)
        hit = s > 0
        if xlim is not None:
            xw = t[0] + s * rays_w[..., 0]
            hit &= (xw >= xlim[0]) & (xw <= xlim[1])
        depth = np.where(hit & (s < depth), s, depth)
    return depth


def _rig(k=5, step=0.3):
    poses = np.array([[step * i, 0.05 * i, 0, *Rotation.from_euler("y", 2 * i, degrees=True).as_quat()]
                      for i in range(k)])
    disps = np.stack([1.0 / _scene_depth(p) for p in poses])
    return torch.from_numpy(poses), torch.from_numpy(disps)


def test_far_filter_is_relative_and_scale_invariant():
    d = torch.full((2, H, W), 0.5, dtype=torch.float64)  # depth 2
    d[0, :2] = 0.01  # depth 100: far
    d[1, 5, 5] = 0.0  # invalid
    m = far_mask(d, factor=3.0)
    assert not m[0, :2].any() and m[0, 2:].all()
    assert not m[1, 5, 5] and m[1].sum() == H * W - 1
    # a monocular map at another scale keeps exactly the same pixels
    assert torch.equal(far_mask(d * 1e-3, 3.0), m) and torch.equal(far_mask(d * 1e3, 3.0), m)


def test_edge_filter_drops_pixels_next_to_a_depth_step():
    d = torch.full((1, H, W), 0.5, dtype=torch.float64)
    d[0, :, W // 2:] = 0.125  # depth 2 -> 8 at column 16
    m = edge_mask(d, ratio=1.5)
    assert not m[0, :, W // 2 - 1].any() and not m[0, :, W // 2].any()  # both sides of the step
    assert m[0, :, : W // 2 - 1].all() and m[0, :, W // 2 + 1:].all()
    # a smooth slanted surface (5 % disparity change per pixel) is kept
    ramp = (0.5 * 1.05 ** torch.arange(W, dtype=torch.float64)).expand(1, H, W)
    assert edge_mask(ramp, 1.5).all()


def test_consistency_counts_agreeing_neighbours():
    poses, disps = _rig()
    count = consistency_count(poses, disps, INTR, neighbours=2, consistency=0.02)
    mid = count[2]
    # exact depths: almost every pixel of the middle keyframe is confirmed by several neighbours
    assert (mid >= 2).float().mean() > 0.8, (mid >= 2).float().mean()
    # corrupt a patch of keyframe 2's depth by 30 %: those pixels lose every confirmation, the rest keep theirs
    bad = disps.clone()
    bad[2, 8:14, 4:10] *= 1.3
    count2 = consistency_count(poses, bad, INTR, neighbours=2, consistency=0.02)
    assert (count2[2, 9:13, 5:9] == 0).all()
    assert torch.equal(count2[2, 16:, 20:], count[2, 16:, 20:])
    # scale invariance: the same counts for the map scaled by 7 (poses' translation x7, depth x7)
    scaled = poses.clone()
    scaled[:, :3] *= 7
    assert torch.equal(consistency_count(scaled, disps / 7, INTR, 2, 0.02), count)


def _bilinear(img: np.ndarray, u: float, v: float) -> float:
    x0, y0 = int(np.floor(u)), int(np.floor(v))
    a, b = u - x0, v - y0
    val = 0.0
    for dy, wy in ((0, 1 - b), (1, b)):
        for dx, wx in ((0, 1 - a), (1, a)):
            y, x = y0 + dy, x0 + dx
            if 0 <= y < img.shape[0] and 0 <= x < img.shape[1]:
                val += wy * wx * img[y, x]
    return val


def test_consistency_against_a_brute_force_reprojection():
    """Pixel by pixel with a hand-written pinhole projection and bilinear lookup (numpy, no pvslam geometry)."""
    poses, disps = _rig(k=2)
    count = consistency_count(poses, disps, INTR, neighbours=1, consistency=0.02)
    fx, fy, cx, cy = INTR.numpy()
    P0, P1 = poses.numpy()
    R0, R1 = Rotation.from_quat(P0[3:]).as_matrix(), Rotation.from_quat(P1[3:]).as_matrix()
    expected = []
    for y in range(0, H, 3):
        for x in range(W):
            z = 1.0 / disps[0, y, x].item()
            Xw = R0 @ np.array([(x - cx) / fx * z, (y - cy) / fy * z, z]) + P0[:3]
            Xc = R1.T @ (Xw - P1[:3])
            u, v = fx * Xc[0] / Xc[2] + cx, fy * Xc[1] / Xc[2] + cy
            ok = False
            if Xc[2] > 0 and 0 <= u <= W - 1 and 0 <= v <= H - 1:
                d1 = _bilinear(disps[1].numpy(), u, v)
                ok = d1 > 0 and abs(1 / Xc[2] - d1) < 0.02 * max(1 / Xc[2], d1)
            expected.append(ok)
            assert bool(count[0, y, x] >= 1) == ok, (y, x, u, v)
    assert 0 < sum(expected) < len(expected)  # both outcomes occur: out of view, box edges, agreement


def test_sky_category_is_dropped():
    ids = torch.ones(2, H, W, dtype=torch.int64)
    ids[:, :5] = 7
    cats = [Category(1, "road", False), Category(3, "Sky", False)]
    segs = [PanopticSegmentation(ids[0], [Segment(1, 1, False), Segment(7, 3, False)]), None]
    m = category_mask(segs, cats, ["sky"], (2, H, W))
    assert not m[0, :5].any() and m[0, 5:].all() and m[1].all()


def test_clean_mask_combines_the_tests():
    poses, disps = _rig()
    d = disps.clone()
    d[:, 0, :] = 1e-4  # a far row in every keyframe (sky-like, near-zero disparity)
    keep = clean_mask(poses, d, INTR, CloudFilter(depth_factor=3.0, edge_ratio=None, min_views=0))
    assert not keep[:, 0].any() and keep[:, 1:].all()
    off = clean_mask(poses, d, INTR, CloudFilter(depth_factor=None, edge_ratio=None, min_views=0))
    assert off.all()


def test_voxel_downsample_matches_a_brute_force_grouping():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (2000, 3)).astype(np.float32)
    cols = rng.integers(0, 256, (2000, 3)).astype(np.uint8)
    extra = {"frame_index": np.arange(2000, dtype=np.int32)}
    out, ocols, oextra = voxel_downsample(pts, 0.25, cols, extra)
    groups: dict = {}
    for i, p in enumerate(pts):
        groups.setdefault(tuple(np.floor(p / 0.25).astype(int)), []).append(i)
    assert len(out) == len(groups)
    ref = {k: (pts[v].mean(0), np.round(cols[v].astype(float).mean(0)), v[0]) for k, v in groups.items()}
    for p, c, f in zip(out, ocols, oextra["frame_index"]):
        key = tuple(np.floor(pts[f] / 0.25).astype(int))  # the first point of the voxel
        np.testing.assert_allclose(p, ref[key][0], atol=1e-5)
        np.testing.assert_array_equal(c, ref[key][1])
        assert f == ref[key][2]
    first, _, _ = voxel_downsample(pts, 0.25, cols, extra, average=False)
    assert len(first) == len(groups) and all(any((q == pts).all(1)) for q in first[:20])


def test_old_ply_max_depth_key_still_loads_with_a_warning(caplog):
    from pvslam_core.config import load_config

    with caplog.at_level(logging.WARNING):
        cfg = load_config({"outputs": {"ply_max_depth": 50.0}})
    assert "ply_max_depth" in caplog.text
    assert cfg.pipeline.outputs.ply_depth_factor == 3.0
    assert "ply_max_depth" not in cfg.to_dict()["outputs"]
