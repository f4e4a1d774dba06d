"""Stable ids and the edge lifecycle of the frame graph."""
import pytest
import torch

from pvslam_core.slam.graph import EDGE_LOOP, FrameGraph
from pvslam_core.types import EdgeObservations


class Listener:
    def __init__(self, g):
        self.g = g
        self.removed, self.retired = [], []

    def on_keyframe_removed(self, kf_id):
        # called while the keyframe is still readable
        self.removed.append((kf_id, self.g.index_of(kf_id), int(self.g.frame_index[self.g.index_of(kf_id)])))

    def on_edges_retired(self, src, dst):
        self.retired += list(zip(src.tolist(), dst.tolist()))


def make(n=5, h=3, w=4):
    g = FrameGraph(h, w, torch.tensor([4.0, 4.0, 1.5, 1.0]), capacity=2)
    for k in range(n):
        g.add_keyframe(100 + k, float(k), torch.tensor([k, 0, 0, 0, 0, 0, 1.0]), torch.full((h, w), 1.0 + k))
    return g


def obs_for(g, ii, jj, value):
    h, w = g.ba_shape
    E = len(ii)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    target = torch.stack([xs + value, ys - value]).expand(E, 2, h, w).clone()
    return EdgeObservations(torch.tensor(ii), torch.tensor(jj), target, torch.full((E, 2, h, w), 0.5))


def test_ids_are_stable_and_lookups_vectorised():
    g = make(5)
    lis = Listener(g)
    g.add_listener(lis)
    g.add_listener(lis)  # once only
    assert g.ids.tolist() == [0, 1, 2, 3, 4]
    g.add_edges(torch.tensor([1, 3, 2]), torch.tensor([3, 1, 4]), kind=EDGE_LOOP)
    g.remove_keyframe(1)
    assert lis.removed == [(1, 1, 101)]
    assert g.ids.tolist() == [0, 2, 3, 4] and g.frame_index.tolist() == [100, 102, 103, 104]
    assert g.indices_of(torch.tensor([[4, 1], [0, 2]])).tolist() == [[3, -1], [0, 1]]
    assert g.index_of(3) == 2 and g.id_of(-1) == 4 and not g.has_id(1)
    with pytest.raises(KeyError):
        g.index_of(1)
    assert list(zip(g.ii.tolist(), g.jj.tolist())) == [(1, 3)]  # (2 -> 4) by id, shifted to indices
    g.add_keyframe(105, 5.0, g.poses[-1], g.disps[-1])
    assert g.ids.tolist() == [0, 2, 3, 4, 5]  # never reused


def test_retire_keeps_last_observation_and_reactivates():
    g = make(4)
    lis = Listener(g)
    g.add_listener(lis)
    g.add_edges(torch.tensor([0, 1, 2, 3]), torch.tensor([1, 0, 3, 2]))
    g.record_observations(obs_for(g, [0, 1], [1, 0], 0.25))
    g.record_observations(obs_for(g, [0, 2], [1, 3], 1.5))  # the latest observation counts
    g.record_observations(obs_for(g, [0], [2], 9.0))  # not an edge: not recorded
    assert g.retire_edges(torch.tensor([True, True, True, False])) == 3
    assert sorted(lis.retired) == [(0, 1), (1, 0), (2, 3)]
    assert g.num_edges == 1 and g.num_retired == 3 and g.retired_total == 3
    rii, rjj = g.retired_edges()
    assert sorted(zip(rii.tolist(), rjj.tolist())) == [(0, 1), (1, 0), (2, 3)]
    stored = g.retired_observations(torch.tensor([0, 2]), torch.tensor([1, 3]))
    ref = obs_for(g, [0, 2], [1, 3], 1.5)
    assert torch.allclose(stored.target, ref.target, atol=2e-3) and torch.allclose(stored.weight, ref.weight)
    aii, ajj = g.all_edges()
    assert len(aii) == 4
    # re-adding a retired edge makes it active again; its stored observation goes
    g.add_edges(torch.tensor([0]), torch.tensor([1]))
    assert g.num_retired == 2 and bool(g.has_edges([0], [1])[0])
    with pytest.raises(KeyError):
        g.retired_observations(torch.tensor([0]), torch.tensor([1]))
    # removing a keyframe drops its retired edges too, and the indices of the rest shift
    g.remove_keyframe(1)
    rii, rjj = g.retired_edges()
    assert list(zip(rii.tolist(), rjj.tolist())) == [(1, 2)]  # (2 -> 3) by id
    assert g.retired_bytes() == 2 * 2 * 3 * 4 * 2  # offsets and weights in float16


def test_retired_edges_from_a_keyframe_on_selects_both_ends_at_or_after_it():
    g = make(6)
    g.add_edges(torch.tensor([0, 1, 2, 4, 3]), torch.tensor([3, 2, 4, 5, 5]))
    g.record_observations(obs_for(g, [0, 1, 2, 4], [3, 2, 4, 5], 0.5))  # (3 -> 5) never observed: dropped
    g.retire_edges(torch.ones(5, dtype=torch.bool))
    pairs = lambda lo: sorted(zip(*[t.tolist() for t in g.retired_edges(lo)]))
    assert pairs(0) == [(0, 3), (1, 2), (2, 4), (4, 5)]
    assert pairs(1) == [(1, 2), (2, 4), (4, 5)]  # (0 -> 3) has an end before keyframe 1
    assert pairs(2) == [(2, 4), (4, 5)]
    assert pairs(5) == [] and pairs(9) == []
    g.remove_keyframe(1)  # indices shift; the selection follows ids
    assert pairs(1) == [(1, 3), (3, 4)]
    ii, jj = g.retired_edges(1)
    assert g.retired_observations(ii, jj).target.shape == (2, 2, 3, 4)
