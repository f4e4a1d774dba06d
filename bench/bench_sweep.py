"""Sweep benchmark: the same grid run serially in one process and on a local Ray instance.

    python bench/bench_sweep.py                                  # the target: 4 variants x 3 scenarios x 2 seeds
    python bench/bench_sweep.py --scenarios driving_loop --seeds 0 --variants 2 --frames 36 --width 160 --height 120

The grid is configs/sweep_table7.toml (the paper's Table 7 structure) unless ``--config`` names another sweep file;
``--scenarios/--seeds/--frames/--width/--height/--variants`` shrink it.  The sequences are generated into the cache
before either timing starts, so both runs only read them.  Prints both wall times, their ratio (target <= 0.6 on
2 cores) and the per-cell differences of ATE RMSE, RPE and keyframes between the two runs.  Each run writes its
own sweep directory under ``--out`` (a new temporary folder by default), so nothing is resumed from earlier runs.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _toml_value(v) -> str:
    """A TOML value (json's strings, numbers, true/false and arrays are TOML too; tables become inline)."""
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return json.dumps(v)


def write_grid(src: Path, dst: Path, name: str, args) -> None:
    """Write the sweep file ``src`` again with the benchmark's [sweep] (name, output dir, shrunk grid)."""
    from pvslam_core.config import read_toml

    raw = read_toml(src)
    sec = dict(raw.pop("sweep"))
    sec.update(name=name, output_dir=str(dst.parent / "sweeps"), plots=False)
    if args.scenarios:
        sec["scenarios"] = args.scenarios.split(",")
    if args.seeds:
        sec["seeds"] = [int(s) for s in args.seeds.split(",")]
    params = dict(sec.get("scenario_params", {}))
    for key in ("frames", "width", "height"):
        if getattr(args, key) is not None:
            params["num_frames" if key == "frames" else key] = getattr(args, key)
    sec["scenario_params"] = params
    variants = raw.pop("variant")[:args.variants or None]
    sequences = raw.pop("sequence", [])
    lines = ["[sweep]"] + [f"{k} = {_toml_value(v)}" for k, v in sec.items()]
    for table, body in raw.items():  # the base pipeline
        lines += ["", f"[{table}]"] + [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in body.items()]
    for kind, items in (("sequence", sequences), ("variant", variants)):
        for item in items:
            lines += ["", f"[[{kind}]]"] + [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in item.items()]
    dst.write_text("\n".join(lines) + "\n")


def metrics(sweep_dir: Path) -> dict[str, tuple]:
    out = {}
    for d in sorted((sweep_dir / "cells").iterdir()):
        if (d / "done.json").is_file():
            m = json.loads((d / "metrics.json").read_text())
            out[d.name] = (m.get("ate", {}).get("rmse"), m.get("rpe", {}).get("trans_rmse"),
                           m.get("timing", {}).get("keyframes"))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(REPO / "configs" / "sweep_table7.toml"))
    ap.add_argument("--scenarios", help="comma-separated subset of the scenarios")
    ap.add_argument("--seeds", help="comma-separated seeds")
    ap.add_argument("--variants", type=int, help="keep only the first N variants")
    ap.add_argument("--frames", type=int)
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--workers", type=int, help="Ray runs at a time (default: one per core)")
    ap.add_argument("--out", help="working folder (default: a new temporary folder)")
    args = ap.parse_args(argv)

    from pvslam_core.sweep.executors import machine_cores
    from pvslam_core.sweep.runner import run_sweep
    from pvslam_core.sweep.spec import load_sweep

    work = Path(args.out or tempfile.mkdtemp(prefix="bench_sweep_"))
    work.mkdir(parents=True, exist_ok=True)
    files = {kind: work / f"{kind}.toml" for kind in ("serial", "ray")}
    for kind, f in files.items():
        write_grid(Path(args.config), f, f"bench_{kind}", args)
    plan = load_sweep(files["serial"])
    print(f"grid: {len(plan.sequences)} sequences x {len(plan.section.seeds)} seeds x {len(plan.variants)} variants "
          f"= {len(plan.cells)} cells; {machine_cores()} cores; work folder {work}", flush=True)

    # Generate every sequence once, outside both timings.
    from pvslam_core.sweep.cells import prepare_dataset

    seen = set()
    for c in plan.cells:
        ds = json.dumps(c.config.to_dict()["dataset"], sort_keys=True)
        if ds not in seen:
            seen.add(ds)
            r = prepare_dataset({"name": c.sequence, "threads": machine_cores(), "dataset": json.loads(ds)})
            if r["status"] != "done":
                print(f"cannot prepare {c.sequence}: {r['error']}", file=sys.stderr)
                return 1

    times = {}
    for kind in ("serial", "ray"):
        t0 = time.perf_counter()
        out = run_sweep(files[kind], serial=(kind == "serial"), workers=args.workers if kind == "ray" else None)
        times[kind] = time.perf_counter() - t0
        print(f"{kind}: {times[kind]:.1f} s wall ({out.executor}, {out.workers} x {out.threads} threads, "
              f"{len(out.ran)} cells, {len(out.failed)} failed)", flush=True)

    ratio = times["ray"] / times["serial"]
    print(f"\nray / serial wall time: {ratio:.3f}  (target <= 0.6)")
    a = metrics(load_sweep(files["serial"]).directory)
    b = metrics(load_sweep(files["ray"]).directory)
    print(f"\n{'cell':<48} {'ATE serial':>11} {'ATE ray':>11} {'|dATE|':>9} {'|dRPE|':>9} {'dKF':>4}")
    worst = 0.0
    for name in sorted(set(a) | set(b)):
        if name not in a or name not in b:
            print(f"{name:<48} finished in only one run")
            continue
        (ea, ra, ka), (eb, rb, kb) = a[name], b[name]
        de = abs(ea - eb) if ea is not None and eb is not None else float("nan")
        dr = abs(ra - rb) if ra is not None and rb is not None else float("nan")
        worst = max(worst, de / max(abs(ea or 0.0), 1e-12)) if de == de else worst
        print(f"{name:<48} {ea if ea is not None else float('nan'):>11.5f} {eb if eb is not None else float('nan'):>11.5f} "
              f"{de:>9.2e} {dr:>9.2e} {(kb or 0) - (ka or 0):>4d}")
    print(f"\nlargest relative ATE difference: {worst:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
