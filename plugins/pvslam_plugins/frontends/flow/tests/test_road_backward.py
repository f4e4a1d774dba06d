"""The road's chain grown backwards (``ROAD_BACKWARD``, road_prior.py): keyframes tracked before the road was first
found join the chain from its velocity, so the distance prior reaches the map's first stretch too."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from pvslam_plugins.frontends.flow import road_prior as road_module
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend
from pvslam_plugins.frontends.flow.road_plane import RoadChain

import _flow_scenes as S
from test_road_depth import KFULL, STEP, _graph
from test_road_plane import CAM_H, _ground_texture, _render

BLIND = 3  # tracked frames that search no road (the back-off), as where the search from scratch loses to DIS


def _drive() -> FlowFrontend:
    """8 keyframes 2 m apart over the textured road, the map's poses the true ones (scale 0.05); frames 1..BLIND
    track without a road, so keyframes 0..BLIND begin chains of their own."""
    tex = _ground_texture()
    zs = [10.0 + STEP * k for k in range(8)]
    fe = FlowFrontend(FlowFrontendConfig(road={"distance_weight": 100.0}))
    fe._graph = _graph(zs, scale=0.05, depth_factor=1.0)  # the map the rotations come from
    for k, z in enumerate(zs):
        f = S.frame(np.repeat(_render(KFULL, (240, 320), z, tex)[..., None], 3, -1), k)
        if k:
            fe.track(f, None)
        fe.add_keyframe(k, f, None)
        if k == 0:
            fe.road._skip = BLIND
    return fe


@pytest.mark.parametrize("backward", [True, False])
def test_keyframes_before_the_first_road_join_its_chain(monkeypatch, backward):
    monkeypatch.setattr(road_module, "ROAD_BACKWARD", backward)
    fe = _drive()
    chain, v_true = fe.road._chain, np.array([0.0, 0.0, -STEP / CAM_H])
    assert fe.road.stats["backed_off"] == BLIND
    for a in range(BLIND, 7):  # the tracking's own chain from the first road found on
        np.testing.assert_allclose(chain.prior(a, a + 1), v_true, atol=0.05 * STEP / CAM_H)
    got = fe.distance_prior(fe._graph, torch.arange(8))
    if backward:
        assert chain.first(0) and chain.same(0, 7)
        for a in range(BLIND):
            np.testing.assert_allclose(chain.prior(a, a + 1), v_true, atol=0.05 * STEP / CAM_H)
        assert got.ii.tolist() == list(range(7)) and got.jj.tolist() == list(range(1, 8))
        torch.testing.assert_close(got.dist, torch.full_like(got.dist, STEP * 0.05), rtol=0.05, atol=0)
    else:
        assert all(chain.prior(a, a + 1) is None for a in range(BLIND))
        assert got is None or min(got.ii.tolist()) >= BLIND  # here too few road pairs to measure the height


def test_a_search_that_leaves_the_velocity_stops_the_walk(monkeypatch):
    """The second backward search settles 2x the velocity's motion, beyond the prior's tolerance: the keyframe it was
    for stays out of the chain, and so do the keyframes before it; the one after it joined."""
    real_back, real_search = road_module.RoadPrior.extend_back, road_module.RoadPlane.search
    calls = []

    def back(self, *args):
        calls.append(0)  # backward searches are counted from here
        try:
            return real_back(self, *args)
        finally:
            calls.clear()

    def search(self, g0, g1, K, R, prior=None):
        out = real_search(self, g0, g1, K, R, prior)
        if calls:
            calls.append(1)
            if len(calls) == 3 and out is not None:
                return 2.0 * prior, out[1], out[2]
        return out

    monkeypatch.setattr(road_module.RoadPrior, "extend_back", back)
    monkeypatch.setattr(road_module.RoadPlane, "search", search)
    chain = _drive().road._chain
    assert chain.same(BLIND - 1, BLIND) and chain.first(BLIND - 1)
    assert all(chain.prior(a, a + 1) is None for a in range(BLIND - 1))


def test_road_chain_grows_backwards():
    """A keyframe prepended to a chain: its priors compose with the chain's as if it had been tracked first."""
    ch = RoadChain()
    R0, R1 = (cv2.Rodrigues(np.array(w))[0] for w in ([0.0, 0.04, 0.0], [0.01, -0.02, 0.0]))
    v0, v1 = np.array([0.02, 0.0, -1.1]), np.array([-0.01, 0.01, -1.2])
    ch.add(4, None, None, None)
    ch.add(5, None, None, None)
    ch.add(6, 5, R1, v1)
    assert ch.first(4) and ch.first(5) and not ch.same(4, 5)
    ch.prepend(4, 5, R0, v0)
    assert ch.first(4) and not ch.first(5) and ch.same(4, 6)
    np.testing.assert_allclose(ch.prior(4, 5), v0, atol=1e-12)
    np.testing.assert_allclose(ch.prior(4, 6), R1 @ v0 + v1, atol=1e-12)
    np.testing.assert_allclose(ch.prior(5, 6), v1, atol=1e-12)
