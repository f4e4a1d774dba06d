"""Id tracking of the fusion head (shared matching + track memory): a car hidden behind a truck keeps its id."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pvslam_core.interfaces import MotionCue
from pvslam_core.types import Frame, Intrinsics, PanopticSegmentation, Segment
from pvslam_plugins.vps import matching
from pvslam_plugins.vps.fusion.config import FusionConfig
from pvslam_plugins.vps.fusion.head import FusionHead
from pvslam_plugins.vps.warp_iou.head import WarpIoUHead

H, W = 48, 96
CAR, TRUCK, ROAD = 1, 2, 7  # category ids (car, truck: things; road: stuff)
CAR_W, CAR_SPEED = 12, 2


def _scene(t: int, hidden: int, truck_x: int = 40):
    """Frame ``t``: a car (rows 20-27) driving right at 2 px/frame behind a parked truck (rows 10-35) wide enough
    to hide it completely for ``hidden`` frames.  Returns ids, segments, the flow t -> t+1 and the car's
    visible area.  Segment ids are renumbered every frame (the segmenter's ids carry no identity)."""
    truck_w = CAR_W + CAR_SPEED * (hidden - 1)
    ids = np.full((H, W), 50, np.int64)  # road segment id 50
    flow = np.zeros((2, H, W), np.float32)
    x0 = truck_x - CAR_W - 4 + CAR_SPEED * t
    car = np.zeros((H, W), bool)
    car[20:28, max(x0, 0):max(min(x0 + CAR_W, W), 0)] = True
    truck = np.zeros((H, W), bool)
    truck[10:36, truck_x:truck_x + truck_w] = True
    visible = car & ~truck
    car_id, truck_id = 3 + t % 2, 6 + t % 2
    ids[truck] = truck_id
    ids[visible] = car_id
    flow[0][visible] = CAR_SPEED
    segs = [Segment(50, ROAD, False), Segment(truck_id, TRUCK, True)]
    if visible.any():
        segs.append(Segment(car_id, CAR, True))
    return ids, segs, flow, int(visible.sum()), car_id


def _frame(t: int) -> Frame:
    return Frame(index=t, timestamp=0.1 * t, image=torch.zeros(3, H, W, dtype=torch.uint8),
                 intrinsics=Intrinsics(100.0, 100.0, W / 2, H / 2, W, H))


def _run(head, hidden: int, frames: int):
    """Per frame: (output id of the car, or None while hidden), plus the hidden frame count actually produced."""
    state, prev_flow, out, n_hidden = None, None, [], 0
    for t in range(frames):
        ids, segs, flow, area, car_sid = _scene(t, hidden)
        seg = PanopticSegmentation(torch.from_numpy(ids), segs)
        cue = MotionCue(flow=torch.from_numpy(prev_flow)) if prev_flow is not None else MotionCue()
        state = head.update(state, _frame(t), seg, cue)
        prev_flow = flow
        if area == 0:
            n_hidden += 1
            out.append(None)
        else:
            out.append(int(state.panoptic.ids[torch.from_numpy(ids == car_sid)].unique().item()))
    return out, n_hidden


@pytest.mark.parametrize("hidden", [1, 5, 10])
def test_car_hidden_up_to_10_frames_keeps_its_id(hidden):
    frames = hidden + 22
    ids, n_hidden = _run(FusionHead(FusionConfig(memory_frames=10)), hidden, frames)
    assert n_hidden == hidden  # the construction hides the car for exactly that many frames
    seen = [i for i in ids if i is not None]
    assert len(seen) >= 15 and ids[0] is not None and ids[-1] is not None
    assert len(set(seen)) == 1, f"car ids over time: {ids}"


def test_without_memory_the_reappearing_car_gets_a_new_id():
    # the test above can fail: warp_iou (no memory) and the fusion head with memory off both re-identify wrongly
    for head in (WarpIoUHead(), FusionHead(FusionConfig(memory_frames=0))):
        ids, _ = _run(head, 10, 32)
        assert len({i for i in ids if i is not None}) == 2


def test_memory_expires():
    ids, n_hidden = _run(FusionHead(FusionConfig(memory_frames=10)), 14, 36)
    assert n_hidden == 14
    assert len({i for i in ids if i is not None}) == 2  # hidden longer than remembered: a new id


def test_match_segments_matches_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(20):
        ids = rng.integers(0, 6, size=(12, 14))
        warped = rng.integers(0, 6, size=(12, 14)) * 10
        cur_cat = {g: int(rng.integers(1, 3)) for g in range(1, 6)}
        prev_cat = {p: int(rng.integers(1, 3)) for p in range(10, 60, 10)}
        got = matching.match_segments(ids, warped, sorted(cur_cat), cur_cat, prev_cat, "overlap", 0.05)
        # reference: all pairs by hand, then the same greedy order (score, intersection, ids)
        cand = []
        for g in cur_cat:
            for p in prev_cat:
                inter = int(((ids == g) & (warped == p)).sum())
                area = int((warped == p).sum())
                s = inter / max(area, 1)
                if cur_cat[g] == prev_cat[p] and inter > 0 and s >= 0.05:
                    cand.append((-s, -inter, g, p))
        used_g, used_p, ref = set(), set(), []
        for s, n, g, p in sorted(cand):
            if g not in used_g and p not in used_p:
                used_g.add(g)
                used_p.add(p)
                ref.append((g, p, -s))
        assert [(g, p) for g, p, _ in got] == [(g, p) for g, p, _ in ref]
        assert np.allclose([s for *_, s in got], [s for *_, s in ref])


def test_warp_iou_uses_the_shared_matching():
    import pvslam_plugins.vps.fusion.head as fh
    import pvslam_plugins.vps.warp_iou.head as wh

    assert wh.match_segments is matching.match_segments is fh.match_segments
    assert wh.compose_id is matching.compose_id
