"""The compiled per-pixel loops of the dense BA (:mod:`pvslam_core.geometry.ba_kernels`) compute what the torch
reference computes (``BAOptions.compiled=False``), to float32 summation order, on every kind of call the pipeline
makes: several iterations, a disparity prior, chunks with fixed-depth edges, no free pose, no robust kernel."""
import numpy as np
import pytest
import torch

from pvslam_core.geometry import ba_problem
from pvslam_core.geometry.ba import BAOptions, dense_ba
from pvslam_core.geometry.ba_problem import fused_available
from pvslam_core.geometry.ba_residuals import edge_rt
from pvslam_core.geometry.projective import _rays, project_points
from pvslam_core.geometry.testing import make_problem, perturb
from pvslam_core.types import DepthPrior, EdgeObservations

H, W = 30, 40


@pytest.fixture(scope="module")
def problem():
    pr = make_problem(n=8, h=H, w=W, seed=7, noise=0.3, radius=2)
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(8, dtype=torch.bool)
    free[:2] = False
    return pr, p0, d0, free


def both(pr, p0, d0, free, obs=None, **kw):
    """``(torch, compiled)``: (graph, report) of the same call through each path."""
    out = []
    for compiled in (False, True):
        g = pr.graph(p0, d0)
        kw.setdefault("iters", 3)
        rep = dense_ba(g, pr.obs() if obs is None else obs, free, compiled=compiled, robust="cauchy", **kw)
        out.append((g, rep))
    return out


def assert_close(ref, got, rtol=2e-4):
    (g0, r0), (g1, r1) = ref, got
    assert not r0.rejected and not r1.rejected
    assert r1.iterations == r0.iterations
    assert r1.cost_after < r1.cost_before
    assert r1.cost_before == pytest.approx(r0.cost_before, rel=1e-4)
    assert r1.cost_after == pytest.approx(r0.cost_after, rel=rtol)
    torch.testing.assert_close(g1.poses, g0.poses, rtol=rtol, atol=1e-5)
    torch.testing.assert_close(g1.disps, g0.disps, rtol=rtol, atol=1e-5)


def test_the_compiled_loops_give_the_torch_result(problem):
    assert_close(*both(*problem))


@pytest.mark.parametrize("case", ["prior", "chunks", "fixed_depths", "no_free_pose", "no_robust_kernel"])
def test_the_compiled_loops_on_each_kind_of_call(problem, case):
    pr, p0, d0, free = problem
    kw, obs = {}, None
    if case == "prior":
        o = pr.obs()
        ids = torch.arange(8)
        obs = EdgeObservations(o.ii, o.jj, o.target, o.weight,
                               disp_prior=DepthPrior(ids, pr.disps, torch.full_like(pr.disps, 0.05)))
    elif case == "chunks":
        kw["max_chunk_pixels"] = 5 * H * W  # several chunks: the back-substitution recomputes their depth rows
    elif case == "fixed_depths":
        depth_free = torch.ones(8, dtype=torch.bool)
        depth_free[[2, 5]] = False
        kw.update(depth_free=depth_free, max_chunk_pixels=4 * H * W)
    elif case == "no_free_pose":
        free = torch.zeros(8, dtype=torch.bool)
    elif case == "no_robust_kernel":
        out = []
        for compiled in (False, True):
            g = pr.graph(p0, d0)
            out.append((g, dense_ba(g, pr.obs(), free, iters=3, compiled=compiled, robust=None)))
        assert_close(*out)
        return
    assert_close(*both(pr, p0, d0, free, obs=obs, **kw))


def test_one_edges_sums_match_the_jacobians(problem):
    """The kernel's per-edge ``J^T W J``, ``J^T W r`` and depth terms against :func:`project_points`' Jacobians."""
    pr, p0, d0, _ = problem
    kern = ba_problem.ba_kernels()
    G = pr.graph(p0, d0)
    from pvslam_core.geometry.lie import se3_inv

    Gw = se3_inv(G.poses)
    ii, jj = pr.ii[:4], pr.jj[:4]
    R, t = edge_rt(Gw, ii, jj, torch.float32)
    d = G.disps.reshape(8, -1).float().contiguous()
    fx, fy, cx, cy = (float(v) for v in pr.intr.tolist())
    rays = _rays(H, W, fx, fy, cx, cy, torch.float32, torch.device("cpu"))
    tgt = pr.target[:4].reshape(4, 2, -1).float().contiguous()
    cf = pr.weight[:4].reshape(4, 2, -1).float().contiguous()
    ws, scale = 1e-3, 2.0
    ls = torch.tensor([0, 0, 1, 1])
    C, wd = torch.zeros(2, H * W), torch.zeros(2, H * W)
    acc = torch.empty(4, 28)
    kern.pass_blocks(R.numpy(), t.numpy(), d.numpy(), ii.numpy(), rays[0].numpy(), rays[1].numpy(), tgt.numpy(),
                     cf.numpy(), fx, fy, cx, cy, 0.2, 1 / scale ** 2, ws, 4, ls.numpy(), C.numpy(), wd.numpy(),
                     acc.numpy())
    out = project_points(R.double(), t.double(), d[ii].double(), pr.intr, H, W, 0.2, "parts")
    ru, rv = tgt[:, 0].double() - out["u"], tgt[:, 1].double() - out["v"]
    w = out["valid"].double() * ws / (1 + (ru ** 2 + rv ** 2) / scale ** 2)
    wu, wv = cf[:, 0].double() * w, cf[:, 1].double() * w
    Hjj = torch.einsum("ekp,elp,ep->ekl", out["JuT"], out["JuT"], wu) + \
        torch.einsum("ekp,elp,ep->ekl", out["JvT"], out["JvT"], wv)
    q = torch.einsum("ekp,ep->ek", out["JuT"], wu * ru) + torch.einsum("ekp,ep->ek", out["JvT"], wv * rv)
    iu = torch.triu_indices(6, 6)
    torch.testing.assert_close(acc[:, :21].double(), Hjj[:, iu[0], iu[1]], rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(acc[:, 21:27].double(), q, rtol=1e-3, atol=1e-3)
    bu, bv = wu * out["Jdu"], wv * out["Jdv"]
    C_ref = torch.zeros(2, H * W, dtype=torch.float64).index_add_(0, ls, bu * out["Jdu"] + bv * out["Jdv"])
    wd_ref = torch.zeros(2, H * W, dtype=torch.float64).index_add_(0, ls, bu * ru + bv * rv)
    torch.testing.assert_close(C.double(), C_ref, rtol=1e-4, atol=1e-9)
    torch.testing.assert_close(wd.double(), wd_ref, rtol=1e-4, atol=1e-7)
    cost = (out["valid"].double() * (cf[:, 0] * ru ** 2 + cf[:, 1] * rv ** 2)).sum(-1)
    torch.testing.assert_close(acc[:, 27].double(), cost, rtol=1e-4, atol=1e-6)
    # the depth rows: (w Jdu Ju + w Jdv Jv) C^-1/2
    sC = torch.rand(2, H * W) + 0.5
    B = torch.empty(4, 6, H * W)
    kern.pass_rows(R.numpy(), t.numpy(), d.numpy(), ii.numpy(), rays[0].numpy(), rays[1].numpy(), tgt.numpy(),
                   cf.numpy(), fx, fy, cx, cy, 0.2, 1 / scale ** 2, ws, 4, ls.numpy(), sC.numpy(), B.numpy())
    B_ref = (out["JuT"] * bu.unsqueeze(1) + out["JvT"] * bv.unsqueeze(1)) * sC.double()[ls].unsqueeze(1)
    torch.testing.assert_close(B.double(), B_ref, rtol=1e-3, atol=1e-6)


def test_tiny_confidences_are_zeroed_for_the_compiled_loops(problem, monkeypatch):
    """Denormal confidences would slow every product they enter; weights that small change no sum, so the loops
    get them as zeros (and negative ones as zeros, as the torch path clamps them)."""
    pr, p0, d0, free = problem
    o = pr.obs()
    w = o.weight.clone()
    w[:, :, :5] = 1e-41  # a denormal float32
    w[:, :, 5:7] = -1.0
    kern, seen = ba_problem.ba_kernels(), []
    real = kern.pass_blocks
    monkeypatch.setattr(kern, "pass_blocks", lambda *a: (seen.append(a[7].copy()), real(*a))[1])
    rep = dense_ba(pr.graph(p0, d0), EdgeObservations(o.ii, o.jj, o.target, w), free, iters=1, robust="cauchy")
    assert not rep.rejected and seen
    cf = seen[0].reshape(len(o.ii), 2, H, W)
    assert (cf[:, :, :7] == 0).all()
    # the rest unchanged (the chunk orders its edges by source: compare the edges as a set)
    rows = sorted(r.tobytes() for r in np.ascontiguousarray(cf[:, :, 7:]))
    assert rows == sorted(r.tobytes() for r in np.ascontiguousarray(w[:, :, 7:].numpy()))


def test_the_torch_path_takes_what_the_loops_do_not_cover():
    cpu = torch.device("cpu")
    t = torch.zeros(2)
    assert fused_available(BAOptions(robust="cauchy"), torch.float32, cpu, t)
    assert fused_available(BAOptions(robust=None), torch.float32, cpu, t)
    assert not fused_available(BAOptions(robust="huber"), torch.float32, cpu, t)
    assert not fused_available(BAOptions(), torch.float64, cpu, t)
    assert not fused_available(BAOptions(), torch.float32, torch.device("cuda"), t)
    assert not fused_available(BAOptions(compiled=False), torch.float32, cpu, t)
    assert not fused_available(BAOptions(), torch.float32, cpu, torch.zeros(2, requires_grad=True))
    assert np.float32(ba_problem.FUSED_MIN_CONF) > 0  # representable: the zeroing threshold is not itself denormal


_SAME_CODE = """
import hashlib, sys, numpy as np
from pvslam_core.geometry import ba_kernels as k
rng = np.random.default_rng(0)
E, N, P, m = 6, 3, 500, 4
f = np.float32
R = np.tile(np.eye(3, dtype=f), (E, 1, 1)) + rng.normal(0, 0.01, (E, 3, 3)).astype(f)
t = rng.normal(0, 0.1, (E, 3)).astype(f)
d = rng.uniform(0.1, 1.0, (N, P)).astype(f)
rx, ry = rng.uniform(-0.5, 0.5, P).astype(f), rng.uniform(-0.4, 0.4, P).astype(f)
tgt, cf = rng.uniform(0, 300, (E, 2, P)).astype(f), rng.uniform(0, 1, (E, 2, P)).astype(f)
ls = np.array([0, 0, 1, 1], np.int64)
a = (R, t, d, np.arange(E) % N, rx, ry, tgt, cf, 300.0, 300.0, 160.0, 120.0, 0.2, 1.0, 1e-3, m, ls)
C, wd, acc, B = np.ones((2, P), f), np.zeros((2, P), f), np.empty((E, 28), f), np.empty((m, 6, P), f)
k.pass_blocks(*a, C, wd, acc)
k.pass_rows(*a, 1 / np.sqrt(C), B)
print(hashlib.md5(b"".join(x.tobytes() for x in (acc, C, wd, B))).hexdigest())
"""


def test_a_fresh_compile_and_the_cached_code_give_the_same_bits(tmp_path):
    """The first run after installing compiles the loops, later runs load them from the cache: both must compute
    the same bits (with helpers left to LLVM's inliner a cached caller summed in another order)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    runs = [subprocess.run([sys.executable, "-c", _SAME_CODE], env=env, capture_output=True, text=True, timeout=300)
            for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr
    assert any((tmp_path / "numba").rglob("*.nbi")), "the first run did not write the cache"
    assert runs[0].stdout.strip() == runs[1].stdout.strip()
