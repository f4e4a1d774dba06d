"""Map fragments (pvslam_core.slam.fragments): relocalisation of a keyframe in an older map from its flow and the
old keyframe's depth, the Sim(3) that moves a whole fragment there, and the fragment bookkeeping."""
import math

import pytest
import torch

from pvslam_core.geometry.lie import quat_rotate, se3_exp, se3_inv, se3_mul
from pvslam_core.geometry.projective import edge_transforms, project_points
from pvslam_core.slam.fragments import Fragments, align_fragment, apply_sim3, fragment_indices, relocalise
from pvslam_core.slam.frame_poses import FramePoses
from pvslam_core.slam.graph import FrameGraph

H, W = 30, 40
INTR = torch.tensor([34.0, 34.0, 19.5, 14.5])  # fx fy cx cy at the BA resolution


def pose(t, rotvec) -> torch.Tensor:
    p = se3_exp(torch.tensor([0, 0, 0, *rotvec], dtype=torch.float64))
    p[:3] = torch.tensor(t, dtype=torch.float64)
    return p


def plane_disp(p: torch.Tensor, z_plane: float = 10.0) -> torch.Tensor:
    """Inverse z-depth [H, W] of the plane world-z = z_plane seen from T_wc ``p`` (cameras look along +z)."""
    fx, fy, cx, cy = INTR.tolist()
    y, x = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(x - cx) / fx, (y - cy) / fy, torch.ones_like(x)], -1)  # camera frame, z = 1
    r_w = quat_rotate(p[3:].expand(H, W, 4), rays)
    lam = (z_plane - p[2]) / r_w[..., 2]  # the ray's z = 1, so lam is the z-depth
    return (1.0 / lam).float()


def flow_target(p_j: torch.Tensor, p_k: torch.Tensor, disp_j: torch.Tensor) -> torch.Tensor:
    """[2, H, W] positions in k of j's pixels (exact)."""
    R, t = edge_transforms(torch.stack([p_j, p_k]), torch.tensor([0]), torch.tensor([1]))
    out = project_points(R.float(), t.float(), disp_j.reshape(1, -1), INTR, H, W)
    return torch.stack([out["u"][0], out["v"][0]]).reshape(2, H, W)


# the old map: keyframe j; the truth for keyframe k (the same place, seen 0.6 m to the side, turned 8 degrees)
P_J = pose([1.0, 0.5, 0.0], [0.02, 0.1, 0.0])
P_K = pose([1.5, 0.4, 0.3], [0.0, 0.1 + math.radians(8), 0.01])
# the new fragment's frame: the truth moved by an unknown similarity (lengths_new = lengths_old / S_TRUE)
S_TRUE = 2.5
Q_OFF = pose([0, 0, 0], [0.3, -1.2, 0.4])[3:]
T_OFF = torch.tensor([4.0, -2.0, 1.0], dtype=torch.float64)


def to_new(p: torch.Tensor) -> torch.Tensor:
    return apply_sim3(p[None], Q_OFF, T_OFF, 1.0 / S_TRUE)[0]


def test_relocalise_recovers_pose_and_scale():
    disp_j, disp_k_true = plane_disp(P_J), plane_disp(P_K)
    target = flow_target(P_J, P_K, disp_j)
    weight = torch.ones(2, H, W)
    weight[:, :5] = 0.0  # some pixels without a confident match
    target[:, 10:12] += 7.0  # and some gross flow outliers among the confident ones
    reloc = relocalise(P_J, disp_j, disp_k_true * S_TRUE, INTR, target, weight)  # k's own depth in new units
    assert reloc is not None
    assert torch.allclose(reloc.pose[:3], P_K[:3], atol=1e-2)  # 1 cm at 10 m depth, with outliers
    dq = se3_mul(se3_inv(P_K), reloc.pose)
    assert 2 * math.degrees(math.acos(min(1.0, abs(float(dq[6]))))) < 0.1
    assert reloc.scale == pytest.approx(S_TRUE, rel=1e-2)
    assert reloc.error < 0.05


def test_relocalise_refuses_unrelated_views():
    disp_j = plane_disp(P_J)
    target = torch.rand(2, H, W) * torch.tensor([W, H]).reshape(2, 1, 1)  # flow that fits no pose
    assert relocalise(P_J, disp_j, disp_j, INTR, target, torch.ones(2, H, W)) is None
    assert relocalise(P_J, disp_j, disp_j, INTR, flow_target(P_J, P_K, disp_j), torch.zeros(2, H, W)) is None


def test_align_fragment_moves_the_fragment_and_its_frames():
    """Old map: keyframes 0, 1 (true poses).  New fragment: keyframes 2, 3 = k and a non-keyframe anchored to 2,
    all in the new frame and scale.  After the alignment everything is at its true pose and scale."""
    g = FrameGraph(H, W, INTR)
    true = [P_J, se3_mul(P_J, pose([0.0, 0.0, 1.0], [0, 0, 0])),
            se3_mul(P_K, pose([0.0, 0.0, -1.0], [0, 0.05, 0])), P_K]
    for n, p in enumerate(true):
        new_frag = n >= 2
        g.add_keyframe(10 * n, float(n), to_new(p) if new_frag else p,
                       plane_disp(p) * (S_TRUE if new_frag else 1.0))
    frames = FramePoses(g)
    for n in range(4):
        frames.add_keyframe(10 * n, float(n), g.id_of(n))
    f_true = se3_mul(true[2], pose([0.1, 0.0, 0.4], [0, 0.02, 0]))  # a frame between keyframes 2 and 3
    rel_new = se3_mul(se3_inv(to_new(true[2])), to_new(f_true))
    frames.add_frame(25, 2.5, g.id_of(2), rel_new)
    frags = Fragments()
    frags.start(g.id_of(2))
    assert not frags.same(g.id_of(3), g.id_of(0)) and frags.unmerged == 2
    idx = fragment_indices(g, frags, g.id_of(3))
    assert idx.tolist() == [2, 3]
    disp_j = g.disps[0].clone()
    reloc = relocalise(g.poses[0], disp_j, g.disps[3], INTR, flow_target(P_J, P_K, disp_j), torch.ones(2, H, W))
    align_fragment(g, frames, idx, 3, reloc)
    frags.merge(g.id_of(3), g.id_of(0))
    assert frags.same(g.id_of(3), g.id_of(0)) and frags.unmerged == 1 and frags.merges == 1
    for n in range(4):
        assert torch.allclose(g.poses[n, :3], true[n][:3], atol=5e-3), n
        assert abs(float((g.poses[n, 3:] * true[n][3:]).sum())) == pytest.approx(1.0, abs=1e-6)
        assert torch.allclose(g.disps[n], plane_disp(true[n]), rtol=2e-2), n
    _, all_poses = frames.poses()
    assert torch.allclose(all_poses[-1, :3], f_true[:3], atol=5e-3)


def test_fragments_bookkeeping():
    f = Fragments()
    f.start(10)
    f.start(20)
    assert [f.of(x) for x in (0, 9, 10, 19, 20, 99)] == [0, 0, 10, 10, 20, 20]
    f.merge(25, 3)  # the newest with the first; the middle one stays apart
    assert f.same(25, 0) and not f.same(15, 0) and f.unmerged == 2
    f.merge(12, 30)
    assert f.unmerged == 1 and f.merges == 2
    with pytest.raises(ValueError):
        f.start(5)


def test_gap_frames_are_interpolated_between_the_merged_fragments():
    from pvslam_core.slam.fragments import replace_gap_frames

    g = FrameGraph(H, W, INTR)
    p0, p1 = pose([0.0, 0, 0], [0, 0, 0]), pose([10.0, 0, 0], [0, 0.4, 0])
    g.add_keyframe(0, 0.0, p0, torch.ones(H, W))
    g.add_keyframe(10, 1.0, p1, torch.ones(H, W))
    frames = FramePoses(g)
    frames.add_keyframe(0, 0.0, g.id_of(0))
    rel_extrapolated = pose([0.5, 0, 0], [0, 0, 0])
    for n in (2, 5):  # failed frames, extrapolated from keyframe 0
        frames.add_frame(n, 0.1 * n, g.id_of(0), rel_extrapolated, failed=True)
    frames.add_frame(3, 0.3, g.id_of(0), rel_extrapolated)  # a tracked frame: left alone
    frames.add_keyframe(10, 1.0, g.id_of(1))
    assert replace_gap_frames(g, frames, 1) == 2
    _, poses = frames.poses()
    from pvslam_core.geometry.lie import se3_interpolate

    for row, alpha in ((1, 0.2), (2, 0.5)):  # 0.2 and 0.5 of the way from keyframe 0 to keyframe 1
        assert torch.allclose(poses[row], se3_interpolate(p0, p1, alpha), atol=1e-9)
    assert 1.5 < float(poses[1, 0]) < 2.5 and 4.5 < float(poses[2, 0]) < 5.5
    assert poses[3, 0] == pytest.approx(0.5)  # the tracked frame kept its pose
    e = frames.entries[1]
    assert (e.anchor, e.upto) == (g.id_of(0), g.id_of(1))  # held between the two: they follow both from now on
    p1_moved = pose([12.0, 1.0, 0], [0, 0.5, 0])
    g.set_poses(torch.tensor([1]), p1_moved[None])
    _, poses = frames.poses()
    assert torch.allclose(poses[1], se3_interpolate(p0, p1_moved, 0.2), atol=1e-9)
