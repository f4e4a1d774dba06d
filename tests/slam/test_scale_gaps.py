"""Stretches of keyframes whose depth was never measured (pvslam_core/slam/scale_gaps.py): where they are, the turn
across them, the warning, and the measured share each keyframe had after its own window BA (observed.py)."""
import logging
import math

import pytest
import torch

from pvslam_core.slam.graph import FrameGraph
from pvslam_core.slam.observed import ObservedMasks
from pvslam_core.slam.scale_gaps import find_scale_gaps, graph_scale_gaps, horizontal_fov_deg


def _yaw_poses(deg):
    """Camera-to-world poses at the origin turned ``deg[k]`` degrees about the camera's y axis."""
    half = torch.tensor([math.radians(d) / 2 for d in deg], dtype=torch.float64)
    z = torch.zeros_like(half)
    return torch.stack([z, z, z, z, torch.sin(half), z, torch.cos(half)], dim=1)


def test_the_field_of_view():
    assert horizontal_fov_deg(272.0, 320) == pytest.approx(60.93, abs=0.01)
    assert horizontal_fov_deg(160.0, 320) == pytest.approx(90.0)


def test_a_turn_on_the_spot_wider_than_the_view():
    """Keyframes 0-2 measured, 3-7 turning 15 deg each with their depth unmeasured (two of them not at all), 8-9
    measured again: one gap, keyframes 3-7, turned 90 deg between keyframes 2 and 8, wider than a 61 deg view."""
    deg = [0, 0, 0, 15, 30, 45, 60, 75, 90, 90]
    shares = [1.0, 0.9, 0.8, 0.3, 0.02, 0.0, 0.2, 0.4, 0.6, 0.9]
    frames = [10 * k for k in range(10)]
    gaps = find_scale_gaps(_yaw_poses(deg), shares, frames, [f / 10 for f in frames], [0] * 10, fov_deg=61.0)
    assert len(gaps) == 1
    g = gaps[0]
    assert (g.first_frame, g.last_frame, g.keyframes, g.unmeasured) == (30, 70, 5, 2)
    assert (g.first_time, g.last_time) == (3.0, 7.0)
    assert g.turn_deg == pytest.approx(90.0) and g.beyond_fov
    assert g.as_dict()["beyond_fov"] is True


def test_what_is_not_a_gap():
    deg = [0, 0, 15, 30, 45, 45]
    frames = list(range(6))
    # a dip that never reaches "unmeasured" (a drive's newest keyframes: 0.35-0.49)
    assert find_scale_gaps(_yaw_poses(deg), [1, 0.4, 0.3, 0.35, 0.6, 1], frames, frames, [0] * 6, 61.0) == []
    # unmeasured to the end: nothing after it to compare
    assert find_scale_gaps(_yaw_poses(deg), [1, 0.9, 0.0, 0.0, 0.0, 0.0], frames, frames, [0] * 6, 61.0) == []
    # a new fragment starts inside it: the two sides are different maps
    assert find_scale_gaps(_yaw_poses(deg), [1, 0.9, 0.0, 0.0, 1, 1], frames, frames, [0, 0, 0, 1, 1, 1], 61.0) == []


def test_a_narrow_gap_is_reported_but_not_beyond_the_view():
    deg = [0, 0, 10, 20, 30]
    gaps = find_scale_gaps(_yaw_poses(deg), [1, 1, 0.0, 0.0, 1], [0, 1, 2, 3, 4], [0, 1, 2, 3, 4], [0] * 5,
                           fov_deg=61.0)
    assert len(gaps) == 1 and gaps[0].turn_deg == pytest.approx(30.0) and not gaps[0].beyond_fov


def test_mismatched_inputs_are_refused():
    with pytest.raises(ValueError, match="3 poses, 2 shares"):
        find_scale_gaps(_yaw_poses([0, 0, 0]), [1, 1], [0, 1, 2], [0, 1, 2], [0, 0, 0], 61.0)


def test_the_share_after_its_own_window_ba_is_what_counts():
    obs = ObservedMasks(0.3, 0.5, 0.5)
    obs.set(7, torch.zeros(4, 4, dtype=torch.bool))
    obs.settle(7)
    obs.set(7, torch.ones(4, 4, dtype=torch.bool))  # measured later, by edges to keyframes after the gap
    obs.settle(7)  # only the first call records
    assert obs.settled_fraction(7) == 0.0 and obs.fraction(7) == 1.0
    assert obs.settled_fraction(8) == 1.0  # none on record: the current share (none: measured)
    obs.forget(7)
    assert 7 not in obs.settled


def test_the_graph_gaps_and_the_warning(caplog):
    """On a frame graph (fx 4 px, 16 px wide: a 127 deg view): a 150 deg turn warns, a 90 deg one is only listed."""
    g = FrameGraph(4, 16, torch.tensor([4.0, 4.0, 8.0, 2.0]))
    deg = [0, 0, 75, 150, 150, 150, 195, 240, 240]
    for k, pose in enumerate(_yaw_poses(deg)):
        g.add_keyframe(100 + 5 * k, 0.1 * k, pose.float(), torch.ones(4, 16))
    shares = dict(zip(g.ids.tolist(), [1, 1, 0.0, 0.0, 1, 1, 0.0, 0.0, 1]))
    with caplog.at_level(logging.WARNING, logger="pvslam"):
        gaps = graph_scale_gaps(g, lambda i: shares[i], [0])
    assert [(x.first_frame, x.last_frame, x.beyond_fov) for x in gaps] == [(110, 115, True), (130, 135, False)]
    assert gaps[0].turn_deg == pytest.approx(150.0, abs=0.01)
    warned = [r.getMessage() for r in caplog.records if "field of view" in r.getMessage()]
    assert len(warned) == 1 and "frames 110-115" in warned[0] and "after frame 115" in warned[0], warned
