"""Edge policy (pvslam_core.slam.edges): which edges a keyframe gets and which edges retire."""
import torch

from pvslam_core.slam.config import EdgesConfig
from pvslam_core.geometry.testing import make_problem
from pvslam_core.slam.edges import active_edges, loop_edges, neighbour_edges, proximity_edges, retirement_mask
from pvslam_core.slam.graph import FrameGraph


def pairs(ii, jj):
    return sorted(zip(ii.tolist(), jj.tolist()))


def test_neighbour_and_loop_edges():
    cfg = EdgesConfig(neighbours=3)
    assert pairs(*neighbour_edges(5, cfg, bidirectional=False)) == [(5, 2), (5, 3), (5, 4)]
    assert pairs(*neighbour_edges(5, cfg, first=4, bidirectional=False)) == [(5, 4)]  # not into an older fragment
    both = EdgesConfig(neighbours=1)
    assert pairs(*neighbour_edges(2, both)) == [(1, 2), (2, 1)]
    assert pairs(*loop_edges(20, 0, 21, bidirectional=False)) == [(20, 0), (20, 1)]  # j - 1 clipped
    assert pairs(*loop_edges(20, 19, 21, bidirectional=False)) == [(20, 18), (20, 19)]  # never i itself


def test_proximity_edges_pick_close_frames_with_nms():
    pr = make_problem(n=12, step=0.02, seed=3)  # small steps: every older keyframe looks at the same place
    g = pr.graph()
    cfg = EdgesConfig(neighbours=2, proximity_window=10, proximity_thresh=1e6, max_proximity=3)
    ii, jj = proximity_edges(g, 11, cfg, nms=2, bidirectional=False)
    chosen = jj.tolist()
    assert (ii == 11).all() and len(chosen) == 3 and all(c <= 8 for c in chosen)
    assert all(abs(a - b) > 2 for a in chosen for b in chosen if a != b)  # index NMS
    d = g.frame_distance(torch.full((9,), 11), torch.arange(9))
    assert chosen[0] == int(torch.argmin(d))  # the closest first
    tight = EdgesConfig(neighbours=2, proximity_thresh=1e-6)
    assert proximity_edges(g, 11, tight, bidirectional=False)[0].numel() == 0


def test_retirement_window_age_and_cap():
    g = FrameGraph(3, 4, torch.tensor([4.0, 4.0, 1.5, 1.0]))
    for k in range(10):
        g.add_keyframe(k, float(k), torch.tensor([0, 0, 0, 0, 0, 0, 1.0]), torch.ones(3, 4))
        if k:
            g.add_edges(torch.tensor([k, k - 1]), torch.tensor([k - 1, k]))
    cfg = EdgesConfig(active_window=3, max_age=5, max_active=1000)
    m = retirement_mask(g, 9, cfg)
    kept = pairs(g.ii[~m], g.jj[~m])
    assert kept == pairs(*active_edges(g, 9, 3))  # exactly the edges the window BAs would use
    assert all(max(i, j) >= 7 for i, j in kept) and all(max(i, j) < 7 for i, j in pairs(g.ii[m], g.jj[m]))
    g.age_edges(torch.tensor([8]), torch.tensor([7]), by=5)
    m = retirement_mask(g, 9, cfg)
    assert (8, 7) not in pairs(g.ii[~m], g.jj[~m])  # too old, although in the window
    g.age_edges(torch.tensor([9]), torch.tensor([8]), by=9)
    assert (9, 8) in pairs(*[t[~retirement_mask(g, 9, cfg)] for t in (g.ii, g.jj)])  # touches the new keyframe
    cap = EdgesConfig(active_window=10, max_age=100, max_active=8)
    m = retirement_mask(g, 9, cap)
    assert int((~m).sum()) == 8
    assert {(9, 8), (8, 9)} <= set(pairs(g.ii[~m], g.jj[~m]))  # the newest survive the cap
