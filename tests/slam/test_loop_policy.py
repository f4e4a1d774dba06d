"""The loop policy (pvslam_core.slam.loops): the one place that decides which candidates close a loop."""
import math

import pytest
import torch

from pvslam_core.config import LoopClosureSection
from pvslam_core.geometry.lie import se3_exp
from pvslam_core.slam import loops
from pvslam_core.slam.graph import FrameGraph
from pvslam_core.slam.loops import LoopPolicy, rotation_deg
from pvslam_core.types import LoopCandidate


def graph(n: int, yaw_deg: dict | None = None) -> FrameGraph:
    g = FrameGraph(3, 4, torch.tensor([4.0, 4.0, 1.5, 1.0]))
    for k in range(n):
        a = math.radians((yaw_deg or {}).get(k, 0.0))
        pose = se3_exp(torch.tensor([0, 0, 0, 0, a, 0], dtype=torch.float64))
        pose[0] = 0.1 * k
        g.add_keyframe(10 * k, float(k), pose, torch.ones(3, 4))
    return g


def policy(g, **kw) -> LoopPolicy:
    return LoopPolicy(LoopClosureSection(**kw), g)


def test_verification_rule():
    g = graph(20)
    for verified, accept_unverified, accepted in ((True, False, True), (None, True, True), (None, False, False),
                                                  (False, True, False)):
        p = policy(g, accept_unverified=accept_unverified)
        d = p.decide([LoopCandidate(19, 2, 0.9, verified=verified)])
        assert (d is not None) == accepted, (verified, accept_unverified)
        if d is not None:
            c = d.closure
            assert (c.frame_i, c.frame_j, c.kf_i, c.kf_j, c.verified) == (190, 20, 19, 2, verified)


def test_best_remaining_candidate_and_orientation_check():
    g = graph(20, yaw_deg={19: 170.0, 5: 160.0})  # keyframe 19 faces the other way than all but keyframe 5
    assert rotation_deg(g.poses[19, 3:], g.poses[2, 3:]) == pytest.approx(170.0, abs=1e-6)
    p = policy(g)
    d = p.decide([LoopCandidate(19, 2, 0.95, True), LoopCandidate(19, 5, 0.9, True)])
    assert d.closure.kf_j == 5  # the first (best) is look-alike seen from the opposite direction


def test_consecutive_hits(monkeypatch):
    g = graph(30)
    monkeypatch.setattr(loops, "CONSECUTIVE_TOLERANCE", 1)
    p = policy(g, consecutive=2)
    assert p.decide([LoopCandidate(20, 3, 0.9, True)]) is None  # first hit: not yet
    d = p.decide([LoopCandidate(21, 4, 0.9, True)])  # the previous keyframe proposed a place within 1 + 1
    assert d is not None and d.closure.kf_j == 4
    p.accepted(d)
    assert p.decide([LoopCandidate(23, 15, 0.9, True)]) is None  # keyframe 22 proposed nothing
    # a failed verification is not a hit
    p2 = policy(g, consecutive=2)
    p2.decide([LoopCandidate(20, 3, 0.9, False)])
    assert p2.decide([LoopCandidate(21, 4, 0.9, True)]) is None


def test_suppression_near_accepted_loops_and_removed_keyframes(monkeypatch):
    g = graph(30)
    for nms, expect in ((2, False), (0, True)):
        monkeypatch.setattr(loops, "NMS_KEYFRAMES", nms)
        p = policy(g)
        d = p.decide([LoopCandidate(20, 3, 0.9, True)])
        p.accepted(d)
        assert p.suppressed(21, 4) == (not expect)
        assert (p.decide([LoopCandidate(21, 4, 0.9, True)]) is not None) == expect
        assert not p.suppressed(21, 12)  # another place
    # distances are taken in the current graph: after removals the indices of ids move closer
    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 2)
    p = policy(g)
    p.accepted(p.decide([LoopCandidate(20, 3, 0.9, True)]))
    assert not p.suppressed(24, 3)
    g.remove_keyframe(g.index_of(21))
    g.remove_keyframe(g.index_of(22))
    assert p.suppressed(24, 3)


def test_loop_ba_gating(monkeypatch):
    g = graph(12)
    monkeypatch.setattr(loops, "LOOP_BA_MIN_GAP", 3)
    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)
    p = policy(g)
    runs = []
    for k in range(6, 12):
        # the policy reads the graph size: grow it as keyframes would arrive
        d = p.decide([LoopCandidate(k, 1, 0.9, True)])
        p.accepted(d)
        runs.append(d.run_loop_ba)
        g.add_keyframe(100 + k, 0.0, g.poses[-1], g.disps[-1])
    assert runs == [True, False, False, True, False, False]
    assert [c.loop_ba for c in p.closures] == runs
