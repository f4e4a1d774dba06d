"""The road search's back-off (road_prior.py): without a road the tracking search from scratch never finds a
plane, so after ROAD_BACKOFF_AFTER consecutive misses it skips a doubling number of frames (at most
ROAD_BACKOFF_MAX); a road coming into view is found again within that many frames and then searched every frame."""
from __future__ import annotations

import numpy as np

from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend
from pvslam_plugins.frontends.flow.road_prior import ROAD_BACKOFF_AFTER, ROAD_BACKOFF_MAX

import _flow_scenes as S
from test_road_depth import KFULL
from test_road_plane import _ground_texture, _render

N_WALL = 40  # frames of a textured wall moving diagonally: no road plane explains them better than DIS's flow


def _road(z: float, tex) -> np.ndarray:
    return np.repeat(_render(KFULL, (240, 320), z, tex)[..., None], 3, -1)


def _track(fe, frames) -> list[int]:
    """Track ``(index, image)`` pairs; the indices of the frames the road was searched on."""
    searched = []
    for k, img in frames:
        n = fe.road.stats["searches"]
        fe.track(S.frame(img, k), None)
        if fe.road.stats["searches"] > n:
            searched.append(k)
    return searched


def test_no_road_backs_off_and_a_road_is_found_again():
    fe = FlowFrontend(FlowFrontendConfig())  # road.enabled: the default
    big = S.texture()
    fe.add_keyframe(0, S.frame(S.base(big), 0), None)
    searched = _track(fe, [(k, S.shifted(big, 0.4 * k, -0.3 * k)) for k in range(1, N_WALL + 1)])
    st = fe.road.stats
    assert st["accepted"] == 0
    # every frame searched until ROAD_BACKOFF_AFTER misses, then 1, 2, 4, ... frames skipped, at most ROAD_BACKOFF_MAX
    n = ROAD_BACKOFF_AFTER
    assert searched[:n] == list(range(1, n + 1))
    gaps = list(np.diff(searched[n - 1:]))
    assert gaps[:3] == [2, 3, 5] and set(gaps[3:]) == {ROAD_BACKOFF_MAX + 1}, gaps
    assert st["searches"] + st["backed_off"] == N_WALL

    # a car drives onto a road (a new keyframe): its plane is found within ROAD_BACKOFF_MAX + 1 frames ...
    tex = _ground_texture()
    k0 = N_WALL + 1
    fe.add_keyframe(k0, S.frame(_road(10.0, tex), k0), None)
    road = [(k0 + j, _road(10.0 + 0.5 * j, tex)) for j in range(1, 21)]
    searched = _track(fe, road)
    assert st["accepted"] > 0 and searched[0] - k0 <= ROAD_BACKOFF_MAX + 1, searched
    # ... and from then on every frame is searched (from the plane's velocity) and found
    first = searched[0]
    assert searched == list(range(first, k0 + 21)) and st["accepted"] == len(searched), (searched, st)
