"""dense_ba linearises the edges in chunks of whole depth sources (``max_chunk_pixels``): any chunking gives the
one-chunk result (exactly up to float32 summation order)."""
import pytest
import torch

import pvslam_core.geometry.ba_linalg as ba_linalg
from pvslam_core.geometry.ba import dense_ba
from pvslam_core.geometry.ba_schur import plan_chunks
from pvslam_core.geometry.testing import make_problem, perturb
from pvslam_core.types import EdgeObservations

H, W = 30, 40
P = H * W
HUGE = 10**12


@pytest.fixture(scope="module")
def problem():
    """9 keyframes, |i - j| <= 2: sources with 2, 3, 4, 4, 4, 4, 4, 3, 2 edges (30 edges)."""
    pr = make_problem(n=9, h=H, w=W, seed=4, noise=0.2, radius=2)
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(9, dtype=torch.bool)
    free[:2] = False
    return pr, p0, d0, free


def run(pr, p0, d0, free, mcp, obs=None, **kw):
    g = pr.graph(p0, d0)
    kw.setdefault("iters", 3)
    rep = dense_ba(g, pr.obs() if obs is None else obs, free, max_chunk_pixels=mcp, **kw)
    return g, rep


def assert_same(ref, got, rtol=1e-5, atol=1e-6):
    (g0, r0), (g1, r1) = ref, got
    assert not r0.rejected and not r1.rejected
    assert (r1.iterations, r1.num_edges, r1.num_free_poses) == (r0.iterations, r0.num_edges, r0.num_free_poses)
    assert r1.cost_after < r1.cost_before
    torch.testing.assert_close(g1.poses, g0.poses, rtol=rtol, atol=atol)
    torch.testing.assert_close(g1.disps, g0.disps, rtol=rtol, atol=atol)
    assert r1.cost_before == pytest.approx(r0.cost_before, rel=rtol)
    assert r1.cost_after == pytest.approx(r0.cost_after, rel=rtol)


def plan(pr, mcp, depth_free=None, free=None):
    n = pr.poses.shape[0]
    ii, jj = pr.ii, pr.jj
    free = torch.ones(n, dtype=torch.bool) if free is None else free
    pose_map = torch.full((n,), -1, dtype=torch.int64)
    pose_map[free] = torch.arange(int(free.sum()))
    dfree = torch.zeros(n, dtype=torch.bool)
    dfree[ii] = True
    if depth_free is not None:
        dfree &= depth_free
    src = torch.nonzero(dfree).squeeze(1)
    src_map = torch.full((n,), -1, dtype=torch.int64)
    src_map[src] = torch.arange(len(src))
    return plan_chunks(ii, jj, pose_map, src_map[ii], len(src), int(free.sum()), P, mcp), src_map[ii]


def test_plan_chunks_whole_sources_within_budget(problem):
    pr = problem[0]
    chunks, es = plan(pr, 9 * P)
    assert len(chunks) == 4
    assert sorted(c.n_src for c in chunks) == [5, 8, 8, 9]  # sources (2, 3, 4) (4, 4) (4, 4) (3, 2)
    assert chunks[-1].n_src == 9  # the largest chunk last: its E^T is kept for the back-substitution
    rows = torch.cat([torch.arange(len(pr.ii))[c.idx] for c in chunks])
    assert sorted(rows.tolist()) == list(range(len(pr.ii)))  # every edge exactly once
    for c in chunks:
        assert len(c.ii) <= 9
        assert sorted(set(es[c.idx].tolist())) == list(range(c.s0, c.s1))  # whole sources, consecutive slots
    # fixed-depth edges (sources 3 and 6): chunked by edge, after the source edges of a chunk
    depth_free = torch.ones(9, dtype=torch.bool)
    depth_free[[3, 6]] = False
    chunks, es = plan(pr, 5 * P, depth_free=depth_free)
    assert all((es[c.idx][:c.n_src] >= 0).all() and (es[c.idx][c.n_src:] < 0).all() for c in chunks)
    assert any(c.ns == 0 for c in chunks) and max(len(c.ii) for c in chunks) <= 5
    # one edge per chunk budget: every source (up to 4 edges) is a chunk of its own
    chunks, _ = plan(pr, 1)
    assert len(chunks) == 9 and all(c.ns == 1 for c in chunks)


@pytest.mark.parametrize("mcp", [9 * P, 5 * P, 7 * P + 1])
def test_chunked_equals_unchunked(problem, mcp):
    pr, p0, d0, free = problem
    assert_same(run(pr, p0, d0, free, HUGE), run(pr, p0, d0, free, mcp))


def test_default_budget_is_one_chunk_for_small_problems(problem):
    pr, p0, d0, free = problem
    g0, r0 = run(pr, p0, d0, free, HUGE)
    g1 = pr.graph(p0, d0)
    r1 = dense_ba(g1, pr.obs(), free, iters=3)
    assert torch.equal(g0.poses, g1.poses) and torch.equal(g0.disps, g1.disps)
    assert (r0.cost_before, r0.cost_after) == (r1.cost_before, r1.cost_after)


def test_fixed_depth_sources_robust_and_shuffled_edges(problem):
    """Sources 3 and 6 keep their depth (their edges are chunked by edge); edges in random order (chunks are
    gathered rows, not slices); Cauchy re-weighting; per-keyframe learned depth damping ``obs.eta``."""
    pr, p0, d0, free = problem
    depth_free = torch.ones(9, dtype=torch.bool)
    depth_free[[3, 6]] = False
    perm = torch.randperm(len(pr.ii), generator=torch.Generator().manual_seed(0))
    eta = 1e-3 * (1.0 + torch.rand(9, H, W, generator=torch.Generator().manual_seed(1)))
    o = pr.obs()
    obs = EdgeObservations(o.ii[perm], o.jj[perm], o.target[perm], o.weight[perm], depth_damping=eta)
    kw = dict(depth_free=depth_free, robust="cauchy", robust_scale=1.0)
    ref = run(pr, p0, d0, free, HUGE, obs=EdgeObservations(o.ii, o.jj, o.target, o.weight, depth_damping=eta), **kw)
    assert torch.equal(ref[0].disps[[3, 6]], d0[[3, 6]])
    for mcp in (5 * P, 2 * P):
        assert_same(ref, run(pr, p0, d0, free, mcp, obs=obs, **kw))


def test_single_source_larger_than_budget():
    """Keyframe 0 is the source of 6 edges, the budget is 2 edges: that source is linearised alone."""
    ii = torch.tensor([0, 0, 0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 6])
    jj = torch.tensor([1, 2, 3, 4, 5, 6, 0, 3, 2, 5, 4, 5, 0])
    pr = make_problem(n=7, h=H, w=W, seed=1, noise=0.1, edges=(ii, jj))
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(7, dtype=torch.bool)
    free[:2] = False
    chunks, _ = plan(pr, 2 * P, free=free)
    big = [c for c in chunks if c.s0 == 0]
    assert len(big) == 1 and big[0].ns == 1 and big[0].n_src == 6 == len(big[0].ii)
    ref = run(pr, p0, d0, free, HUGE)
    assert_same(ref, run(pr, p0, d0, free, 2 * P))
    assert_same(ref, run(pr, p0, d0, free, 1))


def test_float64_chunking_is_exact(problem):
    pr, p0, d0, free = problem
    ref = run(pr, p0, d0, free, HUGE, dtype=torch.float64)
    assert_same(ref, run(pr, p0, d0, free, 5 * P, dtype=torch.float64), rtol=1e-10, atol=1e-12)


def test_depth_only_and_pose_only_problems(problem):
    pr, p0, d0, free = problem
    no_pose = torch.zeros(9, dtype=torch.bool)
    assert_same(run(pr, p0, d0, no_pose, HUGE), run(pr, p0, d0, no_pose, 5 * P))
    no_depth = torch.zeros(9, dtype=torch.bool)  # every edge has a fixed source depth: chunked by edge
    ref = run(pr, p0, d0, free, HUGE, depth_free=no_depth)
    assert torch.equal(ref[0].disps, d0)
    assert_same(ref, run(pr, p0, d0, free, 4 * P, depth_free=no_depth))


def test_sparse_pose_solve_with_chunks(problem, monkeypatch):
    pr, p0, d0, free = problem
    monkeypatch.setattr(ba_linalg, "SPARSE_MIN_POSES", 2)
    assert_same(run(pr, p0, d0, free, HUGE), run(pr, p0, d0, free, 5 * P))


def test_chunked_rejection_keeps_state(problem):
    """Non-finite inputs are still rejected before anything is linearised, whatever the chunking."""
    pr, p0, d0, free = problem
    obs = pr.obs()
    obs.target[7, 1, 3, 3] = float("nan")
    g, rep = run(pr, p0, d0, free, 2 * P, obs=obs)
    assert rep.rejected and "non-finite" in rep.message
    assert torch.equal(g.poses, p0) and torch.equal(g.disps, d0)
