"""The road plane's search on frames larger than OpenCV's remap takes in one call (a map side of 32767 or more)."""
from __future__ import annotations

import numpy as np

from pvslam_plugins.frontends.flow import road_plane as RP
from pvslam_plugins.frontends.flow.road_plane import RoadPlane, flow_intrinsics

from test_road_plane import _ground_texture, _render


def _pair(shape, f):
    H, W = shape
    K = flow_intrinsics(f, f, W - 0.5, H - 0.5, 0.5, 0.5)  # input image 2W x 2H, flow at half of it
    tex = _ground_texture()
    return K, _render(K, shape, 10.0, tex), _render(K, shape, 11.0, tex)


def test_a_tall_frame_is_searched_without_an_opencv_assertion():
    """1200x600 at the flow resolution: the fine level's every 2nd pixel of the ground rows is 63 000 pixels per
    candidate, more than one remap takes (cv2.error on such frames before)."""
    K, g0, g1 = _pair((1200, 600), 2000.0)
    found = RoadPlane().search(g0, g1, K, np.eye(3))
    assert found is not None
    v, cost, r0 = found
    assert np.isfinite(cost) and v[2] < 0, v  # a forward motion


def test_blocks_give_the_same_search(monkeypatch):
    """Candidates in blocks and remaps in column blocks change no value: the search is bit-identical."""
    K, g0, g1 = _pair((120, 160), 288.0)
    want = RoadPlane().search(g0, g1, K, np.eye(3))
    monkeypatch.setattr(RP, "_REMAP_MAX", 97)
    monkeypatch.setattr(RP, "_COST_BLOCK", 5000)
    got = RoadPlane().search(g0, g1, K, np.eye(3))
    assert want is not None and np.array_equal(got[0], want[0]) and got[1:] == want[1:]
