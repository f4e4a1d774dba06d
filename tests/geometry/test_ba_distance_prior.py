"""dense_ba's distance prior (geometry/ba_distance.py): the distance between two camera centres, stated in map units,
moves the monocular scale to it, its Jacobian is the derivative of the distance, the sparse and dense pose solves
agree, zero weight is no prior and bad priors are refused."""
import pytest
import torch

import pvslam_core.geometry.ba_linalg as ba_linalg
from pvslam_core.geometry.ba import dense_ba
from pvslam_core.geometry.ba_distance import distance_prior_terms
from pvslam_core.geometry.lie import se3_exp, se3_inv, se3_mul
from pvslam_core.geometry.testing import make_problem, perturb
from pvslam_core.types import DistancePrior, EdgeObservations


@pytest.fixture(scope="module")
def problem():
    return make_problem(n=7, seed=0)


def centres(poses_wc):
    return poses_wc[:, :3]


def true_pairs(pr, weight=100.0):
    """Consecutive keyframes with their ground-truth centre distances."""
    ii = torch.arange(pr.poses.shape[0] - 1)
    jj = ii + 1
    dist = (centres(pr.poses)[ii] - centres(pr.poses)[jj]).norm(dim=-1)
    return ii, jj, dist, torch.full_like(dist, weight)


def with_dist(pr, ii, jj, dist, alpha):
    o = pr.obs()
    return EdgeObservations(o.ii, o.jj, o.target, o.weight, dist_prior=DistancePrior(ii, jj, dist, alpha))


def test_distance_prior_moves_the_scale_to_it(problem):
    """From the exact solution at twice the scale (zero flow residual: a gauge direction of the monocular problem)
    the plain BA does not move; the true distances between consecutive centres bring poses and depths back."""
    pr = problem
    p0, d0 = pr.poses.clone(), pr.disps / 2.0
    p0[:, :3] *= 2.0
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    g = pr.graph(p0, d0)
    dense_ba(g, pr.obs(), free, iters=8, depth_damping=1e-6)
    assert pr.baseline_ratio(g.poses) == pytest.approx(2.0, rel=1e-3)
    g = pr.graph(p0, d0)
    rep = dense_ba(g, with_dist(pr, *true_pairs(pr)), free, iters=8, depth_damping=1e-6)
    assert not rep.rejected
    assert pr.baseline_ratio(g.poses) == pytest.approx(1.0, abs=0.02)
    rel = ((g.disps - pr.disps).abs() / pr.disps)[pr.observed()]
    assert float(rel.median()) < 0.02  # the depths follow the poses through the flow


def test_jacobian_is_the_derivative_of_the_distance():
    gen = torch.Generator().manual_seed(3)
    T_wc = se3_exp(torch.randn(4, 6, generator=gen, dtype=torch.float64))
    G = se3_inv(T_wc)  # world-to-camera, as the BA keeps them
    ii, jj = torch.tensor([0, 2, 3]), torch.tensor([1, 0, 1])
    L = torch.tensor([0.7, 1.3, 2.0], dtype=torch.float64)
    pose_map = torch.arange(4)
    _, _, v_dest, v_vals, _ = distance_prior_terms(G, pose_map, ii, jj, L, torch.ones(3, dtype=torch.float64), 1.0,
                                                   4)

    def pred(Gx):
        c = se3_inv(Gx)[:, :3]
        return (c[ii] - c[jj]).norm(dim=-1) / L

    # with alpha = weight_scale = 1 each pair's gradient row is J^T r; recover J by pairs on one pose at a time
    r = 1.0 - pred(G)
    for k in range(4):
        for a in range(6):
            xi = torch.zeros(4, 6, dtype=torch.float64)
            xi[k, a] = 1e-6
            num = (pred(se3_mul(se3_exp(xi), G)) - pred(G)) / 1e-6  # [3] d pred / d xi_k[a]
            got = torch.zeros(3, dtype=torch.float64)
            for m in range(3):  # the analytic row: v_vals = J * r for this pair and pose
                sel = [q for q in range(v_dest.shape[0]) if int(v_dest[q]) == k and q % 3 == m]
                got[m] = sum(v_vals[q, a] for q in sel) / r[m]
            torch.testing.assert_close(got, num, rtol=1e-4, atol=1e-6)


def test_sparse_solve_equals_dense(problem, monkeypatch):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0,))
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    ii, jj, dist, alpha = true_pairs(pr)
    out = []
    for thresh in (10**9, 0):
        monkeypatch.setattr(ba_linalg, "SPARSE_MIN_POSES", thresh)
        g = pr.graph(p0, d0)
        rep = dense_ba(g, with_dist(pr, ii, jj, dist * 1.1, alpha), free, iters=3)
        assert not rep.rejected
        out.append((g.poses.clone(), g.disps.clone()))
    torch.testing.assert_close(out[1][0], out[0][0], rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(out[1][1], out[0][1], rtol=1e-5, atol=1e-6)


def test_zero_weight_is_no_prior_and_fixed_pairs_add_nothing(problem):
    """Against the plain BA from the same perturbed start (keyframes 0 and 1 fixed)."""
    pr = problem
    free = torch.arange(7) >= 2
    p0, d0 = perturb(pr, fixed=(0, 1))
    ref = pr.graph(p0, d0)
    dense_ba(ref, pr.obs(), free, iters=3)
    for ii, jj, dist, alpha in ((*true_pairs(pr)[:3], torch.zeros(6, dtype=torch.float64)),
                                (torch.tensor([0]), torch.tensor([1]), torch.tensor([5.0], dtype=torch.float64),
                                 torch.tensor([1e3], dtype=torch.float64))):  # both poses fixed
        g = pr.graph(p0, d0)
        dense_ba(g, with_dist(pr, ii, jj, dist, alpha), free, iters=3)
        torch.testing.assert_close(g.poses, ref.poses)
        torch.testing.assert_close(g.disps, ref.disps)


def test_bad_distance_priors_are_refused(problem):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0,))
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    ii, jj, dist, alpha = true_pairs(pr)
    for bad_d, bad_a in ((torch.full_like(dist, float("nan")), alpha), (torch.zeros_like(dist), alpha),
                         (dist, -alpha)):
        g = pr.graph(p0, d0)
        rep = dense_ba(g, with_dist(pr, ii, jj, bad_d, bad_a), free, iters=2)
        assert rep.rejected and "distance prior" in rep.message
        assert torch.equal(g.poses, p0) and torch.equal(g.disps, d0)
    with pytest.raises(IndexError, match="out of range"):
        dense_ba(pr.graph(p0, d0), with_dist(pr, ii, jj + 1, dist, alpha), free, iters=2)
    with pytest.raises(ValueError, match=r"must each be \[m\]"):
        DistancePrior(ii, jj, dist, alpha[:2])
