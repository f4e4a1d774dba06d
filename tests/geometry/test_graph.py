import torch

from pvslam_core.geometry.lie import identity_se3
from pvslam_core.slam.graph import FrameGraph


def _graph(n=5, cap=2):
    g = FrameGraph(3, 4, torch.tensor([4.0, 4.0, 1.5, 1.0]), capacity=cap)
    for k in range(n):
        p = identity_se3((), torch.float64)
        p[0] = k
        g.add_keyframe(10 * k, 0.5 * k, p, torch.full((3, 4), 1.0 + k))
    return g


def test_add_and_grow():
    g = _graph(5, cap=2)
    assert g.n == 5 and g.capacity >= 5
    assert g.poses.shape == (5, 7) and g.poses.dtype == torch.float64
    assert g.disps.shape == (5, 3, 4) and g.disps.dtype == torch.float32
    assert g.frame_index.tolist() == [0, 10, 20, 30, 40]
    assert torch.allclose(g.timestamps, torch.tensor([0, 0.5, 1.0, 1.5, 2.0], dtype=torch.float64))
    assert g.ba_shape == (3, 4) and g.intrinsics.dtype == torch.float32


def test_edges_dedup_and_remove():
    g = _graph(4)
    added = g.add_edges(torch.tensor([0, 1, 1, 2, 0, 3]), torch.tensor([1, 0, 1, 3, 1, 7]), kind=0)
    assert added.tolist() == [True, True, False, True, False, False]
    assert g.num_edges == 3
    again = g.add_edges([0, 2], [1, 0], kind=2)
    assert again.tolist() == [False, True]
    assert g.edge_kind.tolist() == [0, 0, 0, 2]
    g.age_edges(g.ii, g.jj)
    g.age_edges([2], [0])
    assert g.edge_age.tolist() == [1, 1, 1, 2]
    assert g.retire_edges(g.ii == 0) == 1  # never observed: dropped, nothing stored
    assert list(zip(g.ii.tolist(), g.jj.tolist())) == [(1, 0), (2, 3), (2, 0)]
    assert g.num_retired == 0


def test_remove_keyframe_shifts():
    g = _graph(5)
    g.add_edges([0, 1, 2, 3, 4], [1, 2, 3, 4, 0])
    g.remove_keyframe(2)
    assert g.n == 4
    assert g.frame_index.tolist() == [0, 10, 30, 40]
    assert g.poses[:, 0].tolist() == [0, 1, 3, 4]
    assert g.disps[:, 0, 0].tolist() == [1, 2, 4, 5]
    assert list(zip(g.ii.tolist(), g.jj.tolist())) == [(0, 1), (2, 3), (3, 0)]


def test_set_and_state_dict():
    g = _graph(3)
    g.add_edges([0], [2], kind=1)
    g.set_poses(torch.tensor([1]), identity_se3((1,), torch.float64))
    g.set_disps([2], torch.zeros(1, 3, 4))
    assert g.poses[1, 0] == 0 and g.disps[2].abs().sum() == 0
    sd = g.state_dict()
    g2 = FrameGraph.from_state_dict(sd)
    assert g2.n == 3 and torch.equal(g2.poses, g.poses) and torch.equal(g2.disps, g.disps)
    assert torch.equal(g2.ii, g.ii) and torch.equal(g2.edge_kind, g.edge_kind)
    k = g2.add_keyframe(99, 9.0, identity_se3((), torch.float64), torch.ones(3, 4))
    assert k == 3 and g2.n == 4


def test_frame_distance_method():
    g = _graph(3)
    d = g.frame_distance(torch.tensor([0, 0]), torch.tensor([0, 1]))
    assert d.shape == (2,) and d[0] == 0 and d[1] > 0
