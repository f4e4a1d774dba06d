"""The road search's compiled loops (road_kernels.py) compute what numpy computes, bit for bit, and the tracking's
shortcuts (the backward verification on demand, the map rotation reused) give the results of the full work."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from pvslam_plugins.frontends.flow import road_kernels as RK
from pvslam_plugins.frontends.flow.road_plane import RoadPlane, _remap
from pvslam_core.geometry.projective import edge_transforms
from pvslam_plugins.frontends.flow.road_prior import _MapRotation

from test_road_plane import S_dis, road_pair  # noqa: F401  (the rendered road and plain DIS)


def _numpy_maps(A, B, KV, W, H):
    """The element-wise numpy formulas the kernels replace (the reference)."""
    z = A[2][None] + KV[:, 2:3] * B[None]
    inv = np.reciprocal(np.where(z > 1e-6, z, np.float32(np.nan)))
    mx = (A[0][None] + KV[:, 0:1] * B[None]) * inv
    my = (A[1][None] + KV[:, 1:2] * B[None]) * inv
    return mx, my, (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)


@pytest.mark.parametrize("seed", range(6))
def test_candidate_maps_and_costs_are_numpys_bit_for_bit(seed):
    """Random cameras, rotations and candidates (some behind the camera, some leaving the view): the maps, the
    inside mask and the masked differences equal numpy's exactly, and so the costs do."""
    rng = np.random.default_rng(seed)
    H, W = int(rng.integers(60, 300)), int(rng.integers(80, 900))
    g0 = cv2.GaussianBlur(rng.integers(0, 255, (H, W), dtype=np.uint8), (5, 5), 1)
    g1f = np.roll(g0, 2, 0).astype(np.float32)
    f = W * rng.uniform(0.4, 1.2)
    K = np.array([[f, 0, W / 2 + rng.normal()], [0, f, H / 2 + rng.normal()], [0, 0, 1.0]])
    R = cv2.Rodrigues(rng.normal(0, 0.05, 3))[0]
    rp = RoadPlane()
    level = rp._level(g0, K, R, 2, int(H / 2 + 0.03 * H))
    A, B, ref, _ = level
    V = np.array([0, 0, -rng.uniform(0.02, 8)]) + rng.normal(0, 0.3, (int(rng.choice([1, 6, 289])), 3))
    V[0] = [0.0, 0.0, 0.0]
    V[-1] = [0.0, 0.0, 5.0]  # reversing far: much of the view behind or outside
    KV = (V @ K.T).astype(np.float32)
    mx, my, inside = RK.candidate_maps(A, B, KV, np.float32(W - 1), np.float32(H - 1))
    nx, ny, nin = _numpy_maps(A, B, KV, W, H)
    assert np.array_equal(mx, nx, equal_nan=True) and np.array_equal(my, ny, equal_nan=True)
    assert np.array_equal(inside, nin) and inside.any() and not inside.all()
    s = _remap(g1f, mx, my, cv2.BORDER_CONSTANT)
    d = RK.masked_abs_diff(s, ref, inside)
    nd = np.where(nin, np.abs(s - ref[None]), 0.0)
    assert d.dtype == nd.dtype == np.float32 and np.array_equal(d, nd)
    n_in = nin.sum(1)
    costs = np.where(n_in >= rp.min_inside * B.size, nd.sum(1) / np.maximum(n_in, 1), np.inf)
    assert np.array_equal(rp._block_costs(g1f, K, V, level), costs)


def test_flow_length_is_numpys_norm_bit_for_bit():
    rng = np.random.default_rng(3)
    for scale in (1e-3, 1.0, 40.0, 1e4):
        f = (rng.standard_normal((57, 131, 2)) * scale).astype(np.float32)
        f[0, 0, 0], f[1, 1, 1] = np.inf, np.nan
        assert np.array_equal(RK.flow_length(f), np.linalg.norm(f, axis=-1), equal_nan=True)


def test_backward_verification_on_demand_gives_the_eager_result(road_pair):  # noqa: F811
    """``defer_backward``: one DIS call (the forward one) during apply, the backward one only when asked, and then
    the residuals of the eager call exactly."""
    K, g0, g1, _, _ = road_pair
    z = np.zeros(g0.shape + (2,), np.float32)
    calls = []

    def verify(pairs):
        calls.append(len(pairs))
        return [S_dis(a, c) for a, c in pairs]

    eager = RoadPlane().apply(g0, g1, z, z, K, np.eye(3), verify=verify)
    assert calls == [2]
    lazy = RoadPlane().apply(g0, g1, z, z, K, np.eye(3), verify=verify, defer_backward=True)
    assert calls == [2, 1] and callable(lazy[6])
    for a, b in zip(eager[:6], lazy[:6]):
        assert np.array_equal(a, b)
    assert np.array_equal(lazy[6](), eager[6]) and calls == [2, 1, 1]


def _direct(g, a: int, b: int) -> np.ndarray:
    """The rotation from camera ``a`` to camera ``b`` straight from the poses (float64)."""
    return edge_transforms(g.poses.double(), torch.tensor([a]), torch.tensor([b]))[0][0].numpy()


class _Graph:
    def __init__(self, poses):
        self.poses = poses


def test_map_rotation_is_reused_until_a_pose_moves():
    """The cached rotation equals the direct one; it is recomputed as soon as either pose changes."""
    rng = np.random.default_rng(0)
    q = torch.tensor(rng.normal(size=(3, 4)))
    q = q / q.norm(dim=1, keepdim=True)
    g = _Graph(torch.cat([torch.tensor(rng.normal(size=(3, 3))), q], 1))
    rot = _MapRotation()
    first = rot(g, 0, 1)
    assert np.array_equal(first, _direct(g, 0, 1))
    assert rot(g, 0, 1) is first and not first.flags.writeable  # the same poses: not recomputed; shared
    g.poses = g.poses.clone()
    g.poses[1, 3:] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=g.poses.dtype)  # the second camera turns
    again = rot(g, 0, 1)
    assert again is not first and np.array_equal(again, _direct(g, 0, 1))
    assert not np.allclose(again, first)
    assert np.array_equal(rot(g, 1, 2), _direct(g, 1, 2))
