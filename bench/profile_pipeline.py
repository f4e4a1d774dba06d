"""CPU profile of one pipeline run: per-stage CPU seconds and the top functions of the pipeline thread.

    OMP_NUM_THREADS=1 python bench/profile_pipeline.py                          # default driving loop, 200 frames
    OMP_NUM_THREADS=1 python bench/profile_pipeline.py --frames 0 --no-profile  # whole sequence, accuracy too
    OMP_NUM_THREADS=1 python bench/profile_pipeline.py --config configs/kitti.toml \
        --set 'dataset.path="../shared/data/kitti-odometry"' --set 'dataset.resize=[1226, 370]'

On a shared machine wall-clock time says little; ``time.process_time`` (CPU seconds of this process, all its
threads) does not depend on what else runs.  The function table (``--profile``) is the pipeline thread's own CPU
(``time.thread_time``): with the process clock, a call on that thread would be charged with what the other threads
(the flow worker, the writers) burn while it runs or waits.  Those threads are not in the table; their CPU is the
process's minus the pipeline thread's (``stage_cpu_seconds``).  A profiled run is slower, and code that calls into
threaded libraries (OpenCV's pool) can read several times larger in the table than a wall-clock timing of it: time a
suspect with a wall clock before working on it.  Evaluation runs after the timed part and is reported apart.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance  # noqa: E402
from bench.rss import peak_rss_mb  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=None, help="config file (default: the built-in default)")
    ap.add_argument("--set", action="append", default=[], dest="overrides", help="KEY=VALUE override (repeatable)")
    ap.add_argument("--frames", type=int, default=200, help="run.max_frames (0: the whole sequence)")
    ap.add_argument("--no-profile", action="store_true", help="no cProfile (its overhead is ~10-20 %%)")
    ap.add_argument("--top", type=int, default=35, help="functions listed by cumulative CPU time")
    ap.add_argument("--out", default=None, help="folder for the run directory (default: a temporary folder)")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file (with the commit of the "
                    "measured code; refused without one; not into bench/)")
    args = ap.parse_args()
    prov = None
    if args.json:
        try:
            prov = provenance.check(args.json)
        except provenance.ProvenanceError as exc:
            sys.exit(provenance.fail(exc))

    t_imp = time.process_time()
    from pvslam_core.config import load_config
    from pvslam_core.pipeline import Pipeline
    from pvslam_core.registry import get_registry
    from pvslam_core.rundir import RunLog, init_run_dir, make_run_dir

    out = Path(args.out or tempfile.mkdtemp(prefix="pvslam-prof-"))
    ov = [f'run.output_dir="{out.as_posix()}"', "run.progress=false", "outputs.plots=false", *args.overrides]
    if args.frames:
        ov.append(f"run.max_frames={args.frames}")
    cfg = load_config(args.config, overrides=ov)
    imports_cpu = time.process_time() - t_imp
    run_dir = make_run_dir(cfg.pipeline.run.output_dir, cfg.pipeline.run.name)
    init_run_dir(run_dir, cfg, get_registry(), {})
    prof = None if args.no_profile else cProfile.Profile(time.thread_time)  # the pipeline thread's own CPU
    with RunLog(run_dir, "INFO"):
        pipe = Pipeline(cfg, run_dir)
        eval_enabled = cfg.pipeline.evaluation.enabled
        cfg.pipeline.evaluation.enabled = False  # evaluated below, outside the timed part
        c0, w0 = time.process_time(), time.perf_counter()
        if prof is not None:
            prof.enable()
        res = pipe.run()
        if prof is not None:
            prof.disable()
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        metrics = {}
        if eval_enabled:
            from pvslam_core.api import evaluate_run_dir

            cfg.pipeline.evaluation.enabled = True
            metrics = evaluate_run_dir(run_dir)
    figures = _figures(res.metrics, imports_cpu, cpu, wall, run_dir, metrics, getattr(pipe, "frontend", None))
    print(json.dumps(figures, indent=1))
    if prof is not None:
        s = io.StringIO()
        st = pstats.Stats(prof, stream=s)
        st.sort_stats("cumulative").print_stats(args.top)
        st.sort_stats("tottime").print_stats(args.top)
        print(s.getvalue())
    if args.json:
        provenance.write_json(args.json, figures, prov)


def _figures(run_metrics: dict, imports_cpu: float, cpu: float, wall: float, run_dir: Path, metrics: dict,
             frontend) -> dict:
    """The printed figures: the run's timing per frame and per stage, its tracking counters and, when evaluated,
    its accuracy; the frontend's own counters when it has them."""
    t = run_metrics["timing"]
    n = t["frames"]
    figures = {
        "frames": n, "keyframes": t["keyframes"], "imports_cpu_s": round(imports_cpu, 2),
        "run_cpu_s": round(cpu, 2), "run_wall_s": round(wall, 2),
        "cpu_ms_per_frame": round(1000 * cpu / max(n, 1), 1), "cpu_fps": round(n / cpu, 2) if cpu else None,
        "wall_fps": round(n / wall, 2) if wall else None,
        "stage_seconds": t.get("stage_seconds"), "stage_cpu_seconds": t.get("stage_cpu_seconds"),
        "map_cpu_seconds": t.get("map_cpu_seconds"), "steps": t.get("steps"),
        "process_cpu_s": t.get("cpu_seconds"), "tracking": run_metrics.get("tracking"),
        "peak_rss_mb": round(peak_rss_mb()),
        "run_dir": str(run_dir),
    }
    if metrics:
        ate = metrics.get("ate", {})
        lp = metrics.get("loops", {})
        pan = metrics.get("panoptic", {}) or {}
        figures.update({"ate_pct": ate.get("rmse_percent_of_path"), "ate_m": ate.get("rmse"),
                        "loops": lp.get("num_detected"), "loop_precision": lp.get("precision"),
                        "loop_recall": lp.get("recall"), "pq": pan.get("pq"), "vpq": pan.get("vpq")})
    if frontend is not None and hasattr(frontend, "stats"):
        figures["frontend_stats"] = {k: (round(v, 3) if isinstance(v, float) else v)
                                     for k, v in frontend.stats.items()}
    return figures


if __name__ == "__main__":
    sys.exit(main())
