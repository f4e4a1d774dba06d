"""Poses of every frame anchored to keyframes (pvslam_core.slam.frame_poses)."""
import pytest
import torch

from pvslam_core.geometry.lie import se3_exp, se3_inv, se3_mul
from pvslam_core.geometry.projective import reproject
from pvslam_core.geometry.testing import make_problem
from pvslam_core.slam.frame_poses import FramePoses


def test_poses_follow_keyframes_and_survive_removal():
    pr = make_problem(n=4, seed=2)
    g = pr.graph()
    fp = FramePoses(g)
    rel = se3_exp(torch.tensor([0.1, 0.0, 0.05, 0.0, 0.02, 0.0], dtype=torch.float64))
    for k in range(4):
        fp.add_keyframe(10 * k, float(k), g.id_of(k))
        fp.add_frame(10 * k + 5, k + 0.5, g.id_of(k), rel)
    ts, poses = fp.poses()
    assert ts.tolist() == [0, 0.5, 1, 1.5, 2, 2.5, 3, 3.5]
    assert torch.allclose(poses[3], se3_mul(pr.poses[1], rel))
    # the BA moves keyframe 1: its frames move with it
    moved = se3_mul(pr.poses[1], se3_exp(torch.tensor([0, 0.2, 0, 0.05, 0, 0], dtype=torch.float64)))
    g.set_poses(torch.tensor([1]), moved[None])
    assert torch.allclose(fp.poses()[1][3], se3_mul(moved, rel))
    before = fp.poses()[1]
    g.remove_keyframe(1)  # the graph tells; frames anchored to it re-anchor to keyframe 0 at the same pose
    after = fp.poses()[1]
    assert torch.allclose(before, after, atol=1e-9)
    assert fp.entries[2].anchor == g.id_of(0) and not fp.entries[2].is_keyframe
    with pytest.raises(ValueError):
        g.remove_keyframe(0)


def test_refine_recovers_pose_from_exact_correspondences():
    pr = make_problem(n=3, seed=5, radius=2)
    g = pr.graph()
    fp = FramePoses(g, robust="cauchy", robust_scale=1.0)
    fp.add_keyframe(0, 0.0, g.id_of(0))
    coords, valid = reproject(pr.poses, pr.disps.double(), pr.intr.double(), torch.tensor([0]), torch.tensor([2]))
    target = coords[0].permute(2, 0, 1).float()
    weight = valid[0].float().expand(2, -1, -1).clone()
    e = fp.add_frame(7, 0.7, g.id_of(0), torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64), target, weight)
    init = se3_mul(pr.poses[2], se3_exp(torch.tensor([0.03, -0.02, 0.02, 0.01, -0.01, 0.0], dtype=torch.float64)))
    assert fp.refine(e, init, iters=8)
    err = se3_mul(se3_inv(pr.poses[2]), fp.pose_of(e))
    assert float(err[:3].norm()) < 1e-3
    assert fp.refill(iters=4) == 1


def _frames_of_keyframe_0(pr, g, fp, n=3):
    """``n`` non-keyframes anchored to keyframe 0 with exact correspondences to keyframe 2's pose, and inits."""
    coords, valid = reproject(pr.poses, pr.disps.double(), pr.intr.double(), torch.tensor([0]), torch.tensor([2]))
    target = coords[0].permute(2, 0, 1).float()
    weight = valid[0].float().expand(2, -1, -1).clone()
    ident = torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)
    entries = [fp.add_frame(7 + i, 0.7 + 0.01 * i, g.id_of(0), ident, target, weight) for i in range(n)]
    inits = torch.stack([se3_mul(pr.poses[2], se3_exp(torch.tensor([0.03 * (i + 1), -0.02, 0.02, 0.01, -0.01, 0.0],
                                                                   dtype=torch.float64))) for i in range(n)])
    return entries, inits


def test_refinement_on_the_worker_equals_the_one_in_place_and_readers_wait():
    """refine_many_later: the same relative poses as refine_many, bit for bit, from inputs copied when queued (the
    BA moving the anchor afterwards changes nothing); pose_of / last_rel / a keyframe removal wait for it."""
    pr = make_problem(n=3, seed=5, radius=2)
    results = []
    for later in (False, True):
        g = pr.graph()
        fp = FramePoses(g, robust="cauchy", robust_scale=1.0)
        fp.add_keyframe(0, 0.0, g.id_of(0))
        entries, inits = _frames_of_keyframe_0(pr, g, fp)
        if later:
            fp.refine_many_later(entries, inits, iters=6)
            assert fp._busy == {id(e) for e in entries}
            # the map moves right after the refinement was queued: the refinement used the anchor as it was
            bump = se3_exp(torch.full((6,), 0.1, dtype=torch.float64))
            g.set_poses(torch.tensor([0]), se3_mul(pr.poses[0], bump)[None])
            g.set_disps(torch.tensor([0]), g.disps[0:1] * 2.0)
            rel_last = fp.last_rel()  # the newest entry is being refined: this waits
            assert not fp._busy
        else:
            fp.refine_many(entries, inits, iters=6)
            rel_last = fp.last_rel()
        results.append((torch.stack([e.rel for e in fp.entries[1:]]), rel_last))
        fp.close()
    (a, la), (b, lb) = results
    assert torch.equal(a, b) and torch.equal(la, lb)
    err = se3_mul(se3_inv(pr.poses[2]), se3_mul(pr.poses[0], a[0]))
    assert float(err[:3].norm()) < 1e-3  # and it is the right pose


def test_a_keyframe_removal_waits_for_the_refinement_of_its_frames():
    pr = make_problem(n=3, seed=5, radius=2)
    g = pr.graph()
    fp = FramePoses(g, robust="cauchy", robust_scale=1.0)
    for k in range(3):
        fp.add_keyframe(10 * k, float(k), g.id_of(k))
    coords, valid = reproject(pr.poses, pr.disps.double(), pr.intr.double(), torch.tensor([1]), torch.tensor([2]))
    target, weight = coords[0].permute(2, 0, 1).float(), valid[0].float().expand(2, -1, -1).clone()
    e = fp.add_frame(15, 1.5, g.id_of(1), torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64), target, weight)
    fp.refine_many_later([e], pr.poses[2][None].clone(), iters=6)
    g.remove_keyframe(1)  # re-anchors e to keyframe 0 at the refined pose, not the placeholder
    assert not fp._busy and e.anchor == g.id_of(0)
    err = se3_mul(se3_inv(pr.poses[2]), fp.pose_of(e))
    assert float(err[:3].norm()) < 1e-6


def test_an_error_on_the_worker_surfaces_at_the_next_read(monkeypatch):
    import pvslam_core.geometry.ba as ba

    def broken(*a, **k):
        raise FloatingPointError("solver exploded")

    pr = make_problem(n=3, seed=5, radius=2)
    g = pr.graph()
    fp = FramePoses(g)
    fp.add_keyframe(0, 0.0, g.id_of(0))
    entries, inits = _frames_of_keyframe_0(pr, g, fp, n=2)
    monkeypatch.setattr(ba, "motion_only_ba", broken)
    fp.refine_many_later(entries, inits)  # queued; fails on the worker
    with pytest.raises(FloatingPointError, match="solver exploded"):
        fp.poses()
    fp.close()
