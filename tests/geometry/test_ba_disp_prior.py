"""dense_ba's disparity prior (DROID-SLAM's ``disps_sens`` term): it pulls depths to the prior, fixes the monocular
scale, joins the chunked Schur step exactly, and bad priors are refused."""
import pytest
import torch

from pvslam_core.geometry.ba import dense_ba
from pvslam_core.geometry.testing import make_problem, perturb
from pvslam_core.types import DepthPrior, DistancePrior, EdgeObservations


@pytest.fixture(scope="module")
def problem():
    return make_problem(n=7, seed=0)


def with_prior(pr, target, alpha, ids=None):
    """The problem's observations with a prior on keyframes ``ids`` (default: all, in order)."""
    o = pr.obs()
    ids = torch.arange(target.shape[0]) if ids is None else ids
    return EdgeObservations(o.ii, o.jj, o.target, o.weight, disp_prior=DepthPrior(ids, target, alpha))


def scaled(pr, s):
    """The ground truth seen at scale ``s`` (positions x s, inverse depths / s): same reprojections exactly."""
    p = pr.poses.clone()
    p[:, :3] = p[:, :3] * s
    return p, pr.disps / s


def baseline_ratio(g, pr):
    return pr.baseline_ratio(g.poses)


def test_prior_on_a_third_of_the_pixels_moves_the_scale_to_it(problem):
    """Start at the exact solution scaled by 2 (zero flow residual, a monocular gauge direction): without a prior
    nothing moves; a prior at the true scale on a third of the rows pulls poses and all depths to it."""
    pr = problem
    p0, d0 = scaled(pr, 2.0)
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    g = pr.graph(p0, d0)
    dense_ba(g, pr.obs(), free, iters=8, depth_damping=1e-6)
    assert baseline_ratio(g, pr) == pytest.approx(2.0, rel=1e-3)
    alpha = torch.zeros_like(pr.disps)
    alpha[:, -pr.shape[0] // 3:] = 0.05  # the lower third (as the road's)
    g = pr.graph(p0, d0)
    rep = dense_ba(g, with_prior(pr, pr.disps.clone(), alpha), free, iters=8, depth_damping=1e-6)
    assert not rep.rejected
    assert baseline_ratio(g, pr) == pytest.approx(1.0, abs=0.02)
    rel = ((g.disps - pr.disps).abs() / pr.disps)[pr.observed()]
    assert float(rel.median()) < 0.02  # the rows without a prior follow through the flow


def test_strong_prior_pins_the_depth_and_zero_weight_is_no_prior(problem):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    ref = pr.graph(p0, d0)
    dense_ba(ref, pr.obs(), free, iters=3)
    g = pr.graph(p0, d0)
    dense_ba(g, with_prior(pr, torch.full_like(pr.disps, 123.0), torch.zeros_like(pr.disps)), free, iters=3)
    torch.testing.assert_close(g.disps, ref.disps)  # weight 0 everywhere: the plain BA
    torch.testing.assert_close(g.poses, ref.poses)
    target = pr.disps * 1.3
    alpha = torch.zeros_like(pr.disps)
    alpha[3, 5:10, 5:10] = 1e3
    g = pr.graph(p0, d0)
    dense_ba(g, with_prior(pr, target, alpha), free, iters=3)
    torch.testing.assert_close(g.disps[3, 5:10, 5:10], target[3, 5:10, 5:10], rtol=1e-3, atol=0)


def test_prior_chunked_equals_unchunked():
    pr = make_problem(n=9, h=30, w=40, seed=4, noise=0.2, radius=2)
    p0, d0 = perturb(pr, fixed=(0,))
    free = torch.ones(9, dtype=torch.bool)
    free[0] = False
    gen = torch.Generator().manual_seed(0)
    alpha = 0.05 * (torch.rand(pr.disps.shape, generator=gen) > 0.5).float()
    out = []
    for mcp in (10**12, 1300, 1):
        g = pr.graph(p0, d0)
        rep = dense_ba(g, with_prior(pr, pr.disps * 0.9, alpha), free, iters=3, max_chunk_pixels=mcp)
        assert not rep.rejected
        out.append((g.poses.clone(), g.disps.clone(), rep.iterations))
    for poses, disps, its in out[1:]:
        assert its == out[0][2]
        torch.testing.assert_close(poses, out[0][0], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(disps, out[0][1], rtol=1e-5, atol=1e-6)


def test_bad_priors_are_refused(problem):
    pr = problem
    p0, d0 = perturb(pr, fixed=(0,))
    free = torch.ones(7, dtype=torch.bool)
    free[0] = False
    bad = torch.ones_like(pr.disps)
    bad[2, 3, 4] = float("nan")
    g = pr.graph(p0, d0)
    rep = dense_ba(g, with_prior(pr, bad, torch.ones_like(pr.disps)), free, iters=2)
    assert rep.rejected and "disparity prior" in rep.message
    assert torch.equal(g.poses, p0) and torch.equal(g.disps, d0)
    rep = dense_ba(g, with_prior(pr, pr.disps, -torch.ones_like(pr.disps)), free, iters=2)
    assert rep.rejected and "prior weight" in rep.message
    with pytest.raises(ValueError, match=r"must be \[m\], \[m, h, w\]"):
        DepthPrior(torch.arange(7), pr.disps, pr.disps[:2])


def test_prior_on_some_keyframes_in_any_order(problem):
    """A prior given for keyframes [5, 2] (sparse, unordered) is the same as the full prior that is zero elsewhere;
    a keyframe whose depth is not optimised ignores its prior."""
    pr = problem
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    target, alpha = pr.disps * 1.2, torch.zeros_like(pr.disps)
    alpha[[2, 5]] = 0.05
    full = pr.graph(p0, d0)
    dense_ba(full, with_prior(pr, target, alpha), free, iters=3)
    part = pr.graph(p0, d0)
    ids = torch.tensor([5, 2])
    dense_ba(part, with_prior(pr, target[ids], alpha[ids], ids), free, iters=3)
    torch.testing.assert_close(part.disps, full.disps)
    torch.testing.assert_close(part.poses, full.poses)
    plain = pr.graph(p0, d0)
    dense_ba(plain, pr.obs(), free, iters=3)
    assert not torch.allclose(plain.disps[2], full.disps[2])
    depth_free = torch.ones(7, dtype=torch.bool)
    depth_free[[2, 5]] = False
    a, b = pr.graph(p0, d0), pr.graph(p0, d0)
    dense_ba(a, with_prior(pr, target[ids], alpha[ids], ids), free, iters=3, depth_free=depth_free)
    dense_ba(b, pr.obs(), free, iters=3, depth_free=depth_free)
    torch.testing.assert_close(a.disps, b.disps)
    with pytest.raises(IndexError, match="disp_prior.ids out of range"):
        dense_ba(a, with_prior(pr, target[:1], alpha[:1], torch.tensor([7])), free, iters=1)


def test_the_mapper_asks_the_frontend_for_the_sources_prior(problem):
    """EdgeObserver.with_prior: the frontend's Frontend.depth_prior for the unique depth sources of the observations
    (after live and retired edges are joined), nothing when the frontend has none."""
    from pvslam_core.slam.observe import EdgeObserver, concat

    pr = problem
    asked = []

    asked_dist = []

    class FE:
        def depth_prior(self, graph, idx):
            asked.append(idx.tolist())
            return None if 0 in idx.tolist() else DepthPrior(idx, pr.disps[idx], torch.full_like(pr.disps[idx], 0.05))

        def distance_prior(self, graph, idx):  # consecutive pairs among the edges' keyframes, 1 map unit apart
            asked_dist.append(idx.tolist())
            one = torch.ones(len(idx) - 1, dtype=torch.float64)
            return DistancePrior(idx[:-1], idx[1:], one, 5 * one)

    m = EdgeObserver(pr.graph(), FE())
    o = pr.obs()
    sel = o.ii > 0
    part = EdgeObservations(o.ii[sel], o.jj[sel], o.target[sel], o.weight[sel])
    got = m.with_prior(concat([part, part], torch.arange(2 * int(sel.sum()))))
    assert asked[-1] == sorted(set(o.ii[sel].tolist()))
    assert got.disp_prior.ids.tolist() == asked[-1] and got.disp_prior.disp.shape == (len(asked[-1]), *pr.shape)
    torch.testing.assert_close(got.disp_prior.disp, pr.disps[got.disp_prior.ids])
    # the distance prior: asked for the keyframes at either end of the edges, attached as given
    assert asked_dist[-1] == sorted(set(o.ii[sel].tolist()) | set(o.jj[sel].tolist()))
    assert got.dist_prior.ii.tolist() == asked_dist[-1][:-1] and got.dist_prior.jj.tolist() == asked_dist[-1][1:]
    assert got.dist_prior.weight.tolist() == [5.0] * (len(asked_dist[-1]) - 1)
    assert m.with_prior(o).disp_prior is None  # keyframe 0 among the sources: this frontend gives none
