"""The road's inverse-depth prior (``road.depth_weight``, road_prior.py): the camera height is measured only when
the map's road depth and its motion agree, and the prior sits on the verified road pixels at that height."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pvslam_core.slam.graph import FrameGraph
from pvslam_plugins.frontends.flow import road_prior as road_module
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend

import _flow_scenes as S
from test_road_plane import CAM_H, _ground_texture, _render

KFULL = np.array([[288.0, 0, 159.5], [0, 288.0, 119.5], [0, 0, 1]])
INTR_BA = torch.tensor([36.0, 36.0, 19.5, 14.5])  # 1/8 of the 320x240 images
STEP = 2.0  # m between frames (72 km/h at 10 Hz)
A0 = 10.0


def _drive(cfg: FlowFrontendConfig):
    """A frontend that tracked 8 frames 2 m apart over the textured road, each a keyframe."""
    tex = _ground_texture()
    fe = FlowFrontend(cfg)
    zs = [10.0 + STEP * k for k in range(8)]
    for k, z in enumerate(zs):
        f = S.frame(np.repeat(_render(KFULL, (240, 320), z, tex)[..., None], 3, -1), k)
        if k:
            fe.track(f, None)
        fe.add_keyframe(k, f, None)
    return fe, zs


@pytest.fixture(scope="module")
def drive():
    return _drive(FlowFrontendConfig(road={"depth_weight": A0}))  # the road plane and its verification: defaults


def _graph(zs, scale: float, depth_factor: float) -> FrameGraph:
    """The true keyframes at map scale ``scale`` (positions x scale); road depths also x ``depth_factor``."""
    g = FrameGraph(30, 40, INTR_BA)
    ray = ((torch.arange(30, dtype=torch.float32) - 14.5) / 36.0)[:, None].expand(30, 40)
    disp = torch.where(ray > 0.02, ray / (CAM_H * scale * depth_factor), torch.full_like(ray, 0.01))
    for k, z in enumerate(zs):
        pose = torch.tensor([0.0, 0.0, z * scale, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
        assert g.add_keyframe(k, 0.1 * k, pose, disp.clone()) == k
    return g


def _observe(fe, g):
    """The frontend's edge observations and, as the mapper asks for them, the depth prior of every keyframe."""
    n = g.n
    obs = fe.observe(g, torch.arange(n - 1), torch.arange(1, n))
    assert obs.disp_prior is None  # the prior is per keyframe: the mapper asks for it (Frontend.depth_prior)
    got = fe.depth_prior(g, torch.arange(n))
    if got is not None:
        assert got.ids.tolist() == list(range(n))
    return None if got is None else (got.disp, got.weight)


def test_no_height_while_road_depth_and_motion_disagree(drive):
    fe, zs = drive
    fe.road.height = None
    fe.road.height_tries.clear()
    assert _observe(fe, _graph(zs, scale=0.05, depth_factor=8.0)) is None  # the road 8x too far for the motion
    assert fe.road.height is None
    (n, by_motion, by_depth), = fe.road.height_tries
    assert n == 8 and by_depth / by_motion == pytest.approx(8.0, rel=0.1)


def test_height_and_prior_where_they_agree(drive):
    fe, zs = drive
    fe.road.height = None
    fe.road.height_tries.clear()
    scale = 0.05
    prior, alpha = _observe(fe, _graph(zs, scale=scale, depth_factor=1.0))
    assert fe.road.height == pytest.approx(CAM_H * scale, rel=0.05)
    assert prior.shape == alpha.shape == (8, 30, 40)
    assert float(alpha[0].abs().sum()) == 0.0  # the first keyframe was never tracked: no road pixels known
    ray = ((torch.arange(30, dtype=torch.float32) - 14.5) / 36.0)[:, None].expand(30, 40)
    lower = (ray > 0.3)  # the near road
    for k in range(1, 8):
        on = alpha[k] > 0
        assert float(on[lower].float().mean()) > 0.6  # most of the near road is verified road
        assert not bool(on[ray <= 0].any())  # never above the horizon
        torch.testing.assert_close(prior[k][on], (ray / fe.road.height)[on])
        rel = alpha[k][on] * prior[k][on] ** 2 / A0  # the relative weight: the verification weight in [0, 1]
        assert float(rel.max()) <= 1.0 + 1e-5 and float(rel.median()) > 0.3
    # only the asked keyframes; none with road pixels: no prior
    got = fe.depth_prior(_graph(zs, scale=scale, depth_factor=1.0), torch.tensor([5, 2]))
    p2, a2 = got.disp, got.weight
    torch.testing.assert_close(a2, alpha[[5, 2]])
    torch.testing.assert_close(p2, prior[[5, 2]])
    assert fe.depth_prior(_graph(zs, scale=scale, depth_factor=1.0), torch.tensor([0])) is None
    # measured once: a later map at another scale does not move it
    h = fe.road.height
    _observe(fe, _graph(zs, scale=0.2, depth_factor=1.0))
    assert fe.road.height == h


def test_one_camera_height_per_map(drive):
    """A distance prior measured first gives the depth prior its camera height: two priors at two heights would hold
    the map at two scales.  The depth prior's own agreement gate still decides when it starts."""
    fe, zs = drive
    scale = 0.05
    h_distance = CAM_H * scale * 1.08  # the map's motion read 8 % more when the distance prior measured it
    try:
        fe.road.height_motion = h_distance
        fe.road.height = None
        assert _observe(fe, _graph(zs, scale=scale, depth_factor=8.0)) is None  # the gate: still closed
        assert fe.road.height is None
        prior, alpha = _observe(fe, _graph(zs, scale=scale, depth_factor=1.0))
        (_, _, by_depth), = list(fe.road.height_tries)[-1:]
        assert by_depth == pytest.approx(CAM_H * scale, rel=0.05)  # its own readings: the map's scale
        assert fe.road.height == h_distance  # ... but the distance prior's height
        ray = ((torch.arange(30, dtype=torch.float32) - 14.5) / 36.0)[:, None].expand(30, 40)
        on = alpha[3] > 0
        torch.testing.assert_close(prior[3][on], (ray / h_distance)[on])
    finally:
        fe.road.height_motion = None
        fe.road.height = None


def test_prior_without_the_verified_plane_does_nothing(monkeypatch):
    """road.depth_weight only acts on verified plane pixels: with the verification off (ROAD_VERIFY: no verification
    weights) or road.enabled off the frontend gives the BA no prior, and such a config loads."""
    for verify, cfg in ((False, FlowFrontendConfig()), (True, FlowFrontendConfig(road={"enabled": False}))):
        monkeypatch.setattr(road_module, "ROAD_VERIFY", verify)
        assert cfg.road.depth_weight > 0
        fe, zs = _drive(cfg)
        assert fe.road is None or not any(fe.road.has_road_pixels(k) for k in range(len(zs)))
        assert _observe(fe, _graph(zs, 0.05, 1.0)) is None and (fe.road is None or fe.road.height is None)
    assert FlowFrontendConfig(road={"depth_weight": 0.0}).road.depth_weight == 0.0
    with pytest.raises(ValueError, match="greater than or equal to 0"):
        FlowFrontendConfig(road={"depth_weight": -1.0})
