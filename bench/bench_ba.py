"""Dense BA benchmark: time per Gauss-Newton iteration as keyframes / edges / pixels grow, a side-by-side
with ``scipy.optimize.least_squares`` (trf + jac_sparsity) on the same synthetic problem, and the peak memory of
one large global-BA-sized problem with chunked vs unchunked linearisation (``max_chunk_pixels``), and the CPU time of
the loop closure's Sim(3) pose graph against its number of keyframes (with the closed-form Sim(3) ``W`` matrix and
with the 6x6 matrix exponential it replaced).

    python bench/bench_ba.py [--device cpu|cuda] [--threads N] [--quick] [--mem-keyframes N] [--no-memory]
    python bench/bench_ba.py --only-pose-graph        # the pose-graph table alone (~1 minute)

Prints three tables (and writes them as markdown with ``--out FILE``).  Whole run: about 2 minutes on CPU.
The memory table runs each configuration in a fresh subprocess (its own peak RSS: :func:`bench.rss.peak_rss_mb`).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
import tempfile
import time
from dataclasses import fields

import numpy as np
import torch

from pvslam_core.geometry.ba import BAOptions, dense_ba, weighted_cost
from pvslam_core.geometry.lie import se3_exp, se3_mul
from pvslam_core.geometry.projective import edge_transforms, project_points
from pvslam_core.geometry.testing import SyntheticBAProblem, drifted_loop, make_problem, perturb

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance  # noqa: E402
from bench.rss import peak_rss_mb  # noqa: E402


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
    rep = dense_ba(g, obs, free, iters=iters, lm=1e-6, ep=1e-6, depth_damping=1e-6)
    t_ba, c_ba = time.perf_counter() - t, time.process_time() - c0
    cost_ba = weighted_cost(g, obs)
    return {"keyframes": n, "edges": E, "pixels": P, "unknowns": nvar, "residuals": nres,
            "scipy_s": t_scipy, "scipy_cpu": c_scipy, "ba_cpu": c_ba, "scipy_nfev": int(res.nfev), "scipy_cost": cost_scipy,
            "ba_s": t_ba, "ba_iters": rep.iterations, "ba_cost": cost_ba, "cost_start": rep.cost_before}


# ----------------------------------------------------------------------------------------------- memory
NO_CHUNKING = 10**12  # max_chunk_pixels larger than any problem: one chunk, every per-pixel tensor at once


def pose_graph_timing(sizes=(50, 150, 450, 900), reps: int = 2) -> list[dict]:
    """CPU seconds of one ``sim3_pose_graph`` solve (25 iterations at most, the loop BA's setting) per size, with the
    closed-form ``W`` and with the matrix-exponential one (``expm([[M, I], [0, 0]])``, the previous code)."""
    import pvslam_core.geometry.lie as lie
    from pvslam_core.geometry.lie import hat
    from pvslam_core.geometry.pose_graph import sim3_pose_graph

    def W_expm(phi, sigma):
        shape = phi.shape[:-1]
        I3 = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(shape + (3, 3))
        G = torch.zeros(shape + (6, 6), dtype=phi.dtype, device=phi.device)
        G[..., :3, :3] = hat(phi) + sigma[..., None] * I3
        G[..., :3, 3:] = I3
        return torch.linalg.matrix_exp(G)[..., :3, 3:]

    closed = lie._sim3_W
    rows = []
    for n in sizes:
        # a lap of n keyframes (30 m radius), 0.1 % scale drift and 0.001 rad yaw drift per keyframe: a closure
        prob = drifted_loop(n, radius=30, rate=0.999, yaw_drift=0.001).args()
        row = {"keyframes": n}
        for name, fn in (("closed", closed), ("expm", W_expm)):
            lie._sim3_W = fn
            try:
                best = float("inf")
                for _ in range(reps):
                    t0 = time.process_time()
                    res = sim3_pose_graph(*prob, iters=25)
                    best = min(best, time.process_time() - t0)
            finally:
                lie._sim3_W = closed
            row[name] = best
            row[name + "_cost"] = (res.cost_before, res.cost_after, res.iterations)
        rows.append(row)
    return rows


def _n_chunks(pr: SyntheticBAProblem, free: torch.Tensor, mcp: int) -> int:
    """Chunks dense_ba forms for this problem (default depth_free: every source keyframe of an edge)."""
    from pvslam_core.geometry.ba_schur import plan_chunks

    n = pr.poses.shape[0]
    pose_map = torch.full((n,), -1, dtype=torch.int64)
    pose_map[free] = torch.arange(int(free.sum()))
    src = torch.unique(pr.ii)
    src_map = torch.full((n,), -1, dtype=torch.int64)
    src_map[src] = torch.arange(len(src))
    h, w = pr.shape
    return len(plan_chunks(pr.ii, pr.jj, pose_map, src_map[pr.ii], len(src), int(free.sum()), h * w, mcp))


def _memory_make(path: str, n: int, radius: int) -> None:
    """Subprocess body: build and save the large problem (its own peak RSS stays out of the measured processes)."""
    pr = make_problem(n=n, h=30, w=40, seed=0, noise=0.2, radius=radius, trajectory="loop")
    p0, d0 = perturb(pr, fixed=(0, 1))
    free = torch.ones(n, dtype=torch.bool)
    free[:2] = False
    torch.save({"problem": {f.name: getattr(pr, f.name) for f in fields(pr)}, "p0": p0, "d0": d0, "free": free},
               path)


def _memory_child(path: str, mcp: int, iters: int, reps: int) -> None:
    """Subprocess body: load the problem, warm up on a tiny one, run dense_ba; print one JSON line."""
    data = torch.load(path)
    pr = SyntheticBAProblem(**data["problem"])
    p0, d0, free = data["p0"], data["d0"], data["free"]
    small = make_problem(n=4)
    dense_ba(small.graph(), small.obs(), torch.tensor([False, True, True, True]), iters=1, max_chunk_pixels=mcp)
    obs = pr.obs()
    base = peak_rss_mb()
    times, rep = [], None
    for _ in range(reps):
        g = pr.graph(p0, d0)
        t = time.perf_counter()
        rep = dense_ba(g, obs, free, iters=iters, max_chunk_pixels=mcp)
        times.append((time.perf_counter() - t) / iters)
        del g
    h, w = pr.shape
    print(json.dumps({"base_mb": base, "peak_mb": peak_rss_mb(), "s_per_iter": min(times), "cost": rep.cost_after,
                      "rejected": rep.rejected, "chunks": _n_chunks(pr, free, mcp), "edges": len(pr.ii),
                      "pixels": h * w}), flush=True)


def memory_comparison(n: int = 400, radius: int = 3, iters: int = 2, reps: int = 2, threads: int = 0,
                      budgets=(None, 500_000, NO_CHUNKING)) -> dict:
    """Peak RSS and time per iteration (best of ``reps`` runs of ``iters``) of one large 30x40 problem (a loop of
    ``n`` keyframes, edges ``|i - j| <= radius`` both ways), each ``max_chunk_pixels`` in ``budgets`` (None:
    dense_ba's default) in a fresh process."""
    default = BAOptions().max_chunk_pixels
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    me = [sys.executable, os.path.abspath(__file__), "--threads", str(threads)]

    def child(args):
        res = subprocess.run(me + args, capture_output=True, text=True, env=env)
        if res.returncode != 0:
            raise RuntimeError(f"bench child {args[:2]} failed ({res.returncode}):\n{res.stderr[-2000:]}")
        return res.stdout

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "problem.pt")
        child(["--memory-make", path, "--mem-keyframes", str(n), "--mem-radius", str(radius)])
        for mcp in budgets:
            mcp = default if mcp is None else int(mcp)
            r = json.loads(child(["--memory-child", path, "--mcp", str(mcp), "--mem-iters", str(iters),
                                  "--mem-reps", str(reps)]).strip().splitlines()[-1])
            r["mcp"], r["is_default"] = mcp, mcp == default
            rows.append(r)
    E, P = rows[0]["edges"], rows[0]["pixels"]
    return {"keyframes": n, "free": n - 2, "edges": E, "pixels": P, "edge_px": E * P, "rows": rows}


def print_pose_graph(rows: list[dict], quiet: bool = False) -> list[str]:
    lines = [f"## Sim(3) pose graph of a loop closure: CPU s per solve (best of 2; {torch.get_num_threads()} threads)", "",
             "| keyframes | closed-form W | matrix-exponential W (before) | speed-up | cost before -> after, iterations |",
             "|---:|---:|---:|---:|---|"]
    for r in rows:
        cb, ca, it = r["closed_cost"]
        lines.append(f"| {r['keyframes']} | {r['closed']:.3f} | {r['expm']:.3f} | {r['expm'] / max(r['closed'], 1e-9):.1f}x "
                     f"| {cb:.4g} -> {ca:.3g}, {it} |")
    if not quiet:
        print("\n".join(lines))
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: leave torch's default)")
    ap.add_argument("--dtype", default="auto", choices=["auto", "float32", "float64"])
    ap.add_argument("--quick", action="store_true", help="fewer sizes")
    ap.add_argument("--out", default="", help="also write the tables as markdown to this file (with the commit of "
                    "the measured code; refused without one; not into bench/)")
    ap.add_argument("--mem-keyframes", type=int, default=400, help="keyframes of the memory problem (radius 3: "
                    "about 6 edges per keyframe)")
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory table")
    ap.add_argument("--only-pose-graph", action="store_true", help="only the Sim(3) pose-graph table")
    ap.add_argument("--mem-radius", type=int, default=3, help=argparse.SUPPRESS)
    ap.add_argument("--memory-make", default="", help=argparse.SUPPRESS)
    ap.add_argument("--memory-child", default="", help=argparse.SUPPRESS)
    ap.add_argument("--mcp", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--mem-iters", type=int, default=2, help=argparse.SUPPRESS)
    ap.add_argument("--mem-reps", type=int, default=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.memory_make:
        _memory_make(args.memory_make, args.mem_keyframes, args.mem_radius)
        return
    if args.memory_child:
        _memory_child(args.memory_child, args.mcp, args.mem_iters, args.mem_reps)
        return
    prov = None
    if args.out:
        try:
            prov = provenance.check(args.out)
        except provenance.ProvenanceError as exc:
            sys.exit(provenance.fail(exc))
    dtype = {"auto": None, "float32": torch.float32, "float64": torch.float64}[args.dtype]
    if args.only_pose_graph:
        print_pose_graph(pose_graph_timing())
        return
    if args.device == "cpu" and not args.no_memory:  # measured first (printed last): this process is still small
        m = memory_comparison(n=args.mem_keyframes, radius=args.mem_radius, threads=args.threads)
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
    if args.device == "cpu" and not args.no_memory:
        emit()
        emit(f"## Peak memory: one large problem ({m['keyframes']} keyframes, {m['free']} free poses, {m['edges']} "
             f"edges, 30x40, {m['edge_px']} edge-pixels), each setting in a fresh process (its own peak RSS; "
             f"time: best of 2 runs of 2 iterations)")
        emit()
        emit("| max_chunk_pixels | chunks | peak RSS MB | RSS before BA MB | BA peak above it MB | s / iteration | "
             "final cost |")
        emit("|---:|---:|---:|---:|---:|---:|---:|")
        for r in m["rows"]:
            name = "no chunking" if r["mcp"] >= NO_CHUNKING else f"{r['mcp']:,}"
            name += " (default)" if r["is_default"] else ""
            emit(f"| {name} | {r['chunks']} | {r['peak_mb']:.0f} | {r['base_mb']:.0f} | "
                 f"{r['peak_mb'] - r['base_mb']:.0f} | {r['s_per_iter']:.3f} | {r['cost']:.2f}"
                 f"{' (rejected)' if r['rejected'] else ''} |")
    if args.device == "cpu":
        emit()
        for line in print_pose_graph(pose_graph_timing((50, 150, 450) if args.quick else (50, 150, 450, 900)), quiet=True):
            emit(line)
    if args.out:
        provenance.write_text(args.out, "\n".join(lines) + "\n", prov)


if __name__ == "__main__":
    main()
