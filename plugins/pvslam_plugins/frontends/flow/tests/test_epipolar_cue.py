"""The map-independent epipolar cue (epipolar_cue.py): on a synthetic two-view scene with known motion, a vehicle
crossing the view (off its epipolar lines) and one overtaking the camera (negative depth) are flagged, the static
scene and a vehicle driving straight at the camera (a static point at another depth) are not; the per-pixel tests
are checked against a brute-force reference; a stopped camera gives no mask; the frontend keeps the mask on both
keyframes and ORs it into every judgement of their edges."""
import math

import numpy as np
import torch

from pvslam_plugins.frontends.flow import epipolar_cue as E
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend, _Keyframe

H, W = 30, 40
FX = FY = 34.0
CX, CY = (W - 1) / 2, (H - 1) / 2
INTR = (FX, FY, CX, CY)


def _rot_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


# vehicles: fronto-parallel boxes (x range, y range, z at time 0) and their displacement from time 0 to time 1 (m)
VEHICLES = {
    "crossing": ((-4.5, -1.0), (-0.5, 1.5), 9.0, (0.6, 0.0, 0.0)),
    "overtaking": ((1.2, 3.4), (-0.5, 1.5), 10.0, (0.0, 0.0, 3.0)),  # faster than the camera: moves away
    "oncoming": ((4.0, 6.5), (-0.3, 1.5), 15.0, (0.0, 0.0, -1.0)),  # straight at the camera
}


def _render(view, forward, yaw):
    """Ray-cast camera ``view`` (0 or 1) of the street: ground plane y = 1.5 m (y down), a far wall at z = 40 m, the
    vehicles at their time-``view`` positions.  Returns the 3D point of every pixel at time ``view`` [H, W, 3]
    (world), its vehicle label [H, W] (-1: static) and the camera (centre [3], axes R_wc [3, 3])."""
    Rwc = _rot_y(yaw * view)
    c = np.array([0.0, 0.0, forward * view])
    ys, xs = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    d = np.stack([(xs - CX) / FX, (ys - CY) / FY, np.ones_like(xs)], -1) @ Rwc.T  # world rays [H, W, 3]
    best = (40.0 - c[2]) / d[..., 2]  # the far wall
    with np.errstate(divide="ignore", invalid="ignore"):
        s_g = np.where(d[..., 1] > 1e-9, (1.5 - c[1]) / d[..., 1], np.inf)
    best = np.minimum(best, s_g)
    label = np.full((H, W), -1)
    for k, (xr, yr, z0, m) in enumerate(VEHICLES.values()):
        z = z0 + m[2] * view
        s_v = (z - c[2]) / d[..., 2]
        X = c + s_v[..., None] * d
        hit = ((X[..., 0] >= xr[0] + m[0] * view) & (X[..., 0] <= xr[1] + m[0] * view) & (X[..., 1] >= yr[0])
               & (X[..., 1] <= yr[1]) & (s_v > 0) & (s_v < best))
        best = np.where(hit, s_v, best)
        label[hit] = k
    return c + best[..., None] * d, label, (c, Rwc)


def _scene(forward=1.0, yaw=2.0, view=0):
    """Camera 1 = camera 0 moved ``forward`` m along z and turned by ``yaw`` deg.  The flow of camera ``view``'s
    pixels into the other camera: BA-pixel target [2, H, W], weight, the vehicles' masks in that view's pixels and
    (R, t) of that view -> the other (X_other = R X + t)."""
    P, label, (c, Rwc) = _render(view, forward, yaw)
    other = 1 - view
    moved = P.copy()
    for k, (_, _, _, m) in enumerate(VEHICLES.values()):
        moved[label == k] += (other - view) * np.asarray(m)
    Ro = _rot_y(yaw * other)
    co = np.array([0.0, 0.0, forward * other])
    P1 = (moved - co) @ Ro  # camera coordinates of the other view: R_wc^T (X - c)
    target = torch.from_numpy(np.stack([FX * P1[..., 0] / P1[..., 2] + CX,
                                        FY * P1[..., 1] / P1[..., 2] + CY]).astype(np.float32))
    regions = {name: label == k for k, name in enumerate(VEHICLES)}
    R = Ro.T @ Rwc
    return target, torch.ones(H, W), regions, R, Ro.T @ (c - co)


def _brute_force(target, weight, R, t, thresh, back):
    """Per pixel, with the true motion: the Sampson distance (BA px) to the epipolar geometry and the parallax
    component away from the epipole; candidates as the cue defines them (a loop, no vectorisation)."""
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ess = tx @ R
    out = np.zeros((H, W), bool)
    for y in range(H):
        for x in range(W):
            if weight[y, x] <= 0.5:
                continue
            u, v = float(target[0, y, x]), float(target[1, y, x])
            if not (0 <= u <= W - 1 and 0 <= v <= H - 1):
                continue
            x0 = np.array([(x - CX) / FX, (y - CY) / FY, 1.0])
            x1 = np.array([(u - CX) / FX, (v - CY) / FY, 1.0])
            a, b = Ess @ x0, Ess.T @ x1
            samp = abs(x1 @ a) / math.sqrt(a[0] ** 2 + a[1] ** 2 + b[0] ** 2 + b[1] ** 2) * FX
            r = R @ x0
            inf = r[:2] / r[2]
            away = t[:2] - t[2] * inf
            signed = float((x1[:2] - inf) @ away / np.linalg.norm(away)) * FX
            out[y, x] = samp > thresh or signed < -back
    return out


def test_candidates_match_the_brute_force_reference_and_find_the_movers():
    target, weight, reg, R, t = _scene()
    cand = E.epipolar_candidates(target, weight, INTR, thresh=0.5, rel=0.0, back=0.5, ransac_px=0.05)
    assert cand is not None
    ref = _brute_force(target.numpy(), weight.numpy(), R, t / np.linalg.norm(t), 0.5, 0.5)
    # the fitted motion is the true one up to noise-free RANSAC precision: the same pixels, bar a borderline few
    assert int((cand.numpy() != ref).sum()) <= 2
    static = ~(reg["crossing"] | reg["overtaking"] | reg["oncoming"])
    inside = (target[0] >= 0) & (target[0] <= W - 1) & (target[1] >= 0) & (target[1] <= H - 1)
    # (the overtaking car's pixels nearest the epipole have the least parallax: a few stay below `back`)
    for name, least in (("crossing", 0.95), ("overtaking", 0.8)):
        judged = torch.from_numpy(reg[name]) & inside
        assert float(cand[judged].float().mean()) > least, name
    # a car driving straight at the camera is a static point at another depth in two views: not flagged
    assert float(cand[torch.from_numpy(reg["oncoming"])].float().mean()) < 0.2
    assert float(cand[torch.from_numpy(static)].float().mean()) < 0.01


def test_mask_groups_regions_and_rejects_a_stopped_camera():
    target, weight, reg, _, _ = _scene()
    m = E.epipolar_mask(target, weight, INTR, min_area=4, grow=0, ransac_px=0.05)
    assert m is not None and m.dtype == torch.bool and m.shape == (H, W)
    assert bool(m[16:18, 6:10].all())  # the crossing car's core
    # pure rotation: no translation, no epipolar geometry -> no mask rather than noise
    t0, w0, _, _, _ = _scene(forward=0.0, yaw=3.0)
    assert E.epipolar_mask(t0, w0, INTR, ransac_px=0.05) is None
    # too few confident pixels -> None
    assert E.epipolar_candidates(target, torch.zeros(H, W), INTR) is None


def test_judge_under_the_inverted_motion_matches_the_reverse_flow():
    """The new keyframe judges its own pixels (its edge back to the reference) under the inverted fit: the same
    pixels as the brute force with the true reverse motion."""
    target, weight, reg, R, t = _scene(view=0)
    tb, wb, regb, Rb, tb_t = _scene(view=1)
    assert np.allclose(Rb, R.T) and np.allclose(tb_t, -R.T @ t)
    motion = E.fit_motion(target, weight, INTR, ransac_px=0.05)
    cand = E.judge(tb, wb, INTR, E.invert(motion), inlier_px=0.05, thresh=0.5, rel=0.0, back=0.5)
    ref = _brute_force(tb.numpy(), wb.numpy(), Rb, tb_t / np.linalg.norm(tb_t), 0.5, 0.5)
    assert int((cand.numpy() != ref).sum()) <= 2
    assert float(cand[torch.from_numpy(regb["crossing"])].float().mean()) > 0.9


def test_frontend_keeps_the_cue_on_both_keyframes():
    from pvslam_core.types import Frame, Intrinsics
    from pvslam_plugins.frontends.flow.frontend import _Edge

    target, weight, reg, _, _ = _scene(view=0)
    tb, wb, regb, _, _ = _scene(view=1)
    cfg = FlowFrontendConfig(epipolar_cue=True, epipolar_ransac_px=0.05, dynamic_grow=0)
    fe = FlowFrontend(cfg)
    gray = np.zeros((120, 160), np.uint8)
    fe._kfs[0] = _Keyframe(gray=gray, frame_index=0)
    fe._kfs[1] = _Keyframe(gray=gray, frame_index=2)
    fe._edges[(1, 0)] = _Edge(tb, wb)  # the new keyframe's edge back to its reference
    # a full-resolution frame 8x the BA grid whose intrinsics scale to INTR
    intr = Intrinsics(fx=FX * 8, fy=FY * 8, cx=(CX + 0.5) * 8 - 0.5, cy=(CY + 0.5) * 8 - 0.5, width=W * 8, height=H * 8)
    frame = Frame(index=2, timestamp=0.2, image=torch.zeros(3, H * 8, W * 8, dtype=torch.uint8), intrinsics=intr)
    mask, fit = fe._cue_mask(target.numpy(), weight.numpy(), frame)
    assert np.allclose(fit[1], INTR)
    assert torch.equal(mask, E.epipolar_mask(target, weight, INTR, ransac_px=0.05, grow=0))
    fe._epipolar_cue(0, 1, mask, fit, target)
    m0, m1 = fe._kfs[0].cue, fe._kfs[1].cue
    assert torch.equal(m0, mask) and torch.equal(fe._kfs[0].dyn > 0, m0)
    # each keyframe holds the crossing car in its own pixels
    for m, r in ((m0, reg), (m1, regb)):
        assert float(m[torch.from_numpy(r["crossing"])].float().mean()) > 0.9
    assert fe.stats["epipolar_cue_calls"] == 1
    # the source keyframes' cue is OR-ed into every edge judgement (dynamic_masking._persisted)
    p = fe._persisted([fe._kfs[1], fe._kfs[0]], H, W, "cue")
    assert torch.equal(p[0], m1) and torch.equal(p[1], m0)


def test_a_removed_reference_still_gives_the_new_keyframe_its_mask():
    """The tracking reference was a provisional keyframe, removed just before the new keyframe came (no edge back
    to it): the new keyframe takes the reference-pixel mask moved along the tracked flow."""
    from pvslam_plugins.frontends.flow import dynamic as D

    target, weight, reg, _, _ = _scene(view=0)
    fe = FlowFrontend(FlowFrontendConfig(epipolar_cue=True, epipolar_ransac_px=0.05, dynamic_grow=0))
    fe._kfs[1] = _Keyframe(gray=np.zeros((120, 160), np.uint8), frame_index=2)
    mask = E.epipolar_mask(target, weight, INTR, ransac_px=0.05, grow=0)
    fe._epipolar_cue(0, 1, mask, None, target)  # keyframe 0 is gone
    assert 0 not in fe._kfs
    assert torch.equal(fe._kfs[1].cue, D.warp_mask(mask.float(), target, 0) > 0.5)
    assert bool(fe._kfs[1].cue.any())


def test_edge_cues_judge_both_keyframes_of_a_new_edge():
    """_edge_cues: the newest keyframe's freshly computed edge to an older keyframe is fitted on its own and judged
    in both directions; the crossing car lands in both keyframes' masks, the static scene does not."""
    from pvslam_plugins.frontends.flow.frontend import _Edge

    tb, wb, regb, _, _ = _scene(view=1)  # keyframe 1 (the newest) -> keyframe 0
    tf, wf, reg, _, _ = _scene(view=0)
    fe = FlowFrontend(FlowFrontendConfig(epipolar_cue=True, epipolar_ransac_px=0.05, dynamic_grow=0))
    gray = np.zeros((120, 160), np.uint8)
    fe._kfs[0] = _Keyframe(gray=gray, frame_index=0)
    fe._kfs[1] = _Keyframe(gray=gray, frame_index=2)
    fe._edges[(1, 0)], fe._edges[(0, 1)] = _Edge(tb, wb), _Edge(tf, wf)

    class G:
        intrinsics = torch.tensor(INTR)

    fe._edge_cues(G(), [(1, 0)])
    for kf, r in ((fe._kfs[1], regb), (fe._kfs[0], reg)):
        assert kf.cue is not None
        assert float(kf.cue[torch.from_numpy(r["crossing"])].float().mean()) > 0.9
        static = ~torch.from_numpy(r["crossing"] | r["overtaking"] | r["oncoming"])
        assert float(kf.cue[static].float().mean()) < 0.05
    fe2 = FlowFrontend(FlowFrontendConfig(epipolar_cue=True, epipolar_edges=0))
    fe2._kfs, fe2._edges = {0: _Keyframe(gray=gray, frame_index=0), 1: _Keyframe(gray=gray, frame_index=2)}, dict(fe._edges)
    fe2._edge_cues(G(), [(1, 0)])
    assert fe2._kfs[1].cue is None  # epipolar_edges = 0: the tracked flow only


def _judged_mask(**cfg):
    """test_dynamic's two-keyframe scene (a textured car moving on its own): keyframe 1's edge mask as judged on the
    edge's second observation, with a hand-set cue region on keyframe 1."""
    import _flow_scenes as S
    from test_dynamic import BA_H, BA_W, _graph3, _scene as car_scene

    imgs, g, _ = car_scene()
    fe = FlowFrontend(FlowFrontendConfig(preset="medium", epipolar_edges=0, **cfg))  # only the hand-set cue
    fe.add_keyframe(0, S.frame(imgs[0], 0), None)
    fe.add_keyframe(1, S.frame(imgs[1], 1), None)
    cue = torch.zeros(BA_H, BA_W, dtype=torch.bool)
    cue[1:4, 1:4] = True
    fe._kfs[1].cue = cue
    fe.observe(g, torch.tensor([1]), torch.tensor([0]))
    return fe.observe(g, torch.tensor([1]), torch.tensor([0])).dynamic[0] > 0, cue


def test_without_a_segmenter_the_cue_joins_or_replaces_the_residual_test():
    assert not FlowFrontendConfig().epipolar_cue  # off by default (static scenes: bench/RESULTS.md, issue 13)
    residual, _ = _judged_mask(epipolar_cue=False)  # the residual test's regions (the moving car) alone
    assert bool(residual.any())
    alone, cue = _judged_mask(epipolar_cue=True, epipolar_replaces_residual=True)  # the cue alone
    assert torch.equal(alone, cue)
    both, _ = _judged_mask(epipolar_cue=True)  # the default with the cue: both OR-ed
    assert not FlowFrontendConfig().epipolar_replaces_residual
    assert torch.equal(both, residual | cue)


def test_keyframes_with_a_segmentation_skip_the_cue_unless_asked():
    from pvslam_core.types import Frame, Intrinsics

    target, weight, reg, _, _ = _scene(view=0)
    intr = Intrinsics(fx=FX * 8, fy=FY * 8, cx=(CX + 0.5) * 8 - 0.5, cy=(CY + 0.5) * 8 - 0.5, width=W * 8, height=H * 8)
    frame = Frame(index=2, timestamp=0.2, image=torch.zeros(3, H * 8, W * 8, dtype=torch.uint8), intrinsics=intr)
    pend = {"fwd": (target.numpy(), weight.numpy()), "last_sid": 0}
    out = {}
    for with_seg, cfg in ((False, {}), (True, {}), (True, {"epipolar_with_segmenter": True})):
        fe = FlowFrontend(FlowFrontendConfig(epipolar_cue=True, epipolar_ransac_px=0.05, dynamic_grow=0, **cfg))
        seg = torch.zeros(H, W, dtype=torch.int64) if with_seg else None
        fe._kfs[0] = _Keyframe(gray=np.zeros((120, 160), np.uint8), frame_index=0, seg_ba=seg)
        fe._kfs[1] = _Keyframe(gray=np.zeros((120, 160), np.uint8), frame_index=2, seg_ba=seg)
        fe._keyframe_cue(pend, 1, frame)
        out[(with_seg, bool(cfg))] = fe._kfs[0].cue
    assert out[(False, False)] is not None and bool(out[(False, False)].any())  # no segmenter: the cue
    assert out[(True, False)] is None  # a segmenter: its vote, no cue (the default)
    assert torch.equal(out[(True, True)], out[(False, False)])  # epipolar_with_segmenter: both


def test_per_frame_cue_in_tracking_follows_the_keyframe_cue_gate():
    """epipolar_track judges tracked frames only with the keyframe cue on and on keyframes the cue runs on (not
    segmented ones unless epipolar_with_segmenter), as the keyframe cue itself."""
    import _flow_scenes as S
    from test_dynamic import _scene as _street

    imgs, _, _ = _street()
    calls = {}
    for name, cfg, seg in (("track", dict(epipolar_cue=True, epipolar_track=True), False),
                           ("no cue", dict(epipolar_track=True), False),
                           ("segmented", dict(epipolar_cue=True, epipolar_track=True), True),
                           ("segmented, asked", dict(epipolar_cue=True, epipolar_track=True,
                                                     epipolar_with_segmenter=True), True)):
        fe = FlowFrontend(FlowFrontendConfig(preset="medium", **cfg))
        fe.add_keyframe(0, S.frame(imgs[0], 0), None)
        if seg:  # what _cue_on looks at: the keyframe has a segmentation
            fe._kfs[0].seg_ba = torch.zeros(1, 1, dtype=torch.int64)
        seen = []
        orig = fe._cue_mask
        fe._cue_mask = lambda *a, _o=orig, _s=seen: _s.append(1) or _o(*a)
        fe.track(S.frame(imgs[1], 1), None)
        calls[name] = len(seen)
    assert calls == {"track": 1, "no cue": 0, "segmented": 0, "segmented, asked": 1}

