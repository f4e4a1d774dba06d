"""Which proximity edges the edge policy keeps (``edges.PROXIMITY_MAX_FLOW``, pvslam_core/slam/flow_distance.py):
the 90th percentile of the induced flow of a keyframe pair, checked against a pinhole projection written here, and
the edge choice on a camera driving forward along a road (long edges whose near road moves too far are
dropped) and on a slow camera (nothing dropped)."""
import numpy as np
import torch

from pvslam_core.slam import edges
from pvslam_core.slam.config import EdgesConfig
from pvslam_core.slam.flow_distance import pair_flow_quantile
from pvslam_core.slam.graph import EDGE_PROXIMITY, FrameGraph

H, W, FX, CX, CY = 30, 40, 34.0, 19.5, 14.5
CAM_HEIGHT, FAR = 1.5, 1.0 / 200.0


def _road_disp() -> np.ndarray:
    """Inverse depth of a flat road 1.5 m below a forward-looking camera (rows under the horizon), far above it.
    The same for every pose along a straight road: the road's depth at a pixel does not change as the camera
    moves forward."""
    disp = np.full((H, W), FAR)
    rows = np.arange(H) - CY
    below = rows > 0.5
    disp[below] = np.maximum(rows[below] / (FX * CAM_HEIGHT), FAR)[:, None]
    return disp


def _brute_flow(disp: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|flow| and validity (depth in the second camera > 0.25) of every pixel for a camera translated by ``t``
    (no rotation: the full and the translation-only flow are the same)."""
    flow, valid = np.zeros((H, W)), np.zeros((H, W), bool)
    for y in range(H):
        for x in range(W):
            p = np.array([(x - CX) / FX, (y - CY) / FX, 1.0]) / disp[y, x] - t
            valid[y, x] = p[2] * disp[y, x] > 0.25  # homogeneous depth, as project_points' min_depth
            flow[y, x] = np.hypot(FX * p[0] / p[2] + CX - x, FX * p[1] / p[2] + CY - y)
    return flow, valid


def _q(flow, valid, q=0.9):
    return float(np.quantile(flow[valid], q))


def test_pair_quantile_is_the_larger_direction_against_brute_force():
    intr = torch.tensor([FX, FX, CX, CY])
    road, far = _road_disp(), np.full((H, W), FAR)
    t = np.array([0.0, 0.0, 0.8])  # 0.8 m forward
    poses = torch.tensor([[0, 0, 0, 0, 0, 0, 1.0], [*t, 0, 0, 0, 1.0]], dtype=torch.float64)
    # keyframe i sees the road, keyframe j only far structure: the road direction decides
    fwd = _q(*_brute_flow(road, t))
    back = _q(*_brute_flow(far, -t))
    assert fwd > 3.0 > back * 10  # the near road moves several BA px, the far scene hardly
    got = pair_flow_quantile(poses, torch.tensor(road, dtype=torch.float32), torch.tensor(far, dtype=torch.float32),
                             intr)
    assert abs(got - max(fwd, back)) < 1e-3 * fwd
    # symmetric in the pair's order
    swapped = pair_flow_quantile(poses.flip(0), torch.tensor(far, dtype=torch.float32),
                                 torch.tensor(road, dtype=torch.float32), intr)
    assert abs(swapped - got) < 1e-3 * fwd
    # most of the view behind the second camera (a 20 m step over the road): "not comparable", 1000
    big = torch.tensor([[0, 0, 0, 0, 0, 0, 1.0], [0, 0, 20.0, 0, 0, 0, 1.0]], dtype=torch.float64)
    near = torch.full((H, W), 0.5)  # everything 2 m away
    assert pair_flow_quantile(big, near, near, intr) == 1000.0


def _chain(step: float, n: int) -> tuple[FrameGraph, torch.Tensor]:
    g = FrameGraph(H, W, torch.tensor([FX, FX, CX, CY]))
    disp = torch.tensor(_road_disp(), dtype=torch.float32)
    for k in range(n):
        g.add_keyframe(k, 0.1 * k, torch.tensor([0, 0, step * k, 0, 0, 0, 1.0], dtype=torch.float64), disp)
    return g, disp


def _connect_newest(g: FrameGraph, limit: float, fragment_start: int = 0) -> list[tuple[int, int]]:
    """The proximity edges the edge policy gives the newest keyframe (edges.connect_keyframe, initialised map)."""
    old = edges.PROXIMITY_MAX_FLOW
    edges.PROXIMITY_MAX_FLOW = limit
    try:
        edges.connect_keyframe(g, g.n - 1, EdgesConfig(), fragment_start, initialized=True)
    finally:
        edges.PROXIMITY_MAX_FLOW = old
    prox = g.edge_kind == EDGE_PROXIMITY
    return sorted(zip(g.ii[prox].tolist(), g.jj[prox].tolist()))


def test_forward_driving_drops_long_edges_over_the_near_road():
    # 0.3 m between keyframes: keyframes 4+ back have a small mean flow (far scene) but the near road between the
    # newest and the one 6 back moves more than the limit (12 BA px at the 90th percentile), 4 back less (6.3)
    g0, _ = _chain(0.3, 12)
    unlimited = _connect_newest(g0, 0.0)
    assert unlimited, "the mean-flow rule alone should pick long edges here (the scene of the bug)"
    k = g0.n - 1
    poses = g0.poses
    q = {j: pair_flow_quantile(torch.stack([poses[j], poses[k]]), g0.disps[j], g0.disps[k], g0.intrinsics)
         for _, j in unlimited if j != k}
    assert max(q.values()) > 8.0 > min(q.values())  # one of each
    g8, _ = _chain(0.3, 12)
    kept = _connect_newest(g8, 8.0)
    kept_j = {j for i, j in kept if i == k}
    for j, qj in q.items():
        assert (j in kept_j) == (qj <= 8.0), (j, qj)
    assert kept_j and len(kept_j) < len(q)
    for i, j in kept:  # both directions of a pair share the decision
        assert (j, i) in kept


def test_a_young_map_keeps_its_long_edges():
    # the same forward drive, but the map fragment started 5 keyframes ago (fewer than active_window = 10): its
    # depths are still the initialisation's guess, so the mean-flow rule alone decides, as without the limit
    ga, _ = _chain(0.3, 12)
    gb, _ = _chain(0.3, 12)
    unlimited = _connect_newest(ga, 0.0, fragment_start=0)
    young = _connect_newest(gb, 8.0, fragment_start=2)  # 11 - 2 = 9 keyframes into the fragment
    assert young and {j for i, j in young if i == 11} == {j for i, j in unlimited if i == 11}
    gc, _ = _chain(0.3, 12)
    assert len(_connect_newest(gc, 8.0, fragment_start=1)) < len(unlimited)  # 10 in: filtered


def test_slow_camera_keeps_every_proximity_edge():
    # 5 cm between keyframes (a slow revisit): the near road moves little, nothing is dropped
    ga, _ = _chain(0.05, 12)
    gb, _ = _chain(0.05, 12)
    unlimited = _connect_newest(ga, 0.0)
    assert unlimited
    assert _connect_newest(gb, 8.0) == unlimited


def test_rotation_alone_keeps_the_edge():
    # a camera turning on the spot by 20 deg over a near road: large image motion, no parallax (the frontend's flow,
    # started from the predicted rotation, follows it), so the pair counts as close
    intr = torch.tensor([FX, FX, CX, CY])
    road = torch.tensor(_road_disp(), dtype=torch.float32)
    s, c = np.sin(np.radians(10.0)), np.cos(np.radians(10.0))  # quaternion of a 20 deg yaw (about the camera y axis)
    poses = torch.tensor([[0, 0, 0, 0, 0, 0, 1.0], [0, 0, 0, 0, s, 0, c]], dtype=torch.float64)
    assert pair_flow_quantile(poses, road, road, intr) < 1e-3
    # the same turn plus 1.8 m forward: the near road's parallax counts
    moved = poses.clone()
    moved[1, 2] = 1.8
    assert pair_flow_quantile(moved, road, road, intr) > 8.0
