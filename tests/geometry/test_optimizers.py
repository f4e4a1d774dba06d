import math

import pytest
import torch

from pvslam_core.geometry.lie import se3_exp, se3_inv, se3_mul, se3_to_matrix, sim3_from_se3
from pvslam_core.geometry.pose_graph import loop_relative_sim3, odometry_measurements, sim3_pose_graph
from pvslam_core.geometry.testing import circle_poses, drifted_loop, make_problem, perturb, scale_drifted, umeyama_ate
from pvslam_core.interfaces import BuildContext, Optimizer
from pvslam_core.registry import get_registry
from pvslam_core.types import DepthPrior, DistancePrior, EdgeObservations, LoopClosure


def _loop(i, j, score=0.9):
    """A closure between graph keyframes i and j (the test graphs' ids equal their indices)."""
    return LoopClosure(frame_i=i, frame_j=j, kf_i=i, kf_j=j, score=score, verified=True)


def make(name, **cfg):
    spec = get_registry().get("optimizer", name)
    return spec.factory(spec.config_model(**cfg), BuildContext(device=torch.device("cpu")))


@pytest.fixture(scope="module")
def loop_problem():
    return make_problem(n=16, trajectory="loop", loop_edges=True, radius=2, seed=1)


def test_registered_with_described_configs():
    reg = get_registry()
    for name in ("online_ba", "offline_ba"):
        spec = reg.get("optimizer", name)
        fields = spec.config_model.model_fields
        for f in ("window", "iters", "robust", "robust_scale", "loop", "final"):
            assert f in fields and fields[f].description, (name, f)
        for sub in ("loop", "final"):
            for f, field in fields[sub].annotation.model_fields.items():
                assert field.description, (name, sub, f)
        assert isinstance(make(name), Optimizer)
        with pytest.raises(Exception):
            spec.config_model(windw=3)


@pytest.mark.parametrize("name", ["online_ba", "offline_ba"])
def test_step_windowed(name):
    pr = make_problem(n=10, seed=4)
    p0, d0 = perturb(pr, fixed=(0,), rot=0.01, trans=0.02, disp_rel=0.1)
    g = pr.graph(p0, d0)
    opt = make(name, window=4, iters=3)
    rep = opt.step(g, pr.obs())
    assert not rep.rejected and rep.cost_after < rep.cost_before
    assert rep.num_free_poses == 4
    assert torch.equal(g.poses[:6], p0[:6])  # outside the window: fixed
    for _ in range(5):
        opt.step(g, pr.obs())
    err = se3_mul(se3_inv(pr.poses[6:]), g.poses[6:])[:, :3].norm(dim=-1)
    assert float(err.max()) < float(se3_mul(se3_inv(pr.poses[6:]), p0[6:])[:, :3].norm(dim=-1).max())


@pytest.mark.parametrize("name", ["online_ba", "offline_ba"])
def test_loop_and_finalize_fix_scale_drift(name, loop_problem):
    pr = loop_problem
    n = pr.poses.shape[0]
    p0, d0 = scale_drifted(pr, rate=0.96, yaw_drift=0.01)
    g = pr.graph(p0, d0)
    ate0 = umeyama_ate(g.poses[:, :3], pr.poses[:, :3])
    assert ate0 > 0.05
    opt = make(name)
    sel = (pr.ii >= n - 6) | (pr.jj >= n - 6) | ((pr.ii == 0) & (pr.jj == n - 1))
    obs = EdgeObservations(pr.ii[sel], pr.jj[sel], pr.target[sel], pr.weight[sel])
    rep = opt.loop(g, obs, [_loop(n - 1, 0)])
    assert not rep.rejected and "sim3 pgo" in rep.message and opt.last_pgo["applied"]
    ate1 = umeyama_ate(g.poses[:, :3], pr.poses[:, :3])
    assert ate1 < 0.1 * ate0, (ate0, ate1)
    rep = opt.finalize(g, lambda ii, jj: pr.obs(ii, jj))
    assert not rep.rejected and rep.cost_after <= rep.cost_before
    ate2 = umeyama_ate(g.poses[:, :3], pr.poses[:, :3])
    assert ate2 < 0.01 * ate0, (ate0, ate2)


@pytest.mark.parametrize("name", ["online_ba", "offline_ba"])
def test_old_config_keys_still_load(name, caplog):
    """Files written for earlier releases keep working: the flat keys move into the nested tables (with a warning
    naming the new keys; the schedule's other defaults stay), retired keys load at their fixed value and fail naming
    the key at any other (eta was depth_damping's name before it), pgo_min_gap is ignored (the loop policy's
    loop_closure.ba_min_gap gates loop BAs and with them the pose graph)."""
    from pydantic import ValidationError

    spec = get_registry().get("optimizer", name)
    default = spec.config_model()
    cfg = spec.config_model.model_validate({"loop_iters": 2, "sim3_pgo": False, "final_iters": 3, "pgo_min_gap": 3})
    assert cfg.loop.iters == 2 and cfg.loop.sim3_pgo is False and cfg.final.iters == 3
    assert cfg.final.rounds == default.final.rounds and cfg.window == default.window and cfg.iters == default.iters
    assert spec.config_model.model_validate({"final_rounds": 5}).final.rounds == 5
    assert "loop_iters -> loop.iters" in caplog.text and "final_iters -> final.iters" in caplog.text
    assert "pgo_min_gap" in caplog.text and "pgo_min_gap" not in cfg.model_dump()
    # an old run directory's config.json stores every key at its value of the time
    old = {"window": default.window, "iters": default.iters, "iters_max": None, "iters_tol": 0.01, "lm": 1e-4,
           "ep": 0.1, "depth_damping": 1e-5, "depth_damping_shrink": False, "depth_damping_horizon": 50,
           "min_depth": 0.2, "robust": "cauchy", "robust_scale": 1.0, "loop_window": 0, "loop_iters": 4,
           "loop_lm": 1e-5, "loop_ep": 0.01, "sim3_pgo": True, "sim3_pgo_with_depth_prior": False, "pgo_iters": 25,
           "pgo_min_drift": 0.02, "pgo_loop_weight": 10.0, "pgo_max_direction_deg": 15.0,
           "pgo_max_scale_disagreement": 1.25, "pgo_min_pixels": 30, "final_iters": default.final.iters,
           "final_rounds": default.final.rounds, "final_lm": 1e-5, "final_ep": 0.01}
    assert spec.config_model.model_validate(old) == default
    assert spec.config_model.model_validate({"eta": 1e-5}) == default
    for key, value in (("eta", 1e-4), ("depth_damping", 1e-3), ("iters_max", 5), ("sim3_pgo_with_depth_prior", True),
                       ("depth_damping_shrink", True), ("pgo_max_direction_deg", None), ("loop_lm", 1e-4)):
        with pytest.raises(ValidationError, match=f"'{key}' was retired"):
            spec.config_model.model_validate({key: value})


def test_retired_keys_hold_the_constants_the_code_uses():
    """Each retired key's fixed value is the constant the optimizer now uses (a file that gives it gets that run)."""
    from pvslam_plugins.optimizers.dense_ba import optimizer as O
    from pvslam_plugins.optimizers.dense_ba.config import BAConfigBase

    r = BAConfigBase.retired
    assert (r["lm"], r["ep"], r["loop_lm"], r["loop_ep"], r["final_lm"], r["final_ep"]) == \
        (O.WINDOW_LM, O.WINDOW_EP, O.GLOBAL_LM, O.GLOBAL_EP, O.GLOBAL_LM, O.GLOBAL_EP)
    assert r["depth_damping"] == r["eta"] == O.DEPTH_DAMPING and r["min_depth"] == O.MIN_DEPTH
    assert (r["pgo_iters"], r["pgo_min_drift"], r["pgo_loop_weight"], r["pgo_max_direction_deg"],
            r["pgo_max_scale_disagreement"], r["pgo_min_pixels"]) == \
        (O.PGO_ITERS, O.PGO_MIN_DRIFT, O.PGO_LOOP_WEIGHT, O.PGO_MAX_DIRECTION_DEG, O.PGO_MAX_SCALE_DISAGREEMENT,
         O.PGO_MIN_PIXELS)
    opt = make("online_ba")
    for kind, (lm, ep) in (("window", (O.WINDOW_LM, O.WINDOW_EP)), ("loop", (O.GLOBAL_LM, O.GLOBAL_EP)),
                           ("final", (O.GLOBAL_LM, O.GLOBAL_EP))):
        o = opt.options(kind)
        assert (o.lm, o.ep, o.depth_damping, o.min_depth, o.robust, o.robust_scale) == \
            (lm, ep, O.DEPTH_DAMPING, O.MIN_DEPTH, "cauchy", 1.0)
    assert (opt.options("window").iters, opt.options("loop").iters, opt.options("final").iters) == (3, 4, 4)


def test_pose_graph_only_for_real_drift(loop_problem):
    """A loop whose measurement agrees with the estimate leaves the pose graph out; a drifted one runs it."""
    pr = loop_problem
    n = pr.poses.shape[0]
    g = pr.graph()  # exact poses and depths: no drift
    opt = make("online_ba")
    rep = opt.loop(g, pr.obs(), [_loop(n - 1, 0)])
    assert "sim3 pgo skipped (drift" in rep.message and opt.last_pgo["drift"] < 1e-3
    g = pr.graph(*scale_drifted(pr, rate=0.96, yaw_drift=0.01))
    rep = make("online_ba").loop(g, pr.obs(), [_loop(n - 1, 0)])
    assert "sim3 pgo:" in rep.message


def test_loop_without_pgo_runs(loop_problem):
    pr = loop_problem
    g = pr.graph(*perturb(pr, fixed=(0,), rot=0.005, trans=0.01, disp_rel=0.05))
    opt = make("online_ba", loop={"sim3_pgo": False, "iters": 4})
    rep = opt.loop(g, pr.obs(), [_loop(15, 0)])
    assert not rep.rejected and rep.cost_after < rep.cost_before and "sim3" not in rep.message


def test_no_sim3_pose_graph_where_a_depth_prior_observes_the_scale(loop_problem, monkeypatch):
    """A loop whose observations carry a depth prior (the scale is observed) gets the loop BA without the Sim(3)
    pose graph, which would rescale the chain against the prior."""
    import pvslam_plugins.optimizers.dense_ba.optimizer as O

    pr = loop_problem
    n = pr.poses.shape[0]
    calls = []
    orig = O.DenseBAOptimizer.sim3_correction
    monkeypatch.setattr(O.DenseBAOptimizer, "sim3_correction",
                        lambda self, *a: calls.append(1) or orig(self, *a))
    o = pr.obs()
    ids = torch.arange(n)
    prior = EdgeObservations(o.ii, o.jj, o.target, o.weight,
                             disp_prior=DepthPrior(ids, pr.disps.clone(), torch.full_like(pr.disps, 0.05)))
    drifted = scale_drifted(pr, rate=0.96, yaw_drift=0.01)
    g = pr.graph(*drifted)
    rep = make("online_ba").loop(g, prior, [_loop(n - 1, 0)])
    assert not calls and "skipped (the observations carry a depth or distance prior" in rep.message \
        and not rep.rejected
    assert not torch.equal(g.poses, drifted[0])  # the loop BA ran
    # a distance prior (geometry/ba_distance.py) observes the scale as well
    one = torch.ones(1, dtype=torch.float64)
    span = (pr.poses[0, :3] - pr.poses[1, :3]).norm() * one
    dist = EdgeObservations(o.ii, o.jj, o.target, o.weight,
                            dist_prior=DistancePrior(torch.tensor([0]), torch.tensor([1]), span, one))
    rep = make("online_ba").loop(pr.graph(*drifted), dist, [_loop(n - 1, 0)])
    assert not calls and "skipped" in rep.message and not rep.rejected
    make("online_ba").loop(pr.graph(*drifted), pr.obs(), [_loop(n - 1, 0)])
    assert len(calls) == 1


def test_online_finalize_zero_iters(loop_problem):
    g = loop_problem.graph()
    rep = make("online_ba", final={"iters": 0}).finalize(g, lambda ii, jj: loop_problem.obs(ii, jj))
    assert rep.iterations == 0


def test_sim3_pose_graph_scale_drifted_loop():
    lp = drifted_loop(24, radius=3, rate=0.97, yaw_drift=0.01)
    gt, est, c, S = lp.gt, lp.est, lp.drift, lp.S
    res = sim3_pose_graph(*lp.args(), iters=30)
    assert res.cost_after < 1e-2 * res.cost_before
    before = float((est[:, :3] - gt[:, :3]).norm(dim=-1).max())
    after = float((res.poses[:, :3] - gt[:, :3]).norm(dim=-1).max())
    assert before > 1.0 and after < 0.03, (before, after)
    # recovered per-keyframe scale ~ 1 / drift
    assert torch.allclose(res.poses[:, 7], 1 / c, rtol=0.05)
    assert torch.equal(res.poses[0], S[0])


def test_loop_relative_sim3_measures_scale(loop_problem):
    pr = loop_problem
    n = pr.poses.shape[0]
    e = int(torch.nonzero((pr.ii == 0) & (pr.jj == n - 1))[0])
    s_true = 0.8  # keyframe n-1's map is 0.8x the true size
    start = se3_mul(pr.poses[n - 1], se3_exp(torch.tensor([0.05, 0.02, -0.03, 0.01, 0.02, 0.0], dtype=torch.float64)))
    Z, s, used = loop_relative_sim3(pr.poses[0], pr.disps[0], start, pr.disps[n - 1] / s_true, pr.intr,
                                    pr.target[e], pr.weight[e])
    assert used > 100
    assert abs(s - 1 / s_true) < 1e-3
    T_true = se3_mul(se3_inv(pr.poses[0]), pr.poses[n - 1])  # camera n-1 -> camera 0, keyframe 0's (true) scale
    assert torch.allclose(se3_to_matrix(Z[:7]), se3_to_matrix(T_true), atol=1e-5)
    assert abs(float(Z[7]) - s) < 1e-12


def test_sim3_pose_graph_sparse_matches_dense():
    gt = circle_poses(30, radius=3)
    N = gt.shape[0]
    est = se3_mul(gt, se3_exp(0.02 * torch.randn(N, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)))
    est[0] = gt[0]
    S = sim3_from_se3(est, 1.0)
    ii, jj, Z = odometry_measurements(sim3_from_se3(gt, 1.0))
    ii, jj = torch.cat([ii, torch.tensor([N - 1])]), torch.cat([jj, torch.tensor([0])])
    Z = torch.cat([Z, sim3_from_se3(se3_mul(se3_inv(gt[N - 1]), gt[0]), 1.0)[None]])
    fixed = torch.zeros(N, dtype=torch.bool)
    fixed[0] = True
    dense = sim3_pose_graph(S, ii, jj, Z, fixed, iters=10, sparse_min_nodes=10_000)
    sparse = sim3_pose_graph(S, ii, jj, Z, fixed, iters=10, sparse_min_nodes=4)
    assert sparse.cost_after < 1e-6 * sparse.cost_before
    assert torch.allclose(dense.poses[:, :3], sparse.poses[:, :3], atol=1e-6)
    assert float((sparse.poses[:, :3] - gt[:, :3]).norm(dim=-1).max()) < 1e-4


def test_pose_graph_spans_the_loop_only():
    """The first loop BA's Sim(3) pose graph runs over keyframes j..n-1 with j fixed (a 3000-frame run spent most of its
    later laps in pose graphs over every keyframe): keyframes before j keep their poses and depths bit for bit, and
    the corrected poses equal those of the same pose graph over all keyframes with keyframe 0 fixed (the keyframes
    before j hang off the chain without a cycle, so the full problem has the same optimum)."""
    from pvslam_plugins.optimizers.dense_ba import optimizer as O

    n, j = 16, 4
    base = make_problem(n=n, trajectory="loop", radius=2, seed=1)
    ii = torch.cat([base.ii, torch.tensor([j, n - 1])])
    jj = torch.cat([base.jj, torch.tensor([n - 1, j])])
    pr = make_problem(n=n, trajectory="loop", radius=2, seed=1, edges=(ii, jj))
    p0, d0 = scale_drifted(pr, rate=0.96, yaw_drift=0.01)
    g = pr.graph(p0.clone(), d0.clone())
    opt = make("online_ba", loop={"iters": 0})  # the pose graph alone
    rep = opt.loop(g, pr.obs(), [_loop(n - 1, j)])
    assert f"over keyframes {j}..{n - 1}" in rep.message and opt.last_pgo["applied"], rep.message
    assert float((g.poses[:j + 1] - p0[:j + 1]).abs().max()) < 1e-12 and torch.equal(g.disps[:j], d0[:j])

    # reference: the whole chain, keyframe 0 fixed, the same loop measurement (old keyframe j as the reference)
    e = int(torch.nonzero((pr.ii == j) & (pr.jj == n - 1))[0])
    Zl, _, _ = loop_relative_sim3(p0[j], d0[j], p0[n - 1], d0[n - 1], pr.intr, pr.target[e], pr.weight[e])
    S = sim3_from_se3(p0, 1.0)
    oi, oj, Z = odometry_measurements(S)
    w = torch.ones(len(oi) + 1, dtype=torch.float64)
    w[-1] = O.PGO_LOOP_WEIGHT
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[0] = True
    ref = sim3_pose_graph(S, torch.cat([oi, torch.tensor([j])]), torch.cat([oj, torch.tensor([n - 1])]),
                          torch.cat([Z, Zl[None]]), fixed, w, iters=O.PGO_ITERS)
    assert float((ref.poses[:j + 1, :3] - p0[:j + 1, :3]).norm(dim=-1).max()) < 1e-6  # untouched there too
    assert float((g.poses[:, :3] - ref.poses[:, :3]).norm(dim=-1).max()) < 1e-5
    assert umeyama_ate(g.poses[:, :3], pr.poses[:, :3]) < 0.5 * umeyama_ate(p0[:, :3], pr.poses[:, :3])


def test_pose_graph_corrects_only_since_the_previous_loop():
    """A second closure's pose graph bends only the chain since the newest keyframe of the previous loop BA (those
    before were corrected by it); the old keyframe of the loop and that keyframe stay fixed."""
    n = 16
    base = make_problem(n=n, trajectory="loop", radius=2, seed=1)
    extra = torch.tensor([[2, 11], [11, 2], [4, 15], [15, 4]])
    pr = make_problem(n=n, trajectory="loop", radius=2, seed=1,
                      edges=(torch.cat([base.ii, extra[:, 0]]), torch.cat([base.jj, extra[:, 1]])))
    g = pr.graph(*scale_drifted(pr, rate=0.96, yaw_drift=0.01))
    opt = make("online_ba", loop={"iters": 0})
    rep = opt.loop(g, pr.obs(), [_loop(11, 2)])
    assert "over keyframes 2..15" in rep.message and opt.last_pgo["applied"], rep.message
    p1 = g.poses.clone()
    rep = opt.loop(g, pr.obs(), [_loop(15, 4)])
    assert "over keyframes 11..15" in rep.message, rep.message
    assert float((g.poses[:12] - p1[:12]).abs().max()) < 1e-12  # up to the previous loop's newest keyframe: untouched
    assert float((g.poses[12:] - p1[12:]).abs().max()) > 1e-3
    # a loop whose old side is newer than the previous correction starts the chain at its old keyframe
    rep = make("online_ba", loop={"iters": 0}).loop(g, pr.obs(), [_loop(15, 4)])
    assert "over keyframes 4..15" in rep.message or "skipped" in rep.message, rep.message


def _rotated_translation(Z, deg):
    """``Z`` with its translation turned by ``deg`` about the camera's y axis (the measurement's pose is off)."""
    c, s = torch.cos(torch.deg2rad(torch.tensor(float(deg), dtype=torch.float64))), torch.sin(
        torch.deg2rad(torch.tensor(float(deg), dtype=torch.float64)))
    R = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    out = Z.clone()
    out[:3] = R @ Z[:3].double()
    return out


def test_loop_measurement_checked_against_the_epipolar_direction(loop_problem, monkeypatch):
    """A loop measurement whose translation disagrees with the loop edge's own essential matrix stays out of the
    pose graph; the true one agrees to a fraction of a degree."""
    from pvslam_plugins.optimizers.dense_ba import optimizer as O

    pr = loop_problem
    n = pr.poses.shape[0]
    e = int(torch.nonzero((pr.ii == 0) & (pr.jj == n - 1))[0])
    T_true = se3_mul(se3_inv(pr.poses[0]), pr.poses[n - 1])  # camera n-1 -> camera 0
    Z = sim3_from_se3(T_true, torch.tensor(1.0, dtype=torch.float64))
    off = O.DenseBAOptimizer._direction_error(Z, pr.target[e], pr.weight[e], pr.intr)
    assert off is not None and off < 0.5, off
    off30 = O.DenseBAOptimizer._direction_error(_rotated_translation(Z, 30.0), pr.target[e], pr.weight[e], pr.intr)
    assert abs(off30 - 30.0) < 1.0, off30
    # a drifted map whose loop measurement comes out 30 deg off: no pose graph (with the check off: the pose graph)
    measure = O.loop_relative_sim3
    monkeypatch.setattr(O, "loop_relative_sim3",
                        lambda *a, **k: (lambda Zs, s, u: (_rotated_translation(Zs, 30.0), s, u))(*measure(*a, **k)))
    drifted = scale_drifted(pr, rate=0.96, yaw_drift=0.01)
    rep = make("online_ba").loop(pr.graph(*drifted), pr.obs(), [_loop(n - 1, 0)])
    assert "sim3 pgo skipped (1 left out by the direction / scale checks)" in rep.message, rep.message
    monkeypatch.setattr(O, "PGO_MAX_DIRECTION_DEG", 90.0)  # the check off: no direction is further off
    rep = make("online_ba").loop(pr.graph(*drifted), pr.obs(), [_loop(n - 1, 0)])
    assert "sim3 pgo:" in rep.message, rep.message


def test_loop_scale_measured_from_both_ends_must_agree(loop_problem, monkeypatch):
    """The loop's scale is measured from each end (the old keyframe's depth against the new one's, and the reverse):
    on a drifted map the two ratios multiply to ~1 and the pose graph runs; when one end's ratio is wrong (a loop seen
    on few pixels) the loop stays out of the pose graph, and with the check off the pose graph takes it."""
    from pvslam_plugins.optimizers.dense_ba import optimizer as O

    pr = loop_problem
    n = pr.poses.shape[0]
    drifted = scale_drifted(pr, rate=0.96, yaw_drift=0.01)
    seen = []
    measure = O.loop_relative_sim3

    def spy(*a, **k):
        out = measure(*a, **k)
        seen.append(out[1])
        return out

    monkeypatch.setattr(O, "loop_relative_sim3", spy)
    rep = make("online_ba").loop(pr.graph(*drifted), pr.obs(), [_loop(n - 1, 0)])
    assert "sim3 pgo:" in rep.message and len(seen) == 2, (rep.message, seen)
    assert abs(seen[0] * seen[1] - 1.0) < 0.05 and abs(seen[0] - 1.0) > 0.1, seen  # drifted, and consistent

    def wrong_from_the_old_end(pose_a, disp_a, *a, **k):  # keyframe 0 is the old end: its ratio comes out 2x
        Z, s, u = measure(pose_a, disp_a, *a, **k)
        if torch.equal(pose_a, drifted[0][0]):
            Z = Z.clone()
            Z[7] = 2.0 * s
            return Z, 2.0 * s, u
        return Z, s, u

    monkeypatch.setattr(O, "loop_relative_sim3", wrong_from_the_old_end)
    rep = make("online_ba").loop(pr.graph(*drifted), pr.obs(), [_loop(n - 1, 0)])
    assert "sim3 pgo skipped (1 left out by the direction / scale checks)" in rep.message, rep.message
    monkeypatch.setattr(O, "PGO_MAX_SCALE_DISAGREEMENT", math.inf)  # the check off
    rep = make("online_ba").loop(pr.graph(*drifted), pr.obs(), [_loop(n - 1, 0)])
    assert "sim3 pgo:" in rep.message, rep.message


def test_old_optimizer_keys_through_the_config_loader():
    """A whole pipeline config with the old flat keys: they land in the nested tables (online and offline schedule);
    a retired key at another value is a ConfigError that names it."""
    from pvslam_core.config import ConfigError, load_config

    cfg = load_config(None, overrides=["optimizer.final_iters=6", "optimizer.loop_iters=2", "optimizer.sim3_pgo=false"])
    opt = cfg.models["optimizer"]
    assert (opt.final.iters, opt.final.rounds, opt.loop.iters, opt.loop.sim3_pgo) == (6, 1, 2, False)
    assert cfg.pipeline.optimizer.params["final"] == {"iters": 6, "rounds": 1}  # what a run directory stores
    cfg = load_config(None, overrides=['optimizer.plugin="offline_ba"', "optimizer.final_rounds=3"])
    assert (cfg.models["optimizer"].final.iters, cfg.models["optimizer"].final.rounds) == (8, 3)
    new = load_config(None, overrides=["optimizer.final.iters=6", "optimizer.loop.iters=2"]).models["optimizer"]
    assert new == load_config(None, overrides=["optimizer.final_iters=6", "optimizer.loop_iters=2"]).models["optimizer"]
    with pytest.raises(ConfigError, match="'iters_max' was retired"):
        load_config(None, overrides=["optimizer.iters_max=5"])
