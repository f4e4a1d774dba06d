import logging

import pytest
import torch

from pvslam_core.geometry.ba import dense_ba, motion_only_ba, weighted_cost
from pvslam_core.geometry.lie import se3_exp, se3_inv, se3_log, se3_mul
from pvslam_core.geometry.testing import make_problem, perturb


def pose_err(a, b):
    e = se3_log(se3_mul(se3_inv(a), b))
    return float(e[:, :3].norm(dim=-1).max()), float(e[:, 3:].norm(dim=-1).max())


def observed(pr):
    seen = torch.zeros(pr.disps.shape, dtype=torch.bool)
    for e in range(len(pr.ii)):
        seen[pr.ii[e]] |= pr.weight[e, 0] > 0
    return seen


@pytest.fixture(scope="module")
def problem():
    return make_problem(n=7, seed=0)


def test_noise_free_recovers_ground_truth(problem):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    g = pr.graph(p0, d0)
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False  # two fixed poses fix the monocular scale gauge
    rep = dense_ba(g, pr.obs(), free, iters=10, lm=1e-4, ep=1e-4, depth_damping=1e-4)
    assert not rep.rejected and rep.iterations == 10
    assert rep.cost_after < 1e-6 * rep.cost_before
    et, er = pose_err(pr.poses, g.poses)
    assert et < 1e-5 and er < 1e-5
    seen = observed(pr)
    rel = ((g.disps - pr.disps).abs() / pr.disps)[seen]
    assert rel.max() < 1e-4
    # fixed poses untouched
    assert torch.equal(g.poses[:2], p0[:2])


def test_droid_constants_converge(problem):
    """Frontend constants (lm 1e-4, ep 0.1, eta 1e-3) still converge, a bit slower."""
    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    g = pr.graph(p0, d0)
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    dense_ba(g, pr.obs(), free, iters=12)
    et, er = pose_err(pr.poses, g.poses)
    assert et < 1e-3 and er < 1e-3


def test_noise_and_outliers():
    pr = make_problem(n=7, seed=2, noise=0.3, outlier_frac=0.1, outlier_weight=0.02)
    p0, d0 = perturb(pr, fixed=(0, 1), seed=3)
    g = pr.graph(p0, d0)
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    rep = dense_ba(g, pr.obs(), free, iters=10, lm=1e-4, ep=1e-3, depth_damping=1e-3, robust="huber", robust_scale=1.0)
    assert not rep.rejected and rep.cost_after < rep.cost_before
    et, er = pose_err(pr.poses, g.poses)
    # stated accuracy: 0.3 px noise + 10 % outliers (+-10 px, weight x0.02) at 40x30, depths 1-8 m
    # -> translation error < 2 cm, rotation error < 0.003 rad (0.17 deg); measured ~1.1 cm / 0.0011 rad
    assert et < 0.02 and er < 0.003, (et, er)
    seen = observed(pr) & (pr.disps > 0.15)
    rel = ((g.disps - pr.disps).abs() / pr.disps)[seen]
    assert rel.median() < 0.05


def test_gauge_fixed_poses_and_depth_free(problem):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0,))
    g = pr.graph(p0, d0)
    free = torch.zeros(7, dtype=torch.bool)
    free[4:] = True
    depth_free = torch.zeros(7, dtype=torch.bool)
    depth_free[5] = True
    rep = dense_ba(g, pr.obs(), free, iters=3, depth_free=depth_free)
    assert rep.num_free_poses == 3
    assert torch.equal(g.poses[:4], p0[:4])
    assert not torch.equal(g.poses[4:], p0[4:])
    others = [k for k in range(7) if k != 5]
    assert torch.equal(g.disps[others], d0[others])
    assert not torch.equal(g.disps[5], d0[5])


def test_single_fixed_pose_monocular_stays_finite(problem):
    """Only keyframe 0 fixed: the scale direction is held by damping; the result is finite and the cost drops."""
    pr = problem
    p0, d0 = perturb(pr, fixed=(0,))
    g = pr.graph(p0, d0)
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    rep = dense_ba(g, pr.obs(), free, iters=6)
    assert not rep.rejected and rep.cost_after < 0.01 * rep.cost_before
    assert torch.isfinite(g.poses).all() and torch.isfinite(g.disps).all()


def test_nan_targets_rejected(problem, caplog):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    g = pr.graph(p0, d0)
    obs = pr.obs()
    obs.target[3, 0, 5, 5] = float("nan")
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    with caplog.at_level(logging.WARNING, logger="pvslam.ba"):
        rep = dense_ba(g, obs, free, iters=2)
    assert rep.rejected and "non-finite" in rep.message
    assert torch.equal(g.poses, p0) and torch.equal(g.disps, d0)
    obs.target[3, 0, 5, 5] = 1.0
    obs.weight[2, 1, 0, 0] = float("inf")
    rep = dense_ba(g, obs, free, iters=2)
    assert rep.rejected and torch.equal(g.poses, p0)


def test_no_edges_and_weighted_cost(problem):
    pr = problem
    g = pr.graph()
    obs = pr.obs()
    assert weighted_cost(g, obs) < 1e-6
    empty = pr.obs(torch.tensor([], dtype=torch.long), torch.tensor([], dtype=torch.long))
    rep = dense_ba(g, empty, torch.ones(7, dtype=torch.bool))
    assert rep.iterations == 0 and not rep.rejected


def test_motion_only_ba(problem):
    pr = problem
    k, new = 2, 3
    e = int(torch.nonzero((pr.ii == k) & (pr.jj == new))[0])
    start = se3_mul(pr.poses[new], se3_exp(torch.tensor([0.03, -0.02, 0.02, 0.01, -0.02, 0.01], dtype=torch.float64)))
    pose, cost = motion_only_ba(start, pr.poses[k], pr.disps[k], pr.intr, pr.target[e], pr.weight[e], iters=8,
                                lm=1e-5, ep=1e-4)
    et, er = pose_err(pr.poses[new][None], pose[None])
    assert et < 1e-5 and er < 1e-5 and cost < 1e-6
    bad = pr.target[e].clone()
    bad[0, 0, 0] = float("nan")
    pose2, cost2 = motion_only_ba(start, pr.poses[k], pr.disps[k], pr.intr, bad, pr.weight[e])
    assert torch.equal(pose2, start) and cost2 != cost2


def test_motion_only_ba_robust_kernel_rejects_gross_outliers(problem):
    """A quarter of the targets shifted by 15 px: least squares is pulled off, the Cauchy kernel is not."""
    pr = problem
    k, new = 2, 3
    e = int(torch.nonzero((pr.ii == k) & (pr.jj == new))[0])
    start = se3_mul(pr.poses[new], se3_exp(torch.tensor([0.02, -0.01, 0.01, 0.01, -0.01, 0.01], dtype=torch.float64)))
    bad = pr.target[e].clone()
    gen = torch.Generator().manual_seed(0)
    out = torch.rand(bad.shape[-2:], generator=gen) < 0.25
    bad[0][out] += 15.0
    kw = dict(iters=15, lm=1e-5, ep=1e-4)
    plain, _ = motion_only_ba(start, pr.poses[k], pr.disps[k], pr.intr, bad, pr.weight[e], **kw)
    robust, _ = motion_only_ba(start, pr.poses[k], pr.disps[k], pr.intr, bad, pr.weight[e], robust="cauchy",
                               robust_scale=1.0, **kw)
    et_plain, _ = pose_err(pr.poses[new][None], plain[None])
    et_rob, er_rob = pose_err(pr.poses[new][None], robust[None])
    assert et_plain > 1e-2
    assert et_rob < 0.05 * et_plain and er_rob < 1e-3


def test_float32_path_matches(problem):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    g32, g64 = pr.graph(p0, d0), pr.graph(p0, d0)
    dense_ba(g32, pr.obs(), free, iters=6, ep=1e-4, depth_damping=1e-4, dtype=torch.float32)
    dense_ba(g64, pr.obs(), free, iters=6, ep=1e-4, depth_damping=1e-4, dtype=torch.float64)
    et, er = pose_err(g64.poses, g32.poses)
    assert et < 1e-4 and er < 1e-4


def test_all_finite_fast_path():
    from pvslam_core.geometry.ba import _all_finite

    assert _all_finite(torch.tensor([3e38, 3e38]))  # the float32 sum overflows, the values are finite
    assert not _all_finite(torch.tensor([1.0, float("inf")]))
    assert not _all_finite(torch.tensor([float("inf"), float("-inf")]))
    assert not _all_finite(torch.tensor([1.0, float("nan")]))
    assert _all_finite(torch.zeros(0))


def test_reproject_float32_graph_inputs(problem):
    """The frontend calls reproject with float64 poses and float32 disparities."""
    from pvslam_core.geometry.projective import reproject

    g = problem.graph()
    coords, valid = reproject(g.poses, g.disps, g.intrinsics, problem.ii, problem.jj)
    assert coords.dtype == torch.float32 and coords.shape == (len(problem.ii), 30, 40, 2)
    m = problem.weight[:, 0] > 0
    assert torch.allclose(coords.permute(0, 3, 1, 2)[:, 0][m], problem.target[:, 0][m], atol=1e-3)


def test_indefinite_system_rejected(problem, monkeypatch):
    """A pose system that cannot be factorised (forced here) leaves the state unchanged and is reported."""
    import pvslam_core.geometry.ba as ba

    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    g = pr.graph(p0, d0)
    monkeypatch.setattr(ba, "solve_spd", lambda A, b: None)
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    rep = ba.dense_ba(g, pr.obs(), free, iters=2)
    assert rep.rejected and "positive definite" in rep.message
    assert torch.equal(g.poses, p0) and torch.equal(g.disps, d0)


def test_sparse_pose_solve_matches_dense(problem, monkeypatch):
    import pvslam_core.geometry.ba as ba

    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    g_dense, g_sparse = pr.graph(p0, d0), pr.graph(p0, d0)
    r1 = ba.dense_ba(g_dense, pr.obs(), free, iters=3)
    monkeypatch.setattr(ba, "SPARSE_MIN_POSES", 2)
    r2 = ba.dense_ba(g_sparse, pr.obs(), free, iters=3)
    assert not r2.rejected and abs(r1.cost_after - r2.cost_after) < 1e-6 * max(r1.cost_before, 1.0)
    et, er = pose_err(g_dense.poses, g_sparse.poses)
    assert et < 1e-6 and er < 1e-6


def test_adaptive_iterations_go_on_only_while_the_cost_falls(problem):
    """``max_iters``: after ``iters`` iterations the BA continues while the last one gained more than ``rel_tol``
    of the cost.  Continuing is exactly the plain BA with more iterations (the same updates, bit for bit); a
    converged problem stops at ``iters``; ``max_iters`` None or <= ``iters`` is the plain BA."""
    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    kw = dict(lm=1e-4, ep=0.1, depth_damping=1e-3)  # DROID's frontend constants: slow convergence

    def run(**k):
        g = pr.graph(p0.clone(), d0.clone())
        return g, dense_ba(g, pr.obs(), free, **kw, **k)

    g3, r3 = run(iters=3)
    for off in (dict(max_iters=None), dict(max_iters=3, rel_tol=1e-3), dict(max_iters=2, rel_tol=1e-3)):
        g, r = run(iters=3, **off)
        assert r.iterations == 3 and torch.equal(g.poses, g3.poses) and torch.equal(g.disps, g3.disps)
        assert r.cost_after == r3.cost_after
    ga, ra = run(iters=3, max_iters=12, rel_tol=1e-3)
    assert 3 < ra.iterations <= 12 and ra.cost_after < 0.5 * r3.cost_after
    gp, rp = run(iters=ra.iterations)  # the same iterations run plainly
    assert torch.equal(ga.poses, gp.poses) and torch.equal(ga.disps, gp.disps) and ra.cost_after == rp.cost_after
    if ra.iterations < 12:  # it stopped because the last iteration gained <= rel_tol
        g_prev, r_prev = run(iters=ra.iterations - 1)
        assert r_prev.cost_after - ra.cost_after <= 1e-3 * r_prev.cost_after
    # no iteration gains more than all of the cost: rel_tol 1 stops right after the minimum; a converged problem too
    _, rb = run(iters=3, max_iters=12, rel_tol=1.0)
    assert rb.iterations == 3
    pn = make_problem(n=7, seed=2, noise=0.3)  # noisy: the optimum's cost is well above float noise
    gc = pn.graph(*perturb(pn, fixed=(0, 1), seed=3))
    dense_ba(gc, pn.obs(), free, iters=40, **kw)
    rc = dense_ba(gc, pn.obs(), free, iters=2, max_iters=10, rel_tol=1e-3, **kw)
    assert rc.iterations == 2 and rc.cost_after > 1.0


def test_robust_cost_is_the_irls_objective():
    """With the same confidence on u and v the adaptive check's objective is ``sum conf * 2 rho(n)``: Cauchy
    ``s^2 log(1 + n^2 / s^2)``, Huber ``n^2`` inside ``s`` and ``2 s n - s^2`` outside; its gradient is the IRLS
    weight times the least-squares one (checked by autograd)."""
    from pvslam_core.geometry.ba import _robust_cost, _robust_weights
    g = torch.Generator().manual_seed(0)
    ru, rv = torch.randn(3, 50, generator=g, dtype=torch.float64) * 3, torch.randn(3, 50, generator=g, dtype=torch.float64) * 3
    c = torch.rand(3, 50, generator=g, dtype=torch.float64)
    conf, valid = torch.stack([c, c], 1), (torch.rand(3, 50, generator=g) > 0.2).double()
    n2, s = ru ** 2 + rv ** 2, 1.5
    cauchy = float((valid * c * s * s * torch.log1p(n2 / s ** 2)).sum())
    n = n2.sqrt()
    huber = float((valid * c * torch.where(n <= s, n2, 2 * s * n - s * s)).sum())
    assert _robust_cost(conf, valid, ru, rv, "cauchy", s) == pytest.approx(cauchy, rel=1e-9)
    assert _robust_cost(conf, valid, ru, rv, "huber", s) == pytest.approx(huber, rel=1e-9)
    assert _robust_cost(conf, valid, ru, rv, None, s) == pytest.approx(float((valid * c * n2).sum()), rel=1e-12)
    for kind in ("cauchy", "huber"):  # the same per-pixel factor as _robust_cost, differentiated
        x, y = ru.clone().requires_grad_(), rv.clone().requires_grad_()
        n2g = (x * x + y * y).clamp(min=1e-12)
        ng = n2g.sqrt()
        f = torch.log1p(n2g / s ** 2) * s ** 2 / n2g if kind == "cauchy" else \
            torch.where(ng <= s, torch.ones_like(ng), (2 * s * ng - s * s) / n2g)
        (valid * f * c * n2g).sum().backward()
        w = _robust_weights(ru, rv, kind, s)
        assert torch.allclose(x.grad, 2 * valid * c * w * ru, atol=1e-9) and torch.allclose(y.grad, 2 * valid * c * w * rv, atol=1e-9)
