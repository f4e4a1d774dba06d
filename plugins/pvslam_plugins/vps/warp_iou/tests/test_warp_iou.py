"""Tests of the ``warp_iou`` VPS head: id propagation with a given flow and with DIS, new / vanished instances,
category-aware matching, forward-warp collisions and the rigid (depth + pose) warp."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from pvslam_core.interfaces import MotionCue, VPSState
from pvslam_core.types import Frame, Intrinsics, PanopticSegmentation, Segment
from pvslam_plugins.vps.warp_iou.config import WarpIoUConfig
from pvslam_plugins.vps.warp_iou.head import WarpIoUHead, WarpOptions, compose_id, decompose_id
from pvslam_plugins.vps.warp_iou.warp import dis_flow, forward_warp, rigid_flow

W, H = 320, 240
K = Intrinsics(fx=288.0, fy=288.0, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)
ROAD, BUILDING, CAR, TRUCK = 1, 2, 3, 4  # stuff, stuff, thing, thing
IS_THING = {ROAD: False, BUILDING: False, CAR: True, TRUCK: True}


def _texture(seed: int, h: int, w: int) -> np.ndarray:
    """Smooth multi-scale noise (good for optical flow)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.float32)
    for s, amp in ((1.5, 0.5), (4.0, 1.0), (10.0, 1.5)):
        n = cv2.GaussianBlur(rng.normal(0, 1, (h, w, 3)).astype(np.float32), (0, 0), s)
        img += amp * n / (n.std() + 1e-6)
    return np.clip(128 + 30 * img, 0, 255)


BACKGROUND = _texture(0, H, W)


def scene(objects: dict[str, tuple[int, int, int, int, int]], index: int, seg_ids: dict[str, int] | None = None):
    """objects: name -> (x, y, w, h, category) of textured rectangles (drawn in dict order) over a static textured
    background split into building (top) and road (bottom).  Segmenter ids are arbitrary (``seg_ids`` or 11, 12..)."""
    img = BACKGROUND.copy()
    ids = np.full((H, W), 900, np.int64)
    ids[H // 2 :] = 901
    segments = [Segment(900, BUILDING, False, 0.9), Segment(901, ROAD, False, 0.8)]
    for n, (name, (x, y, w, h, cat)) in enumerate(objects.items()):
        tex = _texture(100 + sum(map(ord, name)), h, w)  # the texture moves with the object
        x0, x1, y0, y1 = max(x, 0), min(x + w, W), max(y, 0), min(y + h, H)
        if x1 <= x0 or y1 <= y0:
            continue
        img[y0:y1, x0:x1] = tex[y0 - y : y1 - y, x0 - x : x1 - x]
        sid = (seg_ids or {}).get(name, 11 + n)
        ids[y0:y1, x0:x1] = sid
        segments.append(Segment(sid, cat, IS_THING[cat], 0.95))
    image = torch.from_numpy(np.clip(img, 0, 255).astype(np.uint8)).permute(2, 0, 1).contiguous()
    fr = Frame(index=index, timestamp=0.1 * index, image=image, intrinsics=K)
    return fr, PanopticSegmentation(torch.from_numpy(ids), segments)


def flow_of(objects0, objects1) -> torch.Tensor:
    """Exact flow of the previous frame (objects0) into the next (objects1): objects move, background is static."""
    f = np.zeros((2, H, W), np.float32)
    for name, (x, y, w, h, _) in objects0.items():
        if name in objects1:
            x1, y1 = objects1[name][:2]
            ys, xs = slice(max(y, 0), min(y + h, H)), slice(max(x, 0), min(x + w, W))
            f[0, ys, xs] = x1 - x
            f[1, ys, xs] = y1 - y
    return torch.from_numpy(f)


def id_at(state: VPSState, x: int, y: int) -> int:
    return int(state.panoptic.ids[y, x])


def run(head, seq, flows: bool = True):
    """seq: list of object dicts; returns the states.  flows=False gives a zero flow (identity warp)."""
    states, prev = [], None
    for t, objs in enumerate(seq):
        fr, seg = scene(objs, t, seg_ids={n: 50 - i - 3 * t for i, n in enumerate(objs)})  # ids change per frame
        if t == 0:
            cue = MotionCue()
        else:
            cue = MotionCue(flow=flow_of(seq[t - 1], objs) if flows else torch.zeros(2, H, W))
        prev = head.update(prev, fr, seg, cue)
        states.append(prev)
    return states


def centre(obj) -> tuple[int, int]:
    x, y, w, h, _ = obj
    return x + w // 2, y + h // 2


def check_consistent(state: VPSState):
    ids = set(torch.unique(state.panoptic.ids).tolist()) - {0}
    assert ids == {s.id for s in state.panoptic.segments}
    for s in state.panoptic.segments:
        if not s.isthing:
            assert s.id == s.category_id * 1000


# --------------------------------------------------------------------------------------------------------------
def test_two_cars_keep_ids_with_given_flow():
    # adjacent cars moving by more than their width: only a warp (not identity overlap) can keep the ids
    seq = []
    for t in range(4):
        seq.append({"a": (40 + 36 * t, 140, 34, 30, CAR), "b": (76 + 36 * t, 140, 34, 30, CAR)})
    head = WarpIoUHead()
    states = run(head, seq)
    ia, ib = id_at(states[0], *centre(seq[0]["a"])), id_at(states[0], *centre(seq[0]["b"]))
    assert ia != ib and decompose_id(ia)[0] == CAR and decompose_id(ib)[0] == CAR
    for st, objs in zip(states, seq):
        check_consistent(st)
        assert id_at(st, *centre(objs["a"])) == ia and id_at(st, *centre(objs["b"])) == ib
        assert id_at(st, 5, 5) == BUILDING * 1000 and id_at(st, 5, H - 5) == ROAD * 1000
    # with a zero flow, identity overlap hands car a's id to car b (this is what the warp prevents)
    states_noflow = run(WarpIoUHead(), seq, flows=False)
    assert id_at(states_noflow[1], *centre(seq[1]["b"])) != ib


def test_two_cars_keep_ids_with_dis_flow():
    seq = []
    for t in range(4):
        seq.append({"a": (60 + 10 * t, 130, 40, 40, CAR), "b": (100 + 10 * t, 130, 40, 40, CAR)})
    head = WarpIoUHead()
    head.warp_options = WarpOptions(flow_preset="medium")
    states, prev = [], None
    for t, objs in enumerate(seq):
        fr, seg = scene(objs, t, seg_ids={"a": 30 - t, "b": 20 + t})
        prev = head.update(prev, fr, seg, MotionCue())  # no flow in the cue: DIS between prev.image and frame
        states.append(prev)
        if t > 0:  # the warped previous ids follow the true motion (+10 px), not the identity
            xa, ya = centre(seq[t - 1]["a"])
            assert head.last_warped[ya, xa + 10] == id_at(states[0], *centre(seq[0]["a"]))
            ys, xs = np.nonzero(head.last_warped == id_at(states[0], *centre(seq[0]["a"])))
            assert abs(xs.mean() - centre(objs["a"])[0]) < 2.5 and abs(ys.mean() - centre(objs["a"])[1]) < 1.5
    ia, ib = id_at(states[0], *centre(seq[0]["a"])), id_at(states[0], *centre(seq[0]["b"]))
    assert ia != ib
    for st, objs in zip(states, seq):
        assert id_at(st, *centre(objs["a"])) == ia and id_at(st, *centre(objs["b"])) == ib
    fr0, _ = scene(seq[0], 0)
    fr1, _ = scene(seq[1], 1)
    f = dis_flow(fr0.image, fr1.image, "medium")
    x, y = centre(seq[0]["a"])
    assert abs(float(np.median(f[0, y - 8 : y + 8, x - 8 : x + 8])) - 10) < 1
    assert abs(float(np.median(f[0, 5:40, 5:40]))) < 0.5  # static background


def test_new_object_gets_fresh_id_and_vanished_id_is_not_reused():
    seq = [
        {"a": (40, 140, 40, 30, CAR), "b": (200, 140, 40, 30, CAR)},
        {"a": (44, 140, 40, 30, CAR)},  # b disappears
        {"a": (48, 140, 40, 30, CAR), "c": (200, 140, 40, 30, CAR)},  # c appears where b was
        {"a": (52, 140, 40, 30, CAR), "c": (204, 140, 40, 30, CAR), "d": (120, 60, 30, 30, TRUCK)},
    ]
    states = run(WarpIoUHead(), seq)
    ia, ib = id_at(states[0], *centre(seq[0]["a"])), id_at(states[0], *centre(seq[0]["b"]))
    ic = id_at(states[2], *centre(seq[2]["c"]))
    assert all(id_at(st, *centre(o["a"])) == ia for st, o in zip(states, seq))
    assert ib not in set(torch.unique(states[1].panoptic.ids).tolist())
    assert ic not in (ia, ib) and decompose_id(ic) == (CAR, 3)
    assert id_at(states[3], *centre(seq[3]["c"])) == ic
    idd = id_at(states[3], *centre(seq[3]["d"]))
    assert decompose_id(idd) == (TRUCK, 1) and idd == TRUCK * 1000 + 1


def test_matching_respects_category():
    # frame 0: a car; frame 1: a truck exactly where the car was (same pixels) -> no match, new truck id
    seq = [{"a": (100, 120, 60, 40, CAR)}, {"t": (100, 120, 60, 40, TRUCK)}]
    states = run(WarpIoUHead(), seq, flows=False)
    i_car, i_truck = id_at(states[0], 130, 140), id_at(states[1], 130, 140)
    assert decompose_id(i_car)[0] == CAR and decompose_id(i_truck)[0] == TRUCK and i_car != i_truck
    # a car and a truck overlapping: the car keeps the car's id even though the truck overlaps it more
    seq = [{"a": (100, 120, 60, 40, CAR)}, {"t": (96, 120, 60, 40, TRUCK), "a": (140, 120, 60, 40, CAR)}]
    states = run(WarpIoUHead(), seq, flows=False)
    assert id_at(states[1], 170, 140) == id_at(states[0], 130, 140)
    assert decompose_id(id_at(states[1], 110, 140))[0] == TRUCK


def test_min_score_and_iou_mode():
    seq = [{"a": (100, 120, 40, 40, CAR)}, {"a": (136, 120, 40, 40, CAR)}]  # 10% overlap without flow
    st = run(WarpIoUHead(WarpIoUConfig(min_score=0.2)), seq, flows=False)
    assert id_at(st[1], 156, 140) != id_at(st[0], 120, 140)
    st = run(WarpIoUHead(WarpIoUConfig(min_score=0.05)), seq, flows=False)
    assert id_at(st[1], 156, 140) == id_at(st[0], 120, 140)
    # iou mode: a big current segment covering a small previous one has overlap 1 but a low IoU
    seq = [{"a": (100, 120, 20, 20, CAR)}, {"a": (80, 100, 80, 80, CAR)}]
    st = run(WarpIoUHead(WarpIoUConfig(match="iou", min_score=0.2)), seq, flows=False)
    assert id_at(st[1], 90, 110) != id_at(st[0], 110, 130)
    st = run(WarpIoUHead(WarpIoUConfig(match="overlap", min_score=0.2)), seq, flows=False)
    assert id_at(st[1], 90, 110) == id_at(st[0], 110, 130)


def test_each_previous_id_used_once_greedy():
    # one car splits into two segments: the better-overlapping one keeps the id, the other gets a new one
    seq = [{"a": (100, 120, 60, 40, CAR)}, {"a": (100, 120, 40, 40, CAR), "b": (140, 120, 20, 40, CAR)}]
    st = run(WarpIoUHead(), seq, flows=False)
    ia = id_at(st[0], 130, 140)
    assert id_at(st[1], 110, 140) == ia and id_at(st[1], 150, 140) not in (ia, 0)


def test_stuff_ids_and_first_frame():
    head = WarpIoUHead()
    fr, seg = scene({"a": (10, 10, 20, 20, CAR)}, 0)
    seg.segments.append(Segment(902, ROAD, False, 0.5))  # a second road segment: merged into one stuff id
    seg.ids[-10:, :10] = 902
    st = head.update(None, fr, seg, MotionCue())
    check_consistent(st)
    assert id_at(st, 5, H - 5) == ROAD * 1000 and id_at(st, 20, 20) == CAR * 1000 + 1
    assert st.frame_index == 0 and st.image is fr.image
    assert compose_id(CAR, 1000) != compose_id(CAR + 1, 0) and decompose_id(compose_id(CAR, 1234)) == (CAR, 1234)


def test_forward_warp_collisions():
    ids = np.zeros((4, 6), np.int64)
    ids[1, 1], ids[1, 3] = 5, 7
    flow = np.zeros((2, 4, 6), np.float32)
    flow[0, 1, 1] = 2.0  # pixel (1,1) -> (1,3) lands on the target of (1,3)
    out = forward_warp(ids, flow, splat="nearest")
    assert out[1, 3] == 7 and out[1, 1] == 0  # last write (raster order) wins
    depth = np.ones((4, 6), np.float32)
    depth[1, 1] = 0.5
    assert forward_warp(ids, flow, depth, splat="nearest")[1, 3] == 5  # nearer wins
    depth[1, 1] = 3.0
    assert forward_warp(ids, flow, depth, splat="nearest")[1, 3] == 7
    # bilinear splat fills holes from sub-pixel targets but never overrides a pixel's own nearest source
    flow[0, 1, 1] = 0.4
    out = forward_warp(ids, flow, splat="bilinear")
    assert out[1, 1] == 5 and out[1, 2] == 5 and out[1, 3] == 7
    # out-of-image targets are dropped
    flow[0, 1, 3] = 10
    assert 7 not in forward_warp(ids, flow, splat="nearest")


def test_rigid_flow_and_depth_cue():
    depth = np.full((H, W), 10.0, np.float32)
    pose0 = np.array([0, 0, 0, 0, 0, 0, 1.0])
    pose1 = np.array([0.5, 0, 0, 0, 0, 0, 1.0])  # camera moves 0.5 m to the right: the scene moves left
    flow, zc, valid = rigid_flow(depth, pose0, pose1, np.array([K.fx, K.fy, K.cx, K.cy]))
    assert valid.all() and np.allclose(flow[0], -K.fx * 0.5 / 10, atol=1e-4) and np.allclose(flow[1], 0, atol=1e-4)
    # a cue with depth + poses: things follow the flow, stuff the rigid warp; ids stay consistent
    seq = [{"a": (100, 120, 40, 40, CAR)}, {"a": (130, 120, 40, 40, CAR)}]
    head = WarpIoUHead()
    fr0, seg0 = scene(seq[0], 0)
    fr1, seg1 = scene(seq[1], 1)
    s0 = head.update(None, fr0, seg0, MotionCue())
    cue = MotionCue(flow=flow_of(seq[0], seq[1]), depth_prev=torch.from_numpy(depth),
                    pose_prev=torch.tensor(pose0), pose_cur=torch.tensor(pose1), intrinsics=K.vector())
    s1 = head.update(s0, fr1, seg1, cue)
    assert id_at(s1, 150, 140) == id_at(s0, 120, 140)
    warped = head.last_warped
    assert warped[140, 150] == id_at(s0, 120, 140)  # car warped with the flow (+30 px)
    assert warped[5, 5] == BUILDING * 1000  # stuff warped rigidly (-14.4 px), the image corner refilled


def test_registered_hook():
    import pvslam_plugins.vps.warp_iou as plugin

    got = []
    plugin.register_vps_heads(register=lambda name, factory, model, description="": got.append((name, factory, model)))
    name, factory, model = got[0]
    assert name == "warp_iou" and isinstance(factory(model(), None), WarpIoUHead)
    with pytest.raises(Exception):
        model(mtach="iou")
