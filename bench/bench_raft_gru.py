"""Benchmark of the learned ``raft_gru`` frontend: speed at 320x240 with a per-stage profile, memory on a
long run, and ATE against the classical ``flow`` frontend on held-out synthetic seeds.

    python bench/bench_raft_gru.py --only ops                              # per network call, fp32 vs bf16
    python bench/bench_raft_gru.py --only speed --frames 120               # frames/s + profile (about 10 min)
    python bench/bench_raft_gru.py --only memory --long-frames 1000        # long run in a child process
    python bench/bench_raft_gru.py --only memory_frontend --set frontend.rounds=1   # steady state, no mapper
    python bench/bench_raft_gru.py --only memory_frontend --mf-stop 300 --mf-ba     # ... with the online BA
    python bench/bench_raft_gru.py --only ate --weights runs/rg/model_final.pth --seeds 200 201
    python bench/bench_raft_gru.py --quick                                 # a smoke run of every section

Speed.  Weights do not change the cost of a network call, but they decide which frames become keyframes, and a
random network's motion filter is meaningless; so without ``--weights`` every frame is made a keyframe candidate
(``keyframe_thresh`` 1e-4: the mapper's provisional-keyframe rule decides which stay) and the figures are an upper
bound of the per-frame work; ``memory_frontend`` gives the steady state.  Wall time on a shared machine depends on
the other jobs; the script prints the load average and each run's CPU seconds (whole process and the pipeline
thread) next to the wall time.  ``est fps`` = frames / max(pipeline-thread CPU, process CPU / cores): the rate on an
otherwise idle machine with that many cores.

Memory.  ``memory``: a separate process runs ``--long-frames`` frames of the driving loop through the pipeline and
samples RSS every 100 frames (the peak at 3000 frames extrapolated from the second half); it needs weights that
initialise the map (a map that never initialises keeps every keyframe).  ``memory_frontend``: the
frontend and frame graph without the mapper, keyframes at ground-truth poses (independent of the weights; also the
steady-state per-frame CPU, ``--mf-stop N`` for a short run).

Results go to ``--json`` (default runs/bench/results_raft_gru.json) with the commit of the measured code
(:mod:`bench.provenance`; refused without one).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance  # noqa: E402
from bench.rss import peak_rss_mb  # noqa: E402
RESULTS: dict = {}


def load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def generate(scenario: str, frames: int | None, seed: int = 0, width: int = 320, height: int = 240) -> Path:
    from pvslam_plugins.datasets.synthetic.generator import generate as gen

    return gen(scenario, None, num_frames=frames, width=width, height=height, seed=seed, progress=False)


def rg_overrides(weights: str | None, profile: str, extra: list[str] = ()) -> list[str]:
    ov = ['frontend.plugin="raft_gru"', f'frontend.profile="{profile}"']
    if weights:
        ov.append(f'frontend.weights="{weights}"')
    else:
        ov += ['frontend.weights="random"', "frontend.keyframe_thresh=0.0001"]
    return ov + list(extra)


def run(seq: Path, overrides: list[str], out: Path):
    """One pipeline run (no loop detector / VPS / point clouds: the frontend's cost is what is measured); returns
    ``(result, frontend or None)``."""
    import pvslam_plugins.frontends.raft_gru.frontend as F
    from pvslam_core.api import run_config

    made = []
    orig = F.RaftGruFrontend.__init__

    def init(self, *a, **k):
        orig(self, *a, **k)
        made.append(self)

    F.RaftGruFrontend.__init__ = init
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = run_config(None, overrides=[f'run.output_dir="{out.as_posix()}"', "run.progress=false",
                                              f'dataset.path="{seq.as_posix()}"', "outputs.ply=false",
                                              "outputs.plots=false", "outputs.panoptic_png=false", "vps.plugin=none",
                                              *overrides])
    finally:
        F.RaftGruFrontend.__init__ = orig
    return res, (made[-1] if made else None)


def summary(res, fe) -> dict:
    t = res.metrics["timing"]
    n = max(int(t["frames"]), 1)
    main = sum((t.get("stage_cpu_seconds") or {}).values())
    cpu = float(t.get("cpu_seconds") or main)
    cores = os.cpu_count() or 1
    d = {"frames": n, "keyframes": t.get("keyframes"), "wall_s": t.get("seconds"), "fps_wall": t.get("fps"),
         "cpu_s_process": cpu, "cpu_s_pipeline_thread": main, "cpu_ms_per_frame": 1000 * cpu / n,
         "est_fps": n / max(main, cpu / cores, 1e-9), "map_cpu_seconds": t.get("map_cpu_seconds"),
         "tracking": res.metrics.get("tracking"), "ate_pct": res.metrics.get("ate", {}).get("rmse_percent_of_path"),
         "threads": __import__("torch").get_num_threads()}
    if fe is not None:
        d["frontend_cpu_s"] = {k: round(v, 2) for k, v in fe.stats.cpu.items()}
        d["frontend_wall_s"] = {k: round(v, 2) for k, v in fe.stats.seconds.items()}
        d["frontend_counts"] = dict(fe.stats.counts)
        d["frontend_mb"] = fe.memory_bytes() / 2**20
    return d


def print_run(name: str, d: dict) -> None:
    print(f"  {name:<28} {d['frames']} frames, {d['keyframes']} keyframes: {d['fps_wall']:.2f} frames/s wall, "
          f"{d['cpu_ms_per_frame']:.0f} ms CPU/frame (process), est {d['est_fps']:.2f} frames/s idle, "
          f"ATE {d['ate_pct']}")
    if "frontend_cpu_s" in d:
        n = d["frames"]
        parts = ", ".join(f"{k} {1000 * v / n:.0f}" for k, v in d["frontend_cpu_s"].items() if v > 0)
        print(f"      frontend CPU ms/frame: {parts}; counts {d['frontend_counts']}")
    print(f"      mapper CPU s: {d['map_cpu_seconds']}")


SPEED_VARIANTS = ("flow", "fast", "fast_fp32", "droid")


def section_speed(out: Path, frames: int, weights: str | None, threads: list[int],
                  variants: list[str] = SPEED_VARIANTS, extra: list[str] = ()) -> None:
    import torch

    print(f"\n== speed at 320x240, driving_loop, {frames} frames (load {load()}) ==")
    seq = generate("driving_loop", frames)
    res_all = {}
    for th in threads:
        torch.set_num_threads(th)
        for key, name, ov in (("flow", "flow", ['frontend.plugin="flow"']),
                              ("fast", "raft_gru fast", rg_overrides(weights, "fast", extra)),
                              ("fast_fp32", "raft_gru fast fp32",
                               rg_overrides(weights, "fast", ['frontend.precision="fp32"', *extra])),
                              ("droid", "raft_gru droid", rg_overrides(weights, "droid", extra))):
            if key not in variants or (key == "droid" and th != threads[0]):
                continue
            before = load()
            res, fe = run(seq, ov + ["loop.plugin=none"], out)
            d = summary(res, fe)
            d["load_before"], d["load_after"] = before, load()
            res_all[f"{name} / {th} thread(s)"] = d
            print_run(f"{name} ({th} thr)", d)
    RESULTS["speed"] = res_all


def _cpu_ms(fn, reps: int) -> tuple[float, float]:
    """``(median thread-CPU ms, median wall ms)`` of ``fn()`` over ``reps`` calls after one warm-up call."""
    fn()
    cpu, wall = [], []
    for _ in range(reps):
        c, t = time.thread_time(), time.perf_counter()
        fn()
        cpu.append(1000 * (time.thread_time() - c))
        wall.append(1000 * (time.perf_counter() - t))
    return sorted(cpu)[reps // 2], sorted(wall)[reps // 2]


def section_ops(edges: int, reps: int) -> None:
    """Per network call at 320x240 (1/8: 30x40), one thread, random weights (weights do not change the cost): the
    frontend's stages in isolation, fp32 vs bf16 autocast, stored volume vs on-the-fly correlation."""
    import torch

    from pvslam_plugins.frontends.raft_gru.corr import CorrVolume, OnTheFlyCorr, coords_grid
    from pvslam_plugins.frontends.raft_gru.net import RaftGruNet, droid_motion

    torch.set_num_threads(1)
    torch.manual_seed(0)
    print(f"\n== per-call CPU at 320x240, 1 thread, {edges} edges per update (load {load()}) ==")
    model = RaftGruNet("droid").eval()
    img = torch.randint(0, 255, (1, 1, 3, 240, 320), dtype=torch.uint8)
    h, w = 30, 40
    fm = torch.randn(1, 4, 128, h, w)
    ii = torch.arange(edges) % 4
    jj = (ii + 1 + torch.arange(edges) // 4 % 3) % 4
    g = coords_grid(h, w)
    c1 = (g + torch.randn(1, edges, h, w, 2)).contiguous()
    net, inp = torch.randn(1, edges, 128, h, w).tanh(), torch.randn(1, edges, 128, h, w).relu()
    motion = droid_motion(g, c1, c1 + 0.5)
    rows = {}
    with torch.no_grad():
        for prec in ("fp32", "bf16"):
            ac = torch.autocast("cpu", dtype=torch.bfloat16, enabled=prec == "bf16")
            dt = torch.bfloat16 if prec == "bf16" else torch.float32

            def fnet():
                with ac:
                    model.features(img, "rgb", context=False)

            def cnet():
                with ac:
                    model.context(img, "rgb")

            vol = CorrVolume(fm[:, ii].to(dt), fm[:, jj].to(dt))
            otf = OnTheFlyCorr(fm.to(dt), ii, jj)
            corr = vol(c1.to(dt)).float()

            def build():
                CorrVolume(fm[:, ii].to(dt), fm[:, jj].to(dt))

            def lookup():
                vol(c1.to(dt))

            def lookup_otf():
                with ac:
                    otf(c1.to(dt))

            def update():
                with ac:
                    model.update(net, inp, corr, motion, ii, jj)

            for name, fn in (("fnet (1 frame)", fnet), ("cnet (1 frame)", cnet),
                             (f"volume build ({edges} edges)", build), (f"lookup volume ({edges} edges)", lookup),
                             (f"lookup on-the-fly ({edges} edges)", lookup_otf), (f"update ({edges} edges)", update)):
                c, t = _cpu_ms(fn, reps)
                rows[f"{name} {prec}"] = {"cpu_ms": c, "wall_ms": t}
                print(f"  {name:<34} {prec}: {c:8.1f} ms CPU  ({t:8.1f} ms wall)")
    RESULTS["ops"] = rows


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _long_child(frames: int, out: str, weights: str | None, profile: str, extra: list[str] = ()) -> None:
    """Separate process (its own peak RSS): feeds the frames itself and samples memory every 100 frames."""
    import torch

    from pvslam_core.background import read_ahead
    from pvslam_core.config import load_config
    from pvslam_core.pipeline import Pipeline
    from pvslam_core.registry import get_registry
    from pvslam_core.rundir import RunLog, init_run_dir, make_run_dir

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    seq = generate("driving_loop", frames)
    cfg = load_config(None, overrides=[f'dataset.path="{seq.as_posix()}"', "outputs.ply=false", "outputs.plots=false",
                                       "outputs.panoptic_png=false", "run.progress=false", "vps.plugin=none",
                                       f'run.output_dir="{Path(out).as_posix()}"',
                                       *rg_overrides(weights, profile, extra)])
    run_dir = make_run_dir(out, "long_raft_gru")
    init_run_dir(run_dir, cfg, get_registry(), {})
    samples = []
    t0, c0 = time.perf_counter(), time.process_time()
    with RunLog(run_dir, "INFO"):
        pipe = Pipeline(cfg, run_dir)
        pipe.start()
        for frame in read_ahead(pipe.dataset, cfg.pipeline.run.read_ahead):
            pipe.step(frame)
            if pipe.frames_done % 100 == 0:
                g, fe = pipe.mapper.graph, pipe.frontend
                samples.append({"frame": pipe.frames_done, "rss_mb": _rss_mb(), "keyframes": g.n,
                                "active_edges": g.num_edges, "retired_edges": g.num_retired,
                                "retired_mb": g.retired_bytes() / 2**20, "frontend_edges": len(fe.edge_ids()),
                                "frontend_mb": fe.memory_bytes() / 2**20,
                                "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0})
                print(json.dumps(samples[-1]), file=sys.stderr, flush=True)
        r = pipe.finish()
    print(json.dumps({"frames": pipe.frames_done, "peak_mb": peak_rss_mb(),
                      "samples": samples, "keyframes": r.metrics["timing"]["keyframes"],
                      "ate_pct": r.metrics.get("ate", {}).get("rmse_percent_of_path"),
                      "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}))


def section_memory(out: Path, frames: int, weights: str | None, profile: str, target_frames: int = 3000,
                   extra: list[str] = ()) -> None:
    print(f"\n== memory: {frames} frames of the driving loop at 320x240, raft_gru {profile} (load {load()}) ==")
    generate("driving_loop", frames)
    cmd = [sys.executable, __file__, "--long-child", str(frames), "--out", str(out), "--profile", profile]
    if weights:
        cmd += ["--weights", weights]
    for e in extra:
        cmd += ["--set", e]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        print(res.stderr[-3000:])
        RESULTS["memory"] = {"error": res.stderr[-2000:]}
        return
    d = json.loads(res.stdout.strip().splitlines()[-1])
    s = d["samples"]
    half = s[len(s) // 2:] or s
    xs = [p["frame"] for p in half]
    ys = [p["rss_mb"] for p in half]
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / max(sum((x - mx) ** 2 for x in xs), 1e-9)
    d["rss_slope_mb_per_1000_frames"] = 1000 * slope
    d["rss_extrapolated_mb"] = ys[-1] + slope * (target_frames - xs[-1])
    RESULTS["memory"] = d
    print(f"  {d['frames']} frames, {d['keyframes']} keyframes in {d['wall_s']:.0f} s wall / {d['cpu_s']:.0f} s CPU; "
          f"peak RSS {d['peak_mb']:.0f} MB; RSS grows {1000 * slope:.0f} MB per 1000 frames over the second half "
          f"-> about {d['rss_extrapolated_mb']:.0f} MB at {target_frames} frames (target < 4096 MB)")
    print("  frame   RSS MB  keyframes  active  retired  retired MB  frontend edges  frontend MB")
    for p in s:
        print(f"  {p['frame']:>5}  {p['rss_mb']:>7.0f}  {p['keyframes']:>9}  {p['active_edges']:>6}  "
              f"{p['retired_edges']:>7}  {p['retired_mb']:>10.1f}  {p['frontend_edges']:>14}  {p['frontend_mb']:>11.1f}")


def section_memory_frontend(frames: int, kf_every: int, window: int, neighbours: int, profile: str,
                            extra: list[str] = (), stop: int | None = None, ba: bool = False) -> None:
    """Steady-state memory of the frontend + frame graph without the mapper: every frame goes through the motion
    filter, every ``kf_every``-th becomes a keyframe placed at its ground-truth pose (inverse depth from the
    ground truth at 1/8), edges to the previous ``neighbours`` keyframes both ways, ``rounds`` observes of the active
    edges (no BA between them: same cost), edges of keyframes older than ``window`` retired (what the mapper does).
    ``stop``: process only the first ``stop`` frames of the ``frames``-frame sequence.  ``ba``: after each observe
    the dense BA the mapper would run (``pvslam_core.geometry.ba.dense_ba``, configs/raft_gru.toml's optimizer: 2
    iterations, no robust kernel, the learned damping; every keyframe of the window free but the oldest), timed as
    stage ``ba``: the per-frame CPU then includes the online BA.  Independent of the weights (a random
    network's flow cannot initialise the mapper on a realistically slow sequence), RSS sampled every
    100 frames on stderr as it runs."""
    import torch
    import torch.nn.functional as F

    from pvslam_core.slam.graph import FrameGraph
    from pvslam_core.types import Frame
    from pvslam_plugins.datasets.synthetic.reader import SyntheticSequence
    from pvslam_plugins.frontends.raft_gru.config import RaftGruConfig
    from pvslam_plugins.frontends.raft_gru.frontend import RaftGruFrontend

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    seq = SyntheticSequence(generate("driving_loop", frames))
    kw = dict(x.split("=", 1) for x in extra)
    cfg = RaftGruConfig(weights="random", profile=profile, dynamic={"enabled": False},
                        **{k.removeprefix("frontend."): json.loads(v) for k, v in kw.items()})
    fe = RaftGruFrontend(cfg)
    intr = seq.intrinsics
    g = FrameGraph(intr.height // 8, intr.width // 8, intr.scaled(1 / 8).vector(torch.float32), capacity=64)
    g.add_listener(fe)
    print(f"\n== frontend + graph memory, {frames} frames, keyframe every {kf_every}, window {window}, {profile} "
          f"(load {load()}) ==", flush=True)
    from pvslam_core.geometry.ba import dense_ba

    ba_cpu = 0.0
    samples, t0, c0 = [], time.perf_counter(), time.process_time()
    for i in range(min(frames, stop or frames)):
        a = seq.arrays(i, ("depth",))
        img = torch.from_numpy(a["rgb"].transpose(2, 0, 1).copy())
        fr = Frame(index=i, timestamp=i / 12.0, image=img, intrinsics=intr)
        fe.track(fr, None)
        if i % kf_every == 0:
            depth = torch.from_numpy(a["depth"])[None, None]
            disp = F.avg_pool2d(torch.where(depth > 0, 1.0 / depth.clamp(min=1e-3), torch.zeros_like(depth)), 8)[0, 0]
            pose = torch.as_tensor(seq.poses[i], dtype=torch.float64)
            k = g.add_keyframe(i, i / 12.0, pose, disp.clamp(min=1e-3))
            fe.add_keyframe(int(g.ids[k]), fr, None)
            prev = torch.arange(max(0, k - neighbours), k)
            g.add_edges(torch.cat([prev, torch.full_like(prev, k)]), torch.cat([torch.full_like(prev, k), prev]))
            old = (g.ii < k - window) | (g.jj < k - window)
            g.retire_edges(old)
            for _ in range(fe.rounds):
                obs = fe.observe(g, g.ii.clone(), g.jj.clone())
                if ba and g.n > 1:
                    cb = time.thread_time()
                    live = torch.unique(torch.cat([g.ii, g.jj]))
                    free = torch.zeros(g.n, dtype=torch.bool)
                    free[live] = True
                    free[live.min()] = False  # the window's oldest keyframe fixes the gauge
                    dense_ba(g, obs, free, iters=2, robust=None)
                    ba_cpu += time.thread_time() - cb
            g.record_observations(obs)
        if (i + 1) % 100 == 0:
            samples.append({"frame": i + 1, "rss_mb": _rss_mb(), "keyframes": g.n, "active_edges": g.num_edges,
                            "retired_edges": g.num_retired, "retired_mb": g.retired_bytes() / 2**20,
                            "frontend_edges": len(fe.edge_ids()), "frontend_mb": fe.memory_bytes() / 2**20,
                            "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0})
            print(json.dumps(samples[-1]), file=sys.stderr, flush=True)
    n = min(frames, stop or frames)
    cpu = time.process_time() - c0
    d = {"frames": frames, "processed": n, "peak_mb": peak_rss_mb(),
         "samples": samples, "rounds": fe.rounds, "frontend_cpu_s": dict(fe.stats.cpu),
         "frontend_counts": dict(fe.stats.counts), "cpu_s": cpu, "ba_cpu_s": ba_cpu, "load_end": load(),
         "cpu_ms_per_frame": 1000 * cpu / n, "fps_1core": n / cpu}
    RESULTS["memory_frontend"] = d
    print(f"  peak RSS {d['peak_mb']:.0f} MB; {1000 * cpu / n:.0f} ms CPU per frame = {n / cpu:.2f} frames/s on one "
          f"core (load {load()}); frontend CPU ms/frame: "
          + ", ".join(f"{k} {1000 * v / n:.0f}" for k, v in fe.stats.cpu.items() if v > 0)
          + (f"; ba {1000 * ba_cpu / n:.0f}" if ba else ""), flush=True)


def section_ate(out: Path, weights: str | None, seeds: list[int], scenarios: list[str], frames: int,
                profile: str, extra: list[str] = ()) -> None:
    import torch

    torch.set_num_threads(1)
    print(f"\n== ATE raft_gru ({weights or 'random'}, {profile}) vs flow, held-out seeds {seeds}, {frames} frames "
          f"(load {load()}) ==")
    rows = []
    for scen in scenarios:
        for seed in seeds:
            seq = generate(scen, frames, seed)
            row = {"scenario": scen, "seed": seed}
            for name, ov in (("flow", ['frontend.plugin="flow"']),
                             ("raft_gru", rg_overrides(weights, profile, extra))):
                res, _ = run(seq, ov, out)
                a = res.metrics.get("ate", {})
                row[name] = a.get("rmse_percent_of_path", float("nan"))
                row[f"{name}_fps"] = res.metrics["timing"]["fps"]
                row[f"{name}_keyframes"] = res.metrics["timing"]["keyframes"]
            rows.append(row)
            print(f"  {scen:<22} seed {seed}: flow {row['flow']:.3f} %  raft_gru {row['raft_gru']:.3f} %  "
                  f"(keyframes {row['flow_keyframes']} / {row['raft_gru_keyframes']})")
    RESULTS["ate"] = rows
    wins = sum(1 for r in rows if r["raft_gru"] < r["flow"])
    print(f"  raft_gru better on {wins} of {len(rows)} sequences")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", choices=["ops", "speed", "memory", "memory_frontend", "ate"])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--weights", help="raft_gru weights (catalogue name or path); default: random")
    ap.add_argument("--profile", default="fast", choices=["fast", "droid"])
    ap.add_argument("--frames", type=int, default=120, help="frames of the speed run")
    ap.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--variants", nargs="*", default=list(SPEED_VARIANTS), choices=SPEED_VARIANTS,
                    help="runs of the speed section")
    ap.add_argument("--set", dest="extra", action="append", default=[], metavar="KEY=VALUE",
                    help="extra config override for every raft_gru run (repeatable), e.g. frontend.rounds=1")
    ap.add_argument("--ops-edges", type=int, default=12, help="edges per update call in the ops section")
    ap.add_argument("--ops-reps", type=int, default=7)
    ap.add_argument("--long-frames", type=int, default=1000)
    ap.add_argument("--kf-every", type=int, default=3, help="memory_frontend: a keyframe every N frames")
    ap.add_argument("--mf-stop", type=int, help="memory_frontend: stop after this many frames")
    ap.add_argument("--mf-ba", action="store_true", help="memory_frontend: run the online dense BA after each observe")
    ap.add_argument("--seeds", type=int, nargs="*", default=[200])
    ap.add_argument("--scenarios", nargs="*", default=["driving_loop", "moving_vehicles", "indoor_handheld",
                                                       "busy_street"])
    ap.add_argument("--ate-frames", type=int, default=150)
    ap.add_argument("--out", default=str(Path("/tmp") / "bench_raft_gru"))
    ap.add_argument("--json", default=str(provenance.RESULTS_DIR / "results_raft_gru.json"),
                    help="result file (not into bench/)")
    ap.add_argument("--long-child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.long_child:
        _long_child(args.long_child, args.out, args.weights, args.profile, args.extra)
        return
    try:
        prov = provenance.check(args.json)
    except provenance.ProvenanceError as exc:
        sys.exit(provenance.fail(exc))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sections = args.only or ["ops", "speed", "memory", "ate"]
    RESULTS["machine"] = {"cores": os.cpu_count(), "load_start": load(), "weights": args.weights or "random"}
    if "ops" in sections:
        section_ops(args.ops_edges, 3 if args.quick else args.ops_reps)
    if "speed" in sections:
        section_speed(out, 30 if args.quick else args.frames, args.weights, args.threads, args.variants, args.extra)
    if "memory" in sections:
        section_memory(out, 200 if args.quick else args.long_frames, args.weights, args.profile, extra=args.extra)
    if "memory_frontend" in sections:
        section_memory_frontend(200 if args.quick else args.long_frames, args.kf_every, 10, 3, args.profile,
                                args.extra, args.mf_stop, args.mf_ba)
    if "ate" in sections:
        section_ate(out, args.weights, args.seeds, args.scenarios[:1] if args.quick else args.scenarios,
                    40 if args.quick else args.ate_frames, args.profile, args.extra)
    RESULTS["machine"]["load_end"] = load()
    provenance.write_json(args.json, RESULTS, prov)
    print(f"\nresults: {args.json}")


if __name__ == "__main__":
    main()
