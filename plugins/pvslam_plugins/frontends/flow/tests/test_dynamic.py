"""Geometric dynamic masks (dynamic.py) against brute-force references, and their use by the frontend: tracking
weights of a moving region, a new keyframe inheriting its reference's mask."""
import numpy as np
import torch

from pvslam_core.slam.confidence import observed_flow_weight
from pvslam_plugins.frontends.flow import dynamic as D
from pvslam_plugins.frontends.flow import dynamic_masking as masking_module
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend

import _flow_scenes as S

BA_H, BA_W = S.H // 8, S.W // 8


def test_residual_candidates_absolute_and_relative_threshold():
    g = torch.Generator().manual_seed(0)
    res = torch.rand(2, 6, 7, generator=g) * 4.0
    valid = torch.rand(2, 6, 7, generator=g) > 0.2
    out = D.residual_candidates(res, valid, thresh=1.0, rel_thresh=2.0)
    for n in range(2):  # brute force: per edge, the median of the valid residuals
        vals = sorted(float(v) for v, ok in zip(res[n].flatten(), valid[n].flatten()) if ok)
        med = vals[(len(vals) - 1) // 2]  # torch's lower median
        thr = max(1.0, 2.0 * med)
        for y in range(6):
            for x in range(7):
                assert bool(out[n, y, x]) == (bool(valid[n, y, x]) and float(res[n, y, x]) > thr)


def test_group_regions_keeps_coherent_blobs_only():
    cand = torch.zeros(1, 12, 16, dtype=torch.bool)
    cand[0, 3:6, 4:8] = True  # a 3x4 blob (12 px): an object
    cand[0, 10, 1] = cand[0, 0, 15] = cand[0, 8, 12] = True  # isolated flow errors
    cand[0, 9, 12] = True  # a 2-pixel pair (8-connected with (8, 12))
    out = D.group_regions(cand, min_area=4, grow=1)[0]
    expected = torch.zeros(12, 16, dtype=torch.bool)
    expected[2:7, 3:9] = True  # the blob grown by one pixel on every side
    assert torch.equal(out, expected)
    assert torch.equal(D.group_regions(cand, min_area=2, grow=0)[0], cand[0] & ~_isolated(cand[0]))


def _isolated(m):
    out = torch.zeros_like(m)
    h, w = m.shape
    for y in range(h):
        for x in range(w):
            if m[y, x] and not any(m[yy, xx] for yy in range(max(0, y - 1), min(h, y + 2))
                                   for xx in range(max(0, x - 1), min(w, x + 2)) if (yy, xx) != (y, x)):
                out[y, x] = True
    return out


def test_keyframe_vote_and_warp():
    a = torch.zeros(4, 5)
    b = torch.zeros(4, 5)
    c = torch.zeros(4, 5)
    a[1, 1] = b[1, 1] = 1  # 2 of 3 edges
    c[2, 3] = 1  # 1 of 3
    v = D.keyframe_vote([a, b, c])
    assert v[1, 1] == 1 and v[2, 3] == 0 and float(v.sum()) == 1
    assert D.keyframe_vote([]) is None
    ys, xs = torch.meshgrid(torch.arange(4.0), torch.arange(5.0), indexing="ij")
    target = torch.stack([xs + 2.2, ys - 0.8])  # the view moved: pixel (x, y) -> (x + 2, y - 1)
    m = torch.zeros(4, 5)
    m[2, 1] = 1
    w = D.warp_mask(m, target, grow=0)
    assert w[1, 3] == 1 and float(w.sum()) == 1
    assert float(D.warp_mask(m, target, grow=1).sum()) == 9  # a 3x3 square around (1, 3)


def _scene():
    """Keyframes 0 and 1 (static background shifted by 16 px, explained by the camera) with a textured 'car' that
    moves by another (+24, +10) px; frame 2 continues both motions."""
    from test_flow_frontend import _graph

    big = S.texture("astronaut")
    patch = S.texture("coffee", (72, 96))
    x0, y0, dx = 100, 80, 16.0
    imgs = [S.with_patch(S.shifted(big, k * dx), patch, x0 + k * (int(dx) + 24), y0 + 10 * k) for k in range(3)]
    return imgs, _graph([0.0, dx]), (x0 + int(dx) + 24, y0 + 10)


def test_tracking_weights_follow_the_reference_keyframes_moving_region(monkeypatch):
    imgs, g, (x1, y1) = _scene()
    masked = {}
    for track in (False, True):
        monkeypatch.setattr(masking_module, "DYNAMIC_TRACK", track)
        fe = FlowFrontend(FlowFrontendConfig(dis={"preset": "medium"}))
        fe.add_keyframe(0, S.frame(imgs[0], 0), None)
        fe.add_keyframe(1, S.frame(imgs[1], 1), None)
        fe.observe(g, torch.tensor([0, 1]), torch.tensor([1, 0]))  # the BA's first round on both edges
        masked[track] = fe.track(S.frame(imgs[2], 2), None)
        kf1 = fe.masking.keyframe(1)
    car = torch.zeros(BA_H, BA_W, dtype=torch.bool)  # BA pixels fully inside the car in keyframe 1
    car[y1 // 8 + 1:(y1 + 72) // 8 - 1, x1 // 8 + 1:(x1 + 96) // 8 - 1] = True
    static = torch.ones(BA_H, BA_W, dtype=torch.bool)  # away from the car in keyframes 0 (disoccluded) and 1
    static[(y1 - 10) // 8 - 4:(y1 + 72) // 8 + 4, (x1 - 40) // 8 - 4:(x1 + 96 + 40) // 8 + 4] = False
    static[:, BA_W - 6:] = False
    assert kf1.dyn_judged and float(kf1.dyn[car].mean()) > 0.9 and float(kf1.dyn[static].mean()) < 0.02
    w0, w1 = masked[False].weight[0], masked[True].weight[0]
    torch.testing.assert_close(w1[static], w0[static])  # static pixels keep their confidence exactly
    bound = float(observed_flow_weight(torch.tensor(1.0), torch.tensor(1.0)))  # eq. 4 on a dynamic pixel
    assert float(w0[car].mean()) > 0.3 and float(w1[car].max()) <= bound + 1e-7


def test_new_keyframe_starts_from_its_references_mask_moved_along_the_flow():
    imgs, g, (x1, y1) = _scene()
    fe = FlowFrontend(FlowFrontendConfig(dis={"preset": "medium"}))
    fe.add_keyframe(0, S.frame(imgs[0], 0), None)
    fe.add_keyframe(1, S.frame(imgs[1], 1), None)
    fe.observe(g, torch.tensor([0, 1]), torch.tensor([1, 0]))
    r = fe.track(S.frame(imgs[2], 2), None)
    fe.add_keyframe(2, S.frame(imgs[2], 2), None)
    new = fe.masking.keyframe(2)
    assert not new.dyn_judged and new.dyn is not None
    ref = fe.masking.keyframe(1).dyn
    expected = D.warp_mask(ref, r.target, grow=1)  # the reference's mask along the tracked flow
    assert torch.equal(new.dyn, expected)
    x2, y2 = x1 + 40, y1 + 10  # the car in frame 2
    inside = torch.zeros(BA_H, BA_W, dtype=torch.bool)
    inside[y2 // 8 + 1:(y2 + 72) // 8 - 1, x2 // 8 + 1:min(BA_W, (x2 + 96) // 8 - 1)] = True
    assert float(new.dyn[inside].mean()) > 0.8
    # an edge from the new keyframe takes that mask at its first observation
    obs = fe.observe(_graph3(), torch.tensor([2]), torch.tensor([1]))
    assert torch.equal(obs.dynamic[0], new.dyn)


def _graph3():
    from test_flow_frontend import _graph

    return _graph([0.0, 16.0, 32.0])


def test_no_masks_before_the_map_has_a_motion_estimate(monkeypatch):
    """Before the initialisation every keyframe of a fragment has the same pose: the residual against that
    'estimate' is the whole flow, so nothing is judged (no edge or keyframe mask, tracking weights untouched);
    the same scene with the camera motion estimated masks the car (test above)."""
    from test_flow_frontend import _graph

    imgs, _, _ = _scene()
    g = _graph([0.0, 0.0])  # identical poses: no estimate yet
    # a lower relative threshold than the default, so that judged against the zero motion the car (5 BA px of
    # flow) would stand out from the background (2 BA px): what happened in a turning hand-held room
    monkeypatch.setattr(masking_module, "DYNAMIC_REL_THRESH", 1.5)
    fe = FlowFrontend(FlowFrontendConfig(dis={"preset": "medium"}))
    ref = FlowFrontend(FlowFrontendConfig(dis={"preset": "medium"}, dynamic={"enabled": False}))
    for f in (fe, ref):
        f.add_keyframe(0, S.frame(imgs[0], 0), None)
        f.add_keyframe(1, S.frame(imgs[1], 1), None)
    for _ in range(3):  # first observation and the dynamic updates after it
        obs = fe.observe(g, torch.tensor([0, 1]), torch.tensor([1, 0]))
    obs_ref = ref.observe(g, torch.tensor([0, 1]), torch.tensor([1, 0]))
    assert float(obs.dynamic.abs().sum()) == 0.0
    torch.testing.assert_close(obs.weight, obs_ref.weight)
    r, r_ref = fe.track(S.frame(imgs[2], 2), None), ref.track(S.frame(imgs[2], 2), None)
    kf1 = fe.masking.keyframe(1)
    assert kf1.dyn is None or float(kf1.dyn.sum()) == 0.0
    torch.testing.assert_close(r.weight, r_ref.weight)
