"""The distance prior from the road's motion (``road.distance_weight``, road_prior.py): consecutive keyframes
tracked over the road are ``h |v|`` apart, ``v`` the road's translation in camera heights and ``h`` the camera
height in map units measured once from the map's motion - whatever the map's road depth says."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.frontends.flow.config import FlowFrontendConfig

from test_road_depth import STEP, _drive, _graph
from test_road_plane import CAM_H

W = 300.0


@pytest.fixture(scope="module")
def drive():
    return _drive(FlowFrontendConfig(road={"distance_weight": W}))


def test_consecutive_keyframes_get_the_roads_distance(drive):
    fe, zs = drive
    fe.road.height_motion = None
    scale = 0.05
    # the map's road 8x too far for its motion: the depth prior's gate stays closed, the distance prior does not
    # need the road depth
    g = _graph(zs, scale=scale, depth_factor=8.0)
    got = fe.distance_prior(g, torch.arange(8))
    ii, jj, dist, alpha = got.ii, got.jj, got.dist, got.weight
    assert fe.road.height_motion == pytest.approx(CAM_H * scale, rel=0.05)
    # keyframe 0 was never tracked (no plane motion into it), so the pairs start at (0, 1) only if 1 chains to 0
    assert (jj - ii).tolist() == [1] * len(ii) and len(ii) >= 6
    torch.testing.assert_close(dist, torch.full_like(dist, STEP * scale), rtol=0.05, atol=0)
    assert dist.dtype == torch.float64 and alpha.tolist() == [W] * len(ii)
    assert fe.depth_prior(g, torch.arange(8)) is None and fe.road.height is None


def test_only_consecutive_pairs_among_the_asked_and_measured_once(drive):
    fe, zs = drive
    fe.road.height_motion = None
    fe.distance_prior(_graph(zs, scale=0.05, depth_factor=1.0), torch.arange(8))
    h = fe.road.height_motion
    g = _graph(zs, scale=0.06, depth_factor=1.0)  # a later map at another scale does not move it
    got = fe.distance_prior(g, torch.tensor([5, 2, 3]))
    ii, jj, dist = got.ii, got.jj, got.dist
    assert fe.road.height_motion == h
    assert ii.tolist() == [2] and jj.tolist() == [3]
    torch.testing.assert_close(dist, torch.tensor([STEP * 0.05], dtype=torch.float64), rtol=0.05, atol=0)
    assert fe.distance_prior(g, torch.tensor([1, 4, 6])) is None  # no consecutive pair
    # a map 4x off the road's distances: the plane's motion is taken for wrong there, no prior (ROAD_DIST_AGREE)
    assert fe.distance_prior(_graph(zs, scale=0.2, depth_factor=1.0), torch.arange(8)) is None


def test_no_height_from_pairs_that_disagree(drive):
    """The height comes only from three pairs that tell one height: with keyframe 4 placed 2 steps from keyframe 3
    (and 0 from 5) the pairs (3, 4), (4, 5) disagree, and it waits."""
    fe, zs = drive
    fe.road.height_motion = None
    uneven = list(zs)
    uneven[4] = zs[5]
    assert fe.distance_prior(_graph(uneven, scale=0.05, depth_factor=1.0), torch.arange(8)) is None
    assert fe.road.height_motion is None
    assert fe.distance_prior(_graph(zs, scale=0.05, depth_factor=1.0), torch.arange(8)) is not None


def test_no_distance_prior_when_off():
    for cfg in (FlowFrontendConfig(road={"distance_weight": 0.0}),
                FlowFrontendConfig(road={"enabled": False, "distance_weight": W})):
        fe, zs = _drive(cfg)
        assert fe.distance_prior(_graph(zs, 0.05, 1.0), torch.arange(8)) is None
        assert fe.road is None or fe.road.height_motion is None
    with pytest.raises(ValueError, match="greater than or equal to 0"):
        FlowFrontendConfig(road={"distance_weight": -1.0})
