"""The ``flow`` frontend: motion filter, failures, edge cache by stable ids, dynamic masking, registry."""
import time

import numpy as np
import pytest
import torch

from pvslam_core.slam.confidence import observed_flow_weight
from pvslam_plugins.frontends.flow import dynamic_masking as masking_module
from pvslam_plugins.frontends.flow import frontend as frontend_module
from pvslam_plugins.frontends.flow import pair_flow, track_starts
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend, make_frontend

import _flow_scenes as S

BA_H, BA_W = S.H // 8, S.W // 8
DISP = 0.5  # fronto-parallel plane at z = 2: a lateral camera translation tx shifts the image by -fx_ba * tx * DISP


def _graph(n_shifts_px):
    """A FrameGraph whose keyframes look at a fronto-parallel plane; keyframe k's image is shifted by
    ``n_shifts_px[k]`` full-res px (camera translated along -x)."""
    from pvslam_core.slam.graph import FrameGraph

    intr = S.INTR.scaled(1 / 8).vector()
    g = FrameGraph(BA_H, BA_W, intr)
    for k, dx in enumerate(n_shifts_px):
        tx = -(dx / 8.0) / (float(intr[0]) * DISP)
        pose = torch.tensor([tx, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)
        g.add_keyframe(k, 0.1 * k, pose, torch.full((BA_H, BA_W), DISP))
    return g


def _grid():
    ys, xs = torch.meshgrid(torch.arange(BA_H, dtype=torch.float32), torch.arange(BA_W, dtype=torch.float32),
                            indexing="ij")
    return xs, ys


def _frontend(**kw):
    return FlowFrontend(FlowFrontendConfig(**kw))


# ------------------------------------------------------------------------------------------ track --
def test_motion_filter_thresholds_and_targets(monkeypatch):
    big = S.texture("astronaut")
    # the weights of the forward-backward and photometric checks alone: the texture term (on by default) lowers the
    # picture's flat parts, which test_texture_term_lowers_flat_regions_once_per_source_image covers
    monkeypatch.setattr(pair_flow, "TEXTURE_TAU", 0.0)
    fe = _frontend()
    r0 = fe.track(S.frame(S.base(big), 0), None)
    assert r0.is_keyframe and not r0.failed  # the first frame is always a keyframe
    fe.add_keyframe(0, S.frame(S.base(big), 0), None)
    small = fe.track(S.frame(S.shifted(big, 8.0), 1), None)  # 1 BA px
    assert not small.failed and not small.is_keyframe
    assert small.mean_flow == pytest.approx(1.0, abs=0.1)
    big_move = fe.track(S.frame(S.shifted(big, 24.0, 4.0), 2), None)  # 3 BA px, > keyframe_thresh = 2
    assert big_move.is_keyframe and not big_move.failed
    assert big_move.mean_flow == pytest.approx(np.hypot(3.0, 0.5), abs=0.15)
    xs, ys = _grid()
    w = big_move.weight[0]
    ok = w > 0.5
    assert ok.float().mean() > 0.6
    assert big_move.target.shape == (2, BA_H, BA_W) and big_move.weight.shape == (2, BA_H, BA_W)
    assert float((big_move.target[0] - xs - 3.0).abs()[ok].median()) < 0.1
    assert float((big_move.target[1] - ys - 0.5).abs()[ok].median()) < 0.1
    # a lower threshold turns the small motion into a keyframe
    fe2 = _frontend(keyframes={"flow_thresh": 0.5})
    fe2.add_keyframe(0, S.frame(S.base(big), 0), None)
    assert fe2.track(S.frame(S.shifted(big, 8.0), 1), None).is_keyframe


def test_repeated_frame_is_not_a_failure():
    big = S.texture("chelsea")
    fe = _frontend()
    img = S.base(big)
    fe.add_keyframe(0, S.frame(img, 0), None)
    r = fe.track(S.frame(img.copy(), 1), None)
    assert not r.failed and not r.is_keyframe
    assert r.mean_flow < 0.02


def test_black_and_constant_frames_fail():
    big = S.texture("astronaut")
    fe = _frontend()
    fe.add_keyframe(0, S.frame(S.base(big), 0), None)
    for img in (np.zeros((S.H, S.W, 3), np.uint8), np.full((S.H, S.W, 3), 128, np.uint8)):
        r = fe.track(S.frame(img, 1), None)
        assert r.failed and not r.is_keyframe and "texture" in r.message
    # also before any keyframe exists
    assert _frontend().track(S.frame(np.zeros((S.H, S.W, 3), np.uint8), 0), None).failed


def test_sudden_jump_fails():
    fe = _frontend()
    fe.add_keyframe(0, S.frame(S.base(S.texture("astronaut")), 0), None)
    r = fe.track(S.frame(S.base(S.texture("coffee")), 1), None)
    assert r.failed and "forward-backward" in r.message
    # tracking still works afterwards (failure changed nothing)
    r2 = fe.track(S.frame(S.shifted(S.texture("astronaut"), 4.0), 2), None)
    assert not r2.failed and fe.num_keyframes == 1


# -------------------------------------------------------------------------------------- observe --
def test_observe_targets_and_track_reuse(monkeypatch):
    big = S.texture("astronaut")
    shifts = [0.0, 24.0, 44.0]  # 3 and 2.5 BA px: over the threshold of this camera (2 x 288 / 272 BA px)
    g = _graph(shifts)
    fe = _frontend(dynamic={"enabled": False})  # default: the track flow is reused for (k-1, k)
    assert fe.rounds == 1
    for k, dx in enumerate(shifts):
        f = S.frame(S.shifted(big, dx), k)
        if k:
            r = fe.track(f, None)
            assert r.is_keyframe
        fe.add_keyframe(k, f, None)
    # edges (0,1), (1,0), (1,2), (2,1) come from tracking; (0,2), (2,0) are computed now
    assert fe.stats["edges_computed"] == 0
    ii = torch.tensor([0, 1, 1, 2, 0, 2])
    jj = torch.tensor([1, 0, 2, 1, 2, 0])
    obs = fe.observe(g, ii, jj)
    assert fe.stats["edges_computed"] == 2
    assert obs.target.shape == (6, 2, BA_H, BA_W) and obs.weight.shape == (6, 2, BA_H, BA_W)
    assert obs.dynamic.shape == (6, BA_H, BA_W) and float(obs.dynamic.abs().max()) == 0.0
    xs, ys = _grid()
    for e in range(6):
        du = (shifts[int(jj[e])] - shifts[int(ii[e])]) / 8.0
        ok = obs.weight[e, 0] > 0.5
        err = (obs.target[e, 0] - xs - du).abs()[ok]
        assert float(err.median()) < 0.1, (e, float(err.median()))
        assert float((obs.target[e, 1] - ys).abs()[ok].median()) < 0.1
    assert torch.equal(obs.weight[:, 0], obs.weight[:, 1])
    assert 0.0 <= float(obs.weight.min()) and float(obs.weight.max()) <= 1.0
    # asking again returns the cache, computing nothing
    obs2 = fe.observe(g, ii, jj)
    assert fe.stats["edges_computed"] == 2
    assert torch.equal(obs2.target, obs.target)
    # without reuse all three pairs are computed for the edges
    monkeypatch.setattr(frontend_module, "REUSE_TRACK_FLOW", False)
    fe3 = _frontend(dynamic={"enabled": False})
    for k, dx in enumerate(shifts):
        f = S.frame(S.shifted(big, dx), k)
        if k:
            fe3.track(f, None)
        fe3.add_keyframe(k, f, None)
    fe3.observe(g, ii, jj)
    assert fe3.stats["edges_computed"] == 6


def test_keyframe_when_coverage_drops():
    """Forward motion: pixels leave the view long before the mean measured flow is large."""
    big = S.texture("astronaut")
    fe = _frontend()
    fe.add_keyframe(0, S.frame(S.base(big), 0), None)
    zoom, _ = S.affine_view(big, np.array([[1.12, 0.0, 0.0], [0.0, 1.12, 0.0]]))
    r = fe.track(S.frame(zoom, 1), None)
    assert not r.failed and r.mean_flow < 2.0
    lo = _frontend(keyframes={"min_coverage": 0.95})
    lo.add_keyframe(0, S.frame(S.base(big), 0), None)
    assert lo.track(S.frame(zoom, 1), None).is_keyframe
    off = _frontend(keyframes={"min_coverage": 0.0})
    off.add_keyframe(0, S.frame(S.base(big), 0), None)
    assert not off.track(S.frame(zoom, 1), None).is_keyframe


def test_state_follows_graph_notifications():
    """The frontend keys its cache by the graph's stable ids: removing a keyframe from the graph (which shifts later
    indices down) and retiring edges both reach it as notifications, and its cache follows."""
    big = S.texture("astronaut")
    shifts = [0.0, 12.0, 30.0, 44.0]
    g = _graph(shifts)
    fe = _frontend(dynamic={"enabled": False})
    g.add_listener(fe)
    for k, dx in enumerate(shifts):
        fe.add_keyframe(g.id_of(k), S.frame(S.shifted(big, dx), k), None)
    ii = torch.tensor([0, 2, 1, 3])
    jj = torch.tensor([2, 0, 3, 1])
    g.add_edges(ii, jj)
    before = fe.observe(g, ii, jj)
    computed = fe.stats["edges_computed"]
    assert sorted(fe.cached_edges()) == [(0, 2), (1, 3), (2, 0), (3, 1)]
    # the graph drops keyframe 1: its edges go from the cache, later graph indices shift down
    g.remove_keyframe(1)
    assert fe.num_keyframes == 3 and sorted(fe.cached_edges()) == [(0, 2), (2, 0)]
    after = fe.observe(g, torch.tensor([0, 1]), torch.tensor([1, 0]))  # old (0, 2) and (2, 0), now indices 0, 1
    assert fe.stats["edges_computed"] == computed  # served from the cache by stable id
    assert torch.equal(after.target, before.target[:2])
    # retiring edges drops their state too (the graph keeps their last observation)
    g.record_observations(after)
    assert g.retire_edges(torch.ones(g.num_edges, dtype=torch.bool)) == 2
    assert fe.cached_edges() == [] and g.num_retired == 2
    stored = g.retired_observations(torch.tensor([0, 1]), torch.tensor([1, 0]))
    assert float((stored.target - after.target).abs().max()) < 0.02  # float16 offsets
    # ids are never reused, and a keyframe id is added once
    g.add_keyframe(5, 0.5, g.poses[-1], g.disps[-1])
    assert g.id_of(-1) == 4
    fe.add_keyframe(4, S.frame(S.shifted(big, 60.0), 5), None)
    with pytest.raises(ValueError):
        fe.add_keyframe(4, S.frame(S.base(big), 6), None)
    with pytest.raises(KeyError):  # observing a keyframe the frontend never saw is a clear error
        g.add_keyframe(6, 0.6, g.poses[-1], g.disps[-1])
        fe.observe(g, torch.tensor([0]), torch.tensor([4]))


def test_reprojection_init_for_long_baseline_edge(monkeypatch):
    big = S.texture("astronaut")
    shifts = [0.0, 130.0]  # 16 BA px: beyond what DIS finds from a zero initialisation here
    xs, ys = _grid()

    def run(use_init):
        g = _graph(shifts)
        monkeypatch.setattr(frontend_module, "USE_REPROJECTION_INIT", use_init)
        fe = _frontend(dynamic={"enabled": False})
        for k, dx in enumerate(shifts):
            fe.add_keyframe(k, S.frame(S.shifted(big, dx), k), None)
        obs = fe.observe(g, torch.tensor([0]), torch.tensor([1]))
        ok = (xs + shifts[1] / 8 < BA_W - 1)  # pixels that stay in view
        err = (obs.target[0, 0] - xs - shifts[1] / 8).abs()[ok]
        return float(err.median()), fe.stats["reprojection_init_used"]

    err_init, used = run(True)
    err_zero, _ = run(False)
    assert used == 1
    assert err_init < 0.1, err_init
    assert err_zero > 1.0, err_zero


def test_discarded_pairs_are_computed_afresh_from_the_next_observes_poses():
    """A pair observed before the map knew the motion (identity poses: the initialisation's chain check) keeps no
    cached flow after ``discard_pairs``: the next observe starts it from the map's poses (reprojection init)."""
    big = S.texture("astronaut")
    shifts = [0.0, 130.0]  # 16 BA px: DIS needs the reprojection init here (the test above)
    xs, ys = _grid()
    ok = xs + shifts[1] / 8 < BA_W - 1  # pixels that stay in view
    fe = _frontend(dynamic={"enabled": False})
    for k, dx in enumerate(shifts):
        fe.add_keyframe(k, S.frame(S.shifted(big, dx), k), None)
    ii, jj = torch.tensor([0]), torch.tensor([1])

    def err(obs):
        return float((obs.target[0, 0] - xs - shifts[1] / 8).abs()[ok].median())

    blind = fe.observe(_graph([0.0, 0.0]), ii, jj)  # no motion known yet
    per_pair = fe.stats["edges_computed"]  # (both directions of the pair)
    assert err(blind) > 1.0 and per_pair > 0
    known = _graph(shifts)
    assert err(fe.observe(known, ii, jj)) == err(blind)  # cached: the blind flow would stay
    assert fe.stats["edges_computed"] == per_pair
    fe.discard_pairs(ii, jj)
    fresh = fe.observe(known, ii, jj)
    assert fe.stats["edges_computed"] == 2 * per_pair and err(fresh) < 0.1
    fe.discard_pairs(jj, ii)  # either direction forgets the pair
    fe.observe(known, ii, jj)
    assert fe.stats["edges_computed"] == 3 * per_pair


def test_initial_depth_median_of_previous_keyframe():
    big = S.texture("astronaut")
    g = _graph([0.0, 16.0])
    g.set_disps(torch.tensor([1]), torch.linspace(0.2, 1.0, BA_H * BA_W).reshape(1, BA_H, BA_W))
    fe = _frontend()
    for k, dx in enumerate([0.0, 16.0]):
        fe.add_keyframe(k, S.frame(S.shifted(big, dx), k), None)
    d = fe.initial_depth(g, 2)
    assert d.shape == (BA_H, BA_W)
    assert float(d[0, 0]) == pytest.approx(float(g.disps[1].median()))


# ------------------------------------------------------------------------- moving object / eq. 4 --
def _moving_patch_scene(convention, with_seg):
    """Static background shifted by 16 px between two keyframes (explained by the camera), plus a textured
    'car' that moves by another (+24, +10) px on its own."""
    big = S.texture("astronaut")
    patch = S.texture("coffee", (72, 96))
    x0, y0 = 100, 80
    dx = 16.0
    i0 = S.with_patch(S.base(big), patch, x0, y0)
    i1 = S.with_patch(S.shifted(big, dx), patch, x0 + int(dx) + 24, y0 + 10)
    seg0 = S.patch_segmentation(x0, y0, 72, 96) if with_seg else None
    seg1 = S.patch_segmentation(x0 + int(dx) + 24, y0 + 10, 72, 96) if with_seg else None
    g = _graph([0.0, dx])
    fe = _frontend(dynamic={"convention": convention}, dis={"preset": "medium"})  # a flow that tracks the object
    assert fe.rounds == 1  # one round per keyframe; masks apply from an edge's second observation
    fe.add_keyframe(0, S.frame(i0, 0), seg0)
    fe.add_keyframe(1, S.frame(i1, 1), seg1)
    ii, jj = torch.tensor([0, 1]), torch.tensor([1, 0])
    first = fe.observe(g, ii, jj)  # round 1: FB confidence only
    second = fe.observe(g, ii, jj)  # round 2: residual vs reprojection -> dynamic mask -> eq. 4
    # BA pixels fully inside the car in keyframe 0 (block centres 8x+3.5 in [x0, x0+96), 8y+3.5 in [y0, y0+72))
    car = torch.zeros(BA_H, BA_W, dtype=torch.bool)
    car[y0 // 8 + 1:(y0 + 72) // 8 - 1, x0 // 8 + 1:(x0 + 96) // 8 - 1] = True
    static = torch.ones(BA_H, BA_W, dtype=torch.bool)
    static[y0 // 8 - 4:(y0 + 72) // 8 + 4, x0 // 8 - 4:(x0 + 96 + 40) // 8 + 4] = False
    static[:, BA_W - 4:] = False  # leaves the image
    return first, second, car, static


def test_moving_patch_downweighted_with_paper_convention_only():
    """The deliberate sign decision: for observed-flow targets, dynamic pixels must lose weight (paper M_d = 1 on
    dynamic pixels); PVO's code convention (its mask is 1 on static pixels) would instead keep / raise them."""
    first, second, car, static = _moving_patch_scene("paper", with_seg=False)
    w1, w2 = first.weight[0, 0], second.weight[0, 0]
    # forward-backward confidence alone does not reject a rigidly moving textured object
    assert float(w1[car].mean()) > 0.5 * float(w1[static].mean())
    assert float(first.dynamic.abs().max()) == 0.0
    # after one round the residual against the camera-explained reprojection marks the object dynamic
    assert float(second.dynamic[0][car].mean()) > 0.9
    assert float(second.dynamic[0][static].mean()) < 0.02
    assert float(w2[car].mean()) < 1e-2 * float(w2[static].mean())
    torch.testing.assert_close(w2[static], w1[static])  # static pixels keep their FB confidence exactly

    _, pvo, car, static = _moving_patch_scene("pvo_code", with_seg=False)
    wp = pvo.weight[0, 0]
    assert float(pvo.dynamic[0][car].mean()) > 0.9  # same mask ...
    assert float(wp[car].mean()) > 0.3 * float(w1[static].mean())  # ... but the object is NOT down-weighted
    assert float(wp[car].mean()) > 100 * float(wp[static].mean())  # (static pixels are, instead)


def test_segment_vote_marks_whole_car():
    _, second, car, static = _moving_patch_scene("paper", with_seg=True)
    x0, y0 = 100, 80
    ys, xs = torch.meshgrid(torch.arange(BA_H), torch.arange(BA_W), indexing="ij")
    cx, cy = 8 * xs + 4, 8 * ys + 4  # block-centre pixel used to downsample the ids
    seg_car = (cx >= x0) & (cx < x0 + 96) & (cy >= y0) & (cy < y0 + 72)
    assert bool(second.dynamic[0][seg_car].bool().all())  # every pixel of the car segment, borders included
    assert float(second.dynamic[0][static].mean()) < 0.02
    assert float(second.weight[0, 0][seg_car].max()) <= float(observed_flow_weight(torch.tensor(1.0), torch.tensor(1.0)))
    assert float(observed_flow_weight(torch.tensor(1.0), torch.tensor(1.0))) < 5e-3


def test_registered_plugin(monkeypatch):
    from pvslam_core.registry import build_registry
    import pvslam_plugins.frontends.flow as flow_plugin

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    reg = build_registry(extra_modules=(flow_plugin,))
    spec = reg.get("frontend", "flow")
    cfg = spec.config_model(dis={"preset": "medium", "scale": 1.0})
    fe = spec.factory(cfg, type("Ctx", (), {"device": torch.device("cpu"), "ba_downsample": 8})())
    assert isinstance(fe, FlowFrontend) and fe.rounds == 1
    assert spec.factory(spec.config_model(rounds=2), type("Ctx", (), {"device": torch.device("cpu")})()).rounds == 2
    # renamed keys of earlier releases still load (test_config.py); ba_downsample comes from the graph now
    old = spec.config_model.model_validate({"eta": 7.0, "ba_downsample": 4})
    assert old.dynamic.panoptic_offset == 7.0
    with pytest.raises(Exception):
        spec.config_model(dis={"scale": 0.3})
    with pytest.raises(Exception):
        spec.config_model(presett="fast")
    assert isinstance(make_frontend(FlowFrontendConfig(dynamic={"enabled": False}), None), FlowFrontend)


def test_memory_per_keyframe_bounded():
    big = S.texture("astronaut")
    fe = _frontend()
    for k in range(5):
        fe.add_keyframe(k, S.frame(S.shifted(big, 3.0 * k), k), S.patch_segmentation(10, 10, 20, 20))
    per_kf = fe.memory_bytes() / 5
    assert per_kf < 200_000, per_kf


def test_dynamic_mask_reestimated_only_dynamic_updates_times(monkeypatch):
    """Each edge's mask is re-estimated on its 2nd .. (1 + DYNAMIC_UPDATES)-th observation, then kept."""
    big = S.texture("astronaut")
    g = _graph([0.0, 16.0])
    monkeypatch.setattr(masking_module, "DYNAMIC_UPDATES", 2)
    fe = _frontend()
    fe.add_keyframe(0, S.frame(S.base(big), 0), None)
    fe.add_keyframe(1, S.frame(S.shifted(big, 16.0), 1), None)
    calls = []
    orig = fe.masking._update
    monkeypatch.setattr(fe.masking, "_update", lambda *a, **k: (calls.append(list(a[3])), orig(*a, **k)))
    ii, jj = torch.tensor([0, 1]), torch.tensor([1, 0])
    for _ in range(5):
        fe.observe(g, ii, jj)
    assert calls == [[0, 1], [0, 1]]


def test_tracking_starts_from_the_previous_frames_motion(monkeypatch):
    """A texture sliding 14 px a frame: from the second frame after a keyframe on, DIS starts from the previous
    frame's flow scaled to the new gap (constant velocity), and three frames out (42 px) far more pixels pass the
    forward-backward check than from zero; a small motion (under TRACK_INIT_MIN_FLOW) and the first frame after a
    keyframe start from zero."""
    big = S.texture("astronaut")
    step = 14.0  # px per frame (full resolution): 1.75 BA px, above TRACK_INIT_MIN_FLOW = 1
    confident = {}
    for vel in (True, False):
        # the predicted start (TRACK_PREDICT_INIT) off: this compares the velocity init with zero
        monkeypatch.setattr(track_starts, "TRACK_VELOCITY_INIT", vel)
        monkeypatch.setattr(track_starts, "TRACK_PREDICT_INIT", False)
        fe = FlowFrontend(FlowFrontendConfig(keyframes={"flow_thresh": 50.0, "min_coverage": 0.0}))
        fe.add_keyframe(0, S.frame(S.shifted(big, 0.0), 0), None)
        inits = []
        orig = fe.starts._velocity_init
        fe.starts._velocity_init = lambda *a: inits.append(orig(*a)[0] is not None) or orig(*a)
        for t in range(1, 4):
            r = fe.track(S.frame(S.shifted(big, step * t), t), None)
        assert inits == ([False, True, True] if vel else [False, False, False])
        u = r.target[0] - torch.arange(r.target.shape[-1], dtype=torch.float32)  # BA px; true: 3 * 14 / 8
        assert float((u[4:-4, 4:-4] - 3 * step / 8).abs().median()) < 0.05
        confident[vel] = float((r.weight[0] > 0.5).float().mean())
    assert confident[True] > confident[False] + 0.08, confident
    monkeypatch.undo()
    slow = FlowFrontend()
    slow.add_keyframe(0, S.frame(S.shifted(big, 0.0), 0), None)
    calls = []
    orig = slow.starts._velocity_init
    slow.starts._velocity_init = lambda *a: calls.append(orig(*a)[0] is not None) or orig(*a)
    for t in range(1, 3):
        slow.track(S.frame(S.shifted(big, 2.0 * t), t), None)  # 0.25 BA px a frame
    assert calls == [False, False]


def test_texture_term_lowers_flat_regions_once_per_source_image(monkeypatch):
    """With ``TEXTURE_TAU`` the flow confidence of a flat region drops (its flow is an aperture-problem guess) and the
    texture term of a keyframe's image is computed once, however many flows start from it."""
    import cv2

    from pvslam_plugins.frontends.flow import flow_ops

    rng = np.random.default_rng(0)
    img = np.full((S.H, S.W), 128, np.uint8)
    img[:, :S.W // 2] = cv2.GaussianBlur((rng.random((S.H, S.W // 2)) * 255).astype(np.uint8), (0, 0), 2.0)
    rgb = np.repeat(img[..., None], 3, -1)
    frames = [S.frame(np.roll(rgb, k, axis=1), k) for k in range(4)]
    calls = []
    real = flow_ops.texture_confidence
    monkeypatch.setattr(flow_ops, "texture_confidence", lambda *a, **k: calls.append(1) or real(*a, **k))
    weights = {}
    for tau in (0.0, 3e-4):
        monkeypatch.setattr(pair_flow, "TEXTURE_TAU", tau)
        fe = FlowFrontend(FlowFrontendConfig())
        fe.add_keyframe(0, frames[0], None)
        calls.clear()
        for f in frames[1:]:
            r = fe.track(f, None)
        weights[tau] = r.weight[0].numpy()
        assert len(calls) == (1 if tau > 0 else 0)  # three tracked frames, one source image
    tex, flat = (slice(2, -2), slice(2, 16)), (slice(2, -2), slice(24, 36))  # BA px (40 x 30 grid)
    assert weights[3e-4][flat].mean() < 0.1 * weights[0.0][flat].mean()
    assert weights[3e-4][tex].mean() > 0.5 * weights[0.0][tex].mean()
