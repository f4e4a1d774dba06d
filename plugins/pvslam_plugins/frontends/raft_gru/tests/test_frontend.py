"""The ``raft_gru`` frontend against independent references built from the network's own calls (DROID's
``MotionFilter`` and ``FactorGraph.update`` written out step by step here), on the golden fixture's network and
images (128 x 136 -> 16 x 17 at 1/8)."""
from __future__ import annotations

import copy

import pytest
import torch

from pvslam_core.geometry.ba import dense_ba
from pvslam_core.geometry.lie import se3_exp
from pvslam_core.geometry.projective import reproject
from pvslam_core.slam.graph import FrameGraph
from pvslam_core.types import EdgeObservations, Frame, Intrinsics, PanopticSegmentation, Segment
from pvslam_plugins.frontends.raft_gru import CorrVolume, RaftGruNet, coords_grid, frontend_state, upsample_disp
from pvslam_plugins.frontends.raft_gru.config import RaftGruConfig
from pvslam_plugins.frontends.raft_gru.frontend import DAMPING_INIT, RaftGruFrontend, RandomWeightsWarning
from pvslam_plugins.frontends.raft_gru.net import droid_motion
from pvslam_core.slam.confidence import panoptic_aware_weight

H, W, h, w = 128, 136, 16, 17
INTR = Intrinsics(110.0, 110.0, 67.5, 63.5, W, H)
INTR8 = INTR.scaled(1.0 / 8).vector()


@pytest.fixture
def net(droid_net) -> RaftGruNet:
    return copy.deepcopy(droid_net)


@pytest.fixture
def rgb(droid_golden) -> list[torch.Tensor]:
    return [f.contiguous() for f in droid_golden["images_uint8"][0, :, [2, 1, 0]]]  # three RGB uint8 [3, H, W]


def frame(img: torch.Tensor, k: int) -> Frame:
    return Frame(index=k, timestamp=0.1 * k, image=img, intrinsics=INTR)


def frontend(model, **kw) -> RaftGruFrontend:
    kw.setdefault("dynamic", {"enabled": False})
    return RaftGruFrontend(RaftGruConfig(weights="random", **kw), model=model)


def graph_of(n: int, seed: int = 0) -> FrameGraph:
    g = FrameGraph(h, w, INTR8, capacity=8)
    gen = torch.Generator().manual_seed(seed)
    for k in range(n):
        xi = torch.zeros(6, dtype=torch.float64)
        xi[0], xi[2] = 0.05 * k, 0.02 * k
        xi[3:] = 0.01 * torch.randn(3, generator=gen, dtype=torch.float64)
        g.add_keyframe(k, 0.1 * k, se3_exp(xi), 0.4 + 0.2 * torch.rand(h, w, generator=gen))
    return g


def features(model, rgb):
    with torch.no_grad():
        return model.features(torch.stack(rgb)[None], "rgb")


def test_motion_filter_is_droids(net, rgb):
    """track = fnet of the frame, correlation with the last keyframe at the identity, one update step from the
    keyframe's context with zero motion; keyframe iff mean |delta| > thresh; the keyframe set is not touched."""
    f = features(net, rgb)
    with torch.no_grad():
        corr = CorrVolume(f.fmap[:, [0]], f.fmap[:, [2]])(coords_grid(h, w).expand(1, 1, h, w, 2))
        ref = net.update(f.net[:, [0]], f.inp[:, [0]], corr)
    mean = float(ref.delta[0, 0].norm(dim=-1).mean())
    for thresh, want in ((0.5 * mean, True), (2.0 * mean, False)):
        fe = frontend(net, keyframe_thresh=thresh)
        assert fe.track(frame(rgb[0], 0), None).is_keyframe  # the first frame
        fe.add_keyframe(0, frame(rgb[0], 0), None)
        r = fe.track(frame(rgb[2], 1), None)
        assert r.is_keyframe is want and r.mean_flow == pytest.approx(mean, rel=1e-5)
        assert fe.num_keyframes == 1 and fe.edge_ids() == []  # track never changes the keyframe set
        torch.testing.assert_close(r.target, (coords_grid(h, w) + ref.delta[0, 0]).permute(2, 0, 1), atol=1e-5, rtol=0)
        torch.testing.assert_close(r.weight, ref.weight[0, 0].permute(2, 0, 1), atol=1e-5, rtol=0)


def test_keyframe_reuses_the_tracked_fmap(net, rgb, monkeypatch):
    fe = frontend(net)
    calls = []
    orig = net.features
    monkeypatch.setattr(net, "features", lambda *a, **k: calls.append(k.get("context", True)) or orig(*a, **k))
    fe.track(frame(rgb[0], 0), None)
    fe.add_keyframe(0, frame(rgb[0], 0), None)
    fe.track(frame(rgb[1], 1), None)
    fe.add_keyframe(1, frame(rgb[1], 1), None)
    assert calls == [False, False]  # fnet once per frame; context through net.context only
    with pytest.raises(ValueError, match="id 1 was added before"):
        fe.add_keyframe(1, frame(rgb[1], 1), None)


def test_observe_is_droids_factor_graph_update(net, rgb):
    """Two rounds of observe against DROID's update written out: new edges start at the reprojection with the
    source's net0; target = coords1 + delta; eta per unique source (others keep 1e-6); state carries over."""
    fe = frontend(net)
    for k in range(3):
        fe.add_keyframe(k, frame(rgb[k], k), None)
    g = graph_of(3)
    ii, jj = torch.tensor([1, 0, 1]), torch.tensor([2, 1, 0])
    f = features(net, rgb)
    coords0 = coords_grid(h, w)
    vol = CorrVolume.from_edges(f.fmap, ii, jj)
    state, target = f.net[:, ii], None
    for rnd in range(2):
        obs = fe.observe(g, ii, jj)
        with torch.no_grad():
            c1, _ = reproject(g.poses, g.disps, g.intrinsics, ii, jj)
            c1 = c1.float()[None]
            tgt = c1 if target is None else target
            out = net.update(state, f.inp[:, ii], vol(c1), droid_motion(coords0, c1, tgt), ii, jj)
        state, target = out.net, c1 + out.delta
        torch.testing.assert_close(obs.target, target[0].permute(0, 3, 1, 2), atol=1e-4, rtol=0)
        torch.testing.assert_close(obs.weight, out.weight[0].permute(0, 3, 1, 2), atol=1e-5, rtol=0)
        assert obs.depth_damping.shape == (3, h, w)
        torch.testing.assert_close(obs.depth_damping[:2], out.eta[0], atol=1e-8, rtol=1e-5)  # sources 0, 1
        assert bool((obs.depth_damping[2] == DAMPING_INIT).all())  # keyframe 2 is no source
        assert obs.dynamic.shape == (3, h, w)
        # the BA moves the estimate between rounds
        g.set_poses(torch.tensor([2]), se3_exp(torch.tensor([[0.12, 0.0, 0.05, 0.0, 0.01, 0.0]], dtype=torch.float64)))
    assert fe.edge_ids() == [(0, 1), (1, 0), (1, 2)]


def test_depth_damping_reaches_the_ba(net, rgb):
    """The optimizer's BA uses the learned eta (0.2 eta + 1e-7, DROID) instead of its configured constant."""
    fe = frontend(net)
    for k in range(3):
        fe.add_keyframe(k, frame(rgb[k], k), None)
    g = graph_of(3)
    obs = fe.observe(g, torch.tensor([0, 1, 2, 1]), torch.tensor([1, 2, 1, 0]))
    assert bool((obs.depth_damping[:3] != DAMPING_INIT).all())
    free = torch.tensor([False, True, True])
    runs = {}
    for name, o, damp in (("learned", obs, 123.0),  # the constant must be ignored when obs carries eta
                          ("explicit", EdgeObservations(obs.ii, obs.jj, obs.target, obs.weight),
                           0.2 * obs.depth_damping + 1e-7),
                          ("constant", EdgeObservations(obs.ii, obs.jj, obs.target, obs.weight), 1e-3)):
        gg = graph_of(3)
        dense_ba(gg, o, free, iters=2, depth_damping=damp)
        runs[name] = gg.disps.clone()
    torch.testing.assert_close(runs["learned"], runs["explicit"], atol=1e-6, rtol=0)
    assert (runs["learned"] - runs["constant"]).abs().max() > 1e-3  # the damping matters here


def test_state_dropped_on_retirement_and_removal(net, rgb):
    fe = frontend(net)
    for k in range(3):
        fe.add_keyframe(k, frame(rgb[k], k), None)
    g = graph_of(3)
    g.add_listener(fe)
    g.add_edges(torch.tensor([0, 1, 1, 2]), torch.tensor([1, 0, 2, 1]))
    fe.observe(g, g.ii, g.jj)
    assert fe.edge_ids() == [(0, 1), (1, 0), (1, 2), (2, 1)]
    g.retire_edges(torch.tensor([True, False, False, False]))
    assert fe.edge_ids() == [(1, 0), (1, 2), (2, 1)]
    old = fe._edges[(1, 2)]
    fe.observe(g, torch.tensor([1]), torch.tensor([2]))
    assert fe._edges[(1, 2)] is old and old.updates == 2
    fe.discard_pairs(torch.tensor([1]), torch.tensor([2]))  # still an edge of the graph, its state forgotten
    assert fe.edge_ids() == [(1, 0), (2, 1)]
    fe.observe(g, torch.tensor([1]), torch.tensor([2]))  # a fresh state, updated once
    assert fe._edges[(1, 2)] is not old and fe._edges[(1, 2)].updates == 1
    assert fe.edge_ids() == [(1, 0), (1, 2), (2, 1)]
    g.remove_keyframe(1)  # ids 0, 2 remain; every edge touched keyframe id 1
    assert fe.edge_ids() == [] and fe.num_keyframes == 2
    obs = fe.observe(g, torch.tensor([0]), torch.tensor([1]))  # a fresh edge 0 -> id 2 (index 1)
    assert fe.edge_ids() == [(0, 2)] and obs.target.shape == (1, 2, h, w)
    with pytest.raises(KeyError, match=r"never added"):
        gg = graph_of(4)
        fe.observe(gg, torch.tensor([3]), torch.tensor([0]))


def test_update_window_keeps_old_edges(net, rgb):
    """fast profile: edges away from the newest keyframes keep their last target and weight (no GRU update)."""
    fe = frontend(net, profile="fast", precision="fp32")
    assert fe.rounds == 2 and fe.update_window == 2
    for k in range(3):
        fe.add_keyframe(k, frame(rgb[k], k), None)
    g = graph_of(3)
    fe.update_window = 1  # only edges touching the newest keyframe (index 2)
    ii, jj = torch.tensor([0, 1, 2]), torch.tensor([1, 0, 1])
    a = fe.observe(g, ii, jj)
    b = fe.observe(g, ii, jj)
    assert torch.equal(a.target[:2], b.target[:2]) and torch.equal(a.weight[:2], b.weight[:2])
    assert not torch.equal(a.target[2], b.target[2])  # edge 2 -> 1 was updated again
    assert [fe._edges[k].updates for k in [(0, 1), (1, 0), (2, 1)]] == [1, 1, 2]


def test_pvo_mask_accumulates_and_eq4_convention(pvo_full_state_dict, rgb):
    """PVO: raw static logits accumulate delta_m (eq. 6); eq. 4 with the paper convention gives dynamic pixels the
    raw logit and static ones +10, pvo_code the reverse; delta_dy survives on dynamic pixels only."""
    model = RaftGruNet("pvo")
    model.load_state_dict(pvo_full_state_dict)
    g = graph_of(2)
    ii, jj = torch.tensor([0]), torch.tensor([1])
    fes = {c: RaftGruFrontend(RaftGruConfig(weights="random", dynamic={"convention": c, "things_only": False}),
                              model=copy.deepcopy(model)) for c in ("paper", "pvo_code")}
    for fe in fes.values():
        for k in range(2):
            fe.add_keyframe(k, frame(rgb[k], k), None)
    outs = {c: [fe.observe(g, ii, jj) for _ in range(2)] for c, fe in fes.items()}
    f = features(model, rgb[:2])
    coords0 = coords_grid(h, w)
    with torch.no_grad():
        c1 = reproject(g.poses, g.disps, g.intrinsics, ii, jj)[0].float()[None]
        corr = CorrVolume.from_edges(f.fmap, ii, jj)(c1)
        z = torch.zeros(1, 1, h, w, 2)
        from pvslam_plugins.frontends.raft_gru.net import pvo_motion

        o1 = model.update(f.net[:, ii], f.inp[:, ii], corr, pvo_motion(c1 - coords0, z, z, z), ii, jj)
        raw1 = o1.delta_m
        dyn1 = (torch.sigmoid(raw1) < 0.5).float()
        t1 = c1 + o1.delta
        o2 = model.update(o1.net, f.inp[:, ii], corr, pvo_motion(t1 - coords0, o1.delta_dy * dyn1, t1 - c1, raw1),
                          ii, jj)
        raw2 = raw1 + o2.delta_m
    dyn2 = (torch.sigmoid(raw2) < 0.5).float()
    assert 0 < float(dyn2.mean()) < 1  # both kinds of pixels present, so the test can tell the conventions apart
    want = {"paper": panoptic_aware_weight(o2.weight, dyn2, 10.0, "paper"),
            "pvo_code": torch.sigmoid(o2.weight + dyn2 * 10.0)}  # PVO's code: sigmoid(w + (1 - static) * 10)
    for c in ("paper", "pvo_code"):
        torch.testing.assert_close(outs[c][1].weight, want[c][0].permute(0, 3, 1, 2), atol=1e-5, rtol=0)
        torch.testing.assert_close(outs[c][1].target, (c1 + o2.delta)[0].permute(0, 3, 1, 2), atol=1e-4, rtol=0)
        e = fes[c]._edges[(0, 1)]
        torch.testing.assert_close(e.raw_mask, raw2[0, 0], atol=1e-5, rtol=0)
        torch.testing.assert_close(e.delta_dy, (o2.delta_dy * dyn2)[0, 0], atol=1e-5, rtol=0)
    paper, code = outs["paper"][1].weight, outs["pvo_code"][1].weight
    d = dyn2[0, 0].permute(2, 0, 1).bool()
    assert bool((paper[0][~d] > code[0][~d]).all()) and bool((paper[0][d] < code[0][d]).all())


def test_segment_vote_spreads_the_mask(pvo_full_state_dict, rgb):
    model = RaftGruNet("pvo")
    model.load_state_dict(pvo_full_state_dict)
    fe = RaftGruFrontend(RaftGruConfig(weights="random", dynamic={"vote_thresh": 0.0}), model=model)
    ids = torch.full((H, W), 3000, dtype=torch.int64)
    ids[:, :64] = 11001  # a car on the left
    seg = PanopticSegmentation(ids, [Segment(3000, 3, False), Segment(11001, 11, True)])
    for k in range(2):
        fe.add_keyframe(k, frame(rgb[k], k), seg)
    obs = fe.observe(graph_of(2), torch.tensor([0]), torch.tensor([1]))
    car = torch.zeros(h, w, dtype=torch.bool)
    car[:, :8] = True
    assert bool((obs.dynamic[0][car] == 1).all())  # any dynamic pixel in the car (vote 0.0) marks all of it
    static = (torch.sigmoid(fe._edges[(0, 1)].raw_mask) >= 0.5).all(-1)
    assert bool(static[~car].any()) and float(obs.dynamic[0][~car & static].max()) <= 0.5  # buildings never vote


def test_eviction_recompute_and_upsampled_disp(net, rgb):
    fe = frontend(net, feature_cache=4)
    for k in range(6):
        fe.add_keyframe(k, frame(rgb[k % 3], k), None)
    g = graph_of(6)
    assert fe._kfs[0].fmap is None and fe._kfs[5].fmap is not None  # LRU of 4
    obs = fe.observe(g, torch.tensor([0, 3]), torch.tensor([1, 0]))  # needs keyframes 0, 1 again
    assert fe.stats.counts["recomputed"] == 2
    ref = frontend(net)  # ids 0, 1, 2 hold the images of keyframes 0, 1, 3
    for i, k in enumerate((0, 1, 3)):
        ref.add_keyframe(i, frame(rgb[k % 3], k), None)
    g3 = FrameGraph(h, w, INTR8, capacity=4)
    for k in (0, 1, 3):
        g3.add_keyframe(k, 0.1 * k, g.poses[k], g.disps[k])
    torch.testing.assert_close(obs.target, ref.observe(g3, torch.tensor([0, 2]), torch.tensor([1, 0])).target,
                               atol=1e-5, rtol=0)
    # upsampling: convex with the learned mask while it is in memory ...
    up = fe.upsampled_disp(g, 3)
    want = upsample_disp(g.disps[3][None, None], fe._upmask(fe._kfs[3])[None, None])[0, 0]
    assert up.shape == (H, W) and torch.allclose(up, want)
    # ... and after eviction the saved upsampling follows later changes of the low-resolution depth
    for k in range(6, 11):
        fe.add_keyframe(k, frame(rgb[0], k), None)
    assert fe._kfs[3].upmask is None and fe._kfs[3].disp_up is not None
    torch.testing.assert_close(fe.upsampled_disp(g, 3), want, atol=2e-3 * float(want.max()), rtol=0)  # fp16 copy
    g.set_disps(torch.tensor([3]), 2.0 * g.disps[3][None])
    torch.testing.assert_close(fe.upsampled_disp(g, 3), 2.0 * want, atol=4e-3 * float(want.max()), rtol=0)


def test_configuration_errors_and_warnings(net, rgb):
    with pytest.warns(RandomWeightsWarning, match="RANDOMLY INITIALISED"):
        RaftGruFrontend(RaftGruConfig(weights="random"))
    with pytest.raises(ValueError, match="ba_downsample = 8"):
        RaftGruFrontend(RaftGruConfig(weights="random"), model=net, ba_downsample=4)
    with pytest.raises(ValueError, match=r"variant='pvo' but the network is 'droid'"):
        RaftGruFrontend(RaftGruConfig(weights="random", variant="pvo"), model=net)
    fe = frontend(net)
    with pytest.raises(ValueError, match="not a multiple of 8"):
        fe.track(frame(torch.randint(0, 255, (3, 130, 136), dtype=torch.uint8), 0), None)
    r = fe.track(frame(torch.zeros(3, H, W, dtype=torch.uint8), 0), None)
    assert r.failed and "no texture" in r.message
    fe.add_keyframe(0, frame(rgb[0], 0), None)
    with pytest.raises(ValueError, match="BA resolution is 30x40"):
        g = FrameGraph(30, 40, INTR8)
        g.add_keyframe(0, 0.0, torch.tensor([0, 0, 0, 0, 0, 0, 1.0]), torch.ones(30, 40))
        g.add_keyframe(1, 0.1, torch.tensor([0, 0, 0, 0, 0, 0, 1.0]), torch.ones(30, 40))
        fe.add_keyframe(1, frame(rgb[1], 1), None)
        fe.observe(g, torch.tensor([0]), torch.tensor([1]))
    cfg = RaftGruConfig(weights="random")
    assert (cfg.resolved("rounds"), cfg.resolved("precision")) == (6, "fp32")
    fast = RaftGruConfig(weights="random", profile="fast", rounds=3)
    assert (fast.resolved("rounds"), fast.resolved("precision"), fast.resolved("update_window")) == (3, "bf16", 2)
    with pytest.raises(Exception, match="extra"):
        RaftGruConfig(weights="random", roundz=3)


def test_config_dynamic_table_and_old_keys():
    """``frontend.dynamic`` is the shared dynamic-masking model (raft_gru's defaults and mask-head keys on top); the
    flat keys of earlier releases land in it, and a retired key loads only at its fixed value."""
    from pvslam_core.slam.dynamic_config import DynamicMaskingConfig
    from pvslam_plugins.frontends.raft_gru import frontend as frontend_module

    d = RaftGruConfig(weights="random").dynamic
    assert isinstance(d, DynamicMaskingConfig)
    assert (d.enabled, d.panoptic_offset, d.convention, d.thresh, d.max_fraction, d.vote_thresh, d.mask_thresh,
            d.things_only) == (True, 10.0, "paper", 1.0, 0.5, None, 0.5, True)
    old = RaftGruConfig.model_validate({
        "weights": "random", "dynamic_masking": False, "panoptic_offset": 7.0, "convention": "pvo_code",
        "dynamic_thresh": 2.0, "max_dynamic_fraction": 0.7, "vote_thresh": 0.3, "mask_thresh": 0.6,
        "things_only": False, "dynamic_rel_thresh": 3.0, "min_texture_std": 2.0})
    assert old.dynamic.model_dump() == {"enabled": False, "panoptic_offset": 7.0, "convention": "pvo_code",
                                        "thresh": 2.0, "max_fraction": 0.7, "vote_thresh": 0.3, "mask_thresh": 0.6,
                                        "things_only": False}
    assert RaftGruConfig.retired == {"dynamic_rel_thresh": frontend_module.DYNAMIC_REL_THRESH,
                                     "min_texture_std": frontend_module.MIN_TEXTURE_STD}
    for key, other in (("dynamic_rel_thresh", 1.0), ("min_texture_std", 5.0)):
        with pytest.raises(ValueError, match=f"'{key}' was retired"):
            RaftGruConfig(weights="random", **{key: other})


def test_bf16_runs_only_where_the_cpu_computes_it_natively(net, monkeypatch, caplog):
    """The fast profile's bf16 falls back to fp32 on a CPU without native bf16 (there torch's reference loops make a
    bf16 convolution tens of times slower than fp32), with a warning; fp32 configs and native CPUs are unchanged."""
    assert isinstance(frontend_state.cpu_bf16_native(), bool)  # the real query answers on this machine
    monkeypatch.setattr(frontend_state, "cpu_bf16_native", lambda: False)
    with caplog.at_level("WARNING", logger="pvslam.frontend.raft_gru"):
        assert frontend(net, profile="fast").precision == "fp32"
    assert "no native bf16" in caplog.text
    assert frontend(net, profile="droid").precision == "fp32"
    monkeypatch.setattr(frontend_state, "cpu_bf16_native", lambda: True)
    assert frontend(net, profile="fast").precision == "bf16"
    assert frontend_state.effective_precision("bf16", torch.device("cuda")) == "bf16"  # autocast on CUDA: its own


def test_corr_impls_agree_and_bf16_is_close(net, rgb, monkeypatch):
    """The memory-light on-the-fly lookup gives the stored volume's numbers; bf16 autocast stays near fp32 (bf16
    forced on CPUs without native bf16, so that its arithmetic is tested everywhere)."""
    monkeypatch.setattr(frontend_state, "cpu_bf16_native", lambda: True)
    ii, jj = torch.tensor([0, 1, 2, 1]), torch.tensor([1, 2, 0, 0])
    out = {}
    for name, kw in (("volume", {"corr_impl": "volume"}), ("onthefly", {"corr_impl": "onthefly"}),
                     ("bf16", {"corr_impl": "volume", "precision": "bf16"})):
        fe = frontend(net, **kw)
        for k in range(3):
            fe.add_keyframe(k, frame(rgb[k], k), None)
        out[name] = fe.observe(graph_of(3), ii, jj)
    torch.testing.assert_close(out["onthefly"].target, out["volume"].target, atol=1e-4, rtol=0)
    torch.testing.assert_close(out["onthefly"].weight, out["volume"].weight, atol=1e-5, rtol=0)
    err = (out["bf16"].target - out["volume"].target).abs()
    assert float(err.max()) < 0.5 and float(err.mean()) < 0.05  # |delta| spans ~[-3, 2] here
    assert float((out["bf16"].weight - out["volume"].weight).abs().max()) < 0.05
