"""Dense BA benchmark: time per Gauss-Newton iteration as keyframes / edges / pixels grow, and a side-by-side
with ``scipy.optimize.least_squares`` (trf + jac_sparsity) on the same synthetic problem.

    python bench/bench_ba.py [--device cpu|cuda] [--threads N] [--quick]

Prints two tables (and writes them as markdown with ``--out FILE``).  Whole run: well under 2 minutes on CPU.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pvslam_core.geometry.ba import dense_ba, weighted_cost
from pvslam_core.geometry.lie import se3_exp, se3_mul
from pvslam_core.geometry.projective import edge_transforms, project_points
from pvslam_core.geometry.testing import make_problem, perturb


def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def time_iteration(n: int, h: int, w: int, device: str, reps: int = 5, radius: int = 2, dtype=None) -> dict:
    pr = make_problem(n=n, h=h, w=w, seed=0, noise=0.2, radius=radius)
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(n, dtype=torch.bool)
    free[:2] = False
    obs = pr.obs()
    obs = type(obs)(obs.ii.to(device), obs.jj.to(device), obs.target.to(device), obs.weight.to(device))
    times, cpu = [], []
    for r in range(reps + 1):
        g = pr.graph(p0, d0, device=device)
        _sync(device)
        t, c = time.perf_counter(), time.process_time()
        dense_ba(g, obs, free.to(device), iters=2, dtype=dtype)
        _sync(device)
        if r > 0:  # the first run warms up
            times.append((time.perf_counter() - t) / 2)
            cpu.append((time.process_time() - c) / 2)
    E = len(pr.ii)
    ms = 1e3 * min(times)
    cpu_ms = 1e3 * min(cpu)
    return {"keyframes": n, "free": n - 2, "edges": E, "pixels": h * w, "edge_px": E * h * w, "ms": ms,
            "cpu_ms": cpu_ms, "us_per_kpx": 1e3 * cpu_ms / (E * h * w / 1000.0)}


# ----------------------------------------------------------------------------------------------- scipy
def scipy_comparison(n: int = 5, h: int = 15, w: int = 20, iters: int = 20) -> dict:
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    pr = make_problem(n=n, h=h, w=w, seed=5, noise=0.3)
    p0, d0 = perturb(pr, fixed=(0, 1), rot=0.01, trans=0.03, disp_rel=0.15)
    fixed = (0, 1)
    free_idx = [k for k in range(n) if k not in fixed]
    F, P, E = len(free_idx), h * w, len(pr.ii)
    ii, jj = pr.ii, pr.jj
    target = pr.target.double().reshape(E, 2, P).transpose(1, 2)  # [E, P, 2]
    sw = pr.weight.double().reshape(E, 2, P).transpose(1, 2).sqrt()
    intr = pr.intr.double()

    def unpack(x):
        xi = torch.from_numpy(x[: 6 * F]).reshape(F, 6)
        poses = p0.clone()
        poses[free_idx] = se3_mul(p0[free_idx], se3_exp(-xi))  # same retraction as the BA
        d = torch.from_numpy(x[6 * F:]).reshape(n, P)
        return poses, d

    def fun(x):
        poses, d = unpack(x)
        R, t = edge_transforms(poses, ii, jj)
        out = project_points(R, t, d[ii], intr, h, w, 0.2)
        r = target - torch.stack([out["u"], out["v"]], -1)
        return (sw * out["valid"].unsqueeze(-1) * r).reshape(-1).numpy()

    # sparsity: residual (e, p, c) depends on the 6 pose params of ii[e], jj[e] (if free) and the depth (ii[e], p)
    nres, nvar = E * P * 2, 6 * F + n * P
    S = lil_matrix((nres, nvar), dtype=np.int8)
    slot = {k: s for s, k in enumerate(free_idx)}
    rows = np.arange(P * 2)
    for e in range(E):
        base = e * P * 2
        for k in (int(ii[e]), int(jj[e])):
            if k in slot:
                S[base:base + P * 2, 6 * slot[k]:6 * slot[k] + 6] = 1
        cols = 6 * F + int(ii[e]) * P + rows // 2
        S[base + rows, cols] = 1
    x0 = np.concatenate([np.zeros(6 * F), d0.double().reshape(-1).numpy()])
    # same constraint as the BA: inverse depth >= 1e-3 (the BA clamps), poses unbounded
    lb = np.concatenate([np.full(6 * F, -np.inf), np.full(n * P, 1e-3)])
    x0 = np.maximum(x0, lb + 1e-9)
    t, c0 = time.perf_counter(), time.process_time()
    res = least_squares(fun, x0, jac_sparsity=S.tocsr(), method="trf", tr_solver="lsmr", x_scale="jac",
                        bounds=(lb, np.full(nvar, np.inf)), ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=200)
    t_scipy, c_scipy = time.perf_counter() - t, time.process_time() - c0
    cost_scipy = float(2 * res.cost)  # scipy reports 0.5 * sum f^2

    g = pr.graph(p0, d0)
    free = torch.ones(n, dtype=torch.bool)
    free[list(fixed)] = False
    obs = pr.obs()
    t, c0 = time.perf_counter(), time.process_time()
    rep = dense_ba(g, obs, free, iters=iters, lm=1e-6, ep=1e-6, eta=1e-6)
    t_ba, c_ba = time.perf_counter() - t, time.process_time() - c0
    cost_ba = weighted_cost(g, obs)
    return {"keyframes": n, "edges": E, "pixels": P, "unknowns": nvar, "residuals": nres,
            "scipy_s": t_scipy, "scipy_cpu": c_scipy, "ba_cpu": c_ba, "scipy_nfev": int(res.nfev), "scipy_cost": cost_scipy,
            "ba_s": t_ba, "ba_iters": rep.iterations, "ba_cost": cost_ba, "cost_start": rep.cost_before}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: leave torch's default)")
    ap.add_argument("--dtype", default="auto", choices=["auto", "float32", "float64"])
    ap.add_argument("--quick", action="store_true", help="fewer sizes")
    ap.add_argument("--out", default="", help="also write the tables as markdown to this file")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = {"auto": None, "float32": torch.float32, "float64": torch.float64}[args.dtype]
    lines = []

    def emit(s=""):
        print(s, flush=True)
        lines.append(s)

    dev_name = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"cpu ({torch.get_num_threads()} threads)"
    emit(f"## Dense BA: time per Gauss-Newton iteration ({dev_name}, torch {torch.__version__}, dtype {args.dtype})")
    emit()
    emit("| keyframes | free poses | edges | pixels/kf | edges x pixels | wall ms / iteration | CPU ms / iteration "
         "| CPU us per 1k edge-pixels |")
    emit("|---:|---:|---:|---:|---:|---:|---:|---:|")
    sizes = [(4, 30, 40), (8, 30, 40), (16, 30, 40), (32, 30, 40), (8, 60, 80), (8, 120, 160)]
    if not args.quick:
        sizes += [(64, 30, 40), (16, 60, 80)]
    for n, h, w in sizes:
        r = time_iteration(n, h, w, args.device, dtype=dtype)
        emit(f"| {r['keyframes']} | {r['free']} | {r['edges']} | {h}x{w} | {r['edge_px']} | {r['ms']:.2f} | "
             f"{r['cpu_ms']:.2f} | {r['us_per_kpx']:.0f} |")
    if args.device == "cpu":
        emit()
        emit("## Same problem: dense BA vs scipy.optimize.least_squares (trf, lsmr, jac_sparsity, 2-point FD, disp >= 1e-3)")
        emit()
        c = scipy_comparison()
        emit("| keyframes | edges | pixels/kf | unknowns | residuals | start cost | scipy cost | BA cost | "
             "scipy wall / CPU | BA wall / CPU | speed-up wall / CPU |")
        emit("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        emit(f"| {c['keyframes']} | {c['edges']} | {c['pixels']} | {c['unknowns']} | {c['residuals']} | "
             f"{c['cost_start']:.2f} | {c['scipy_cost']:.6f} | {c['ba_cost']:.6f} | {c['scipy_s']:.2f} s / "
             f"{c['scipy_cpu']:.2f} s ({c['scipy_nfev']} evals) | {c['ba_s'] * 1e3:.0f} / {c['ba_cpu'] * 1e3:.0f} ms "
             f"({c['ba_iters']} it) | {c['scipy_s'] / c['ba_s']:.0f}x / {c['scipy_cpu'] / max(c['ba_cpu'], 1e-9):.0f}x |")
        rel = abs(c["ba_cost"] - c["scipy_cost"]) / max(c["scipy_cost"], 1e-12)
        emit()
        emit(f"relative final-cost difference: {rel:.2e}")
    if args.out:
        with open(args.out, "w") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
