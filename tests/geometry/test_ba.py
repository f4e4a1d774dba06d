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
    from pvslam_core.geometry.ba_linalg import all_finite as _all_finite

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
    import pvslam_core.geometry.ba_linalg as ba_linalg

    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    g = pr.graph(p0, d0)
    monkeypatch.setattr(ba_linalg, "solve_spd", lambda A, b: None)
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    rep = ba.dense_ba(g, pr.obs(), free, iters=2)
    assert rep.rejected and "positive definite" in rep.message
    assert torch.equal(g.poses, p0) and torch.equal(g.disps, d0)


def test_sparse_pose_solve_matches_dense(problem, monkeypatch):
    import pvslam_core.geometry.ba as ba
    import pvslam_core.geometry.ba_linalg as ba_linalg

    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    g_dense, g_sparse = pr.graph(p0, d0), pr.graph(p0, d0)
    r1 = ba.dense_ba(g_dense, pr.obs(), free, iters=3)
    monkeypatch.setattr(ba_linalg, "SPARSE_MIN_POSES", 2)
    r2 = ba.dense_ba(g_sparse, pr.obs(), free, iters=3)
    assert not r2.rejected and abs(r1.cost_after - r2.cost_after) < 1e-6 * max(r1.cost_before, 1.0)
    et, er = pose_err(g_dense.poses, g_sparse.poses)
    assert et < 1e-6 and er < 1e-6


def test_robust_weights_are_the_irls_weights_of_the_kernel():
    """With the same confidence on u and v the robust objective is ``sum conf * 2 rho(n)``: Cauchy
    ``s^2 log(1 + n^2 / s^2)``, Huber ``n^2`` inside ``s`` and ``2 s n - s^2`` outside; its gradient is the IRLS
    weight times the least-squares one (checked by autograd)."""
    from pvslam_core.geometry.ba_residuals import robust_weights as _robust_weights
    g = torch.Generator().manual_seed(0)
    ru, rv = torch.randn(3, 50, generator=g, dtype=torch.float64) * 3, torch.randn(3, 50, generator=g, dtype=torch.float64) * 3
    c = torch.rand(3, 50, generator=g, dtype=torch.float64)
    valid = (torch.rand(3, 50, generator=g) > 0.2).double()
    s = 1.5
    assert _robust_weights(ru, rv, None, s) is None and _robust_weights(ru, rv, "none", s) is None
    for kind in ("cauchy", "huber"):  # the per-pixel factor of the objective, differentiated
        x, y = ru.clone().requires_grad_(), rv.clone().requires_grad_()
        n2g = (x * x + y * y).clamp(min=1e-12)
        ng = n2g.sqrt()
        f = torch.log1p(n2g / s ** 2) * s ** 2 / n2g if kind == "cauchy" else \
            torch.where(ng <= s, torch.ones_like(ng), (2 * s * ng - s * s) / n2g)
        (valid * f * c * n2g).sum().backward()
        w = _robust_weights(ru, rv, kind, s)
        assert torch.allclose(x.grad, 2 * valid * c * w * ru, atol=1e-9) and torch.allclose(y.grad, 2 * valid * c * w * rv, atol=1e-9)


def test_options_object_and_keyword_overrides_are_the_same_call(problem):
    """``dense_ba(g, obs, free, BAOptions(...))`` is the keyword call of the same fields, bit for bit; keywords
    override single fields of an options object; an unknown keyword (the retired adaptive iterations) is an error."""
    from pvslam_core.geometry.ba import BAOptions

    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    kw = dict(iters=3, lm=1e-5, ep=1e-2, depth_damping=1e-5, robust="cauchy", robust_scale=1.0)
    runs = []
    for args, extra in (((BAOptions(**kw),), {}), ((), kw), ((BAOptions(iters=1, robust="huber"),), kw)):
        g = pr.graph(p0, d0)
        rep = dense_ba(g, pr.obs(), free, *args, **extra)
        runs.append((g.poses, g.disps, rep.cost_before, rep.cost_after, rep.iterations))
    for other in runs[1:]:
        assert torch.equal(runs[0][0], other[0]) and torch.equal(runs[0][1], other[1]) and runs[0][2:] == other[2:]
    with pytest.raises(TypeError, match="max_iters"):
        dense_ba(pr.graph(p0, d0), pr.obs(), free, iters=2, max_iters=5)
    with pytest.raises(Exception):  # frozen: one call's settings cannot change under it
        BAOptions().iters = 3
