"""Benchmark of the ``panoptic_fpn`` segmenter: speed, panoptic quality on held-out seeds, and the ATE of
the moving-vehicles scenario with it against the ``labels`` oracle and no segmenter.

    python bench/bench_segmenter.py                       # everything (about 30-40 minutes on 2 shared cores)
    python bench/bench_segmenter.py --only timing pq
    python bench/bench_segmenter.py --only ate --seeds 200 201 --repeats 2

Sections (each prints its figures and target lines ``[PASS]``/``[MISS]``):
  timing  ms per frame (wall and CPU of this process) at 320x240 and at KITTI resolution (1224x368), for the
          reduced model with the shipped weights and for the full R-50 (coco_r50 preset, native size and the
          detectron2 test resize; random weights: no COCO file can be downloaded here, so the ROI work depends on
          what random heads propose -- the count is printed, and the ``--worst-case`` mode of
          ``python -m pvslam_plugins.segmenters.panoptic_fpn.timing`` bounds it)
  pq      PQ/SQ/RQ (all, things, stuff, per class) of the shipped model on frames of every synthetic scenario
          rendered with generator seeds that training never used (``--pq-seeds``), plus PQ with ground-truth
          segments under 64 px as void
  ate     Sim(3) ATE of ``configs/moving_vehicles.toml`` on held-out seeds (``--seeds``, ``--repeats`` runs a seed,
          starting at raw frames 0, 1, ...) with segmenter panoptic_fpn / labels / none
Results are written as JSON to ``--json`` (default runs/bench/results_segmenter.json) with the commit of the
measured code (:mod:`bench.provenance`; refused without one).  Torch runs with one thread (``--threads``): on this
shared 2-core VM two threads were several times slower in wall time.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance  # noqa: E402
RESULTS: dict = {}


def target(name: str, ok: bool, measured: str, goal: str) -> None:
    print(f"  [{'PASS' if ok else 'MISS'}] {name}: {measured}   (target: {goal})")
    RESULTS.setdefault("targets", []).append({"name": name, "ok": bool(ok), "measured": measured, "target": goal})


def load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def frame_at(width: int, height: int, scenario: str = "moving_vehicles", index: int = 30, seed: int = 100):
    from pvslam_plugins.datasets.synthetic.render import render
    from pvslam_plugins.datasets.synthetic.scenarios import build

    sc = build(scenario, width=width, height=height, seed=seed)
    r = render(sc.scene, index, sc.poses[index], sc.camera)
    return torch.from_numpy(r.rgb.transpose(2, 0, 1).copy())


def time_model(model, img: torch.Tensor, reps: int) -> dict:
    """Median wall ms of whole ``segment`` calls (after a warm-up), CPU ms per call, and the per-stage split."""
    from pvslam_plugins.segmenters.panoptic_fpn.timing import profile

    with torch.no_grad():
        model.segment(img)
        walls, cpus = [], []
        for _ in range(reps):
            c0, t0 = time.process_time(), time.perf_counter()
            out = model.segment(img)
            walls.append((time.perf_counter() - t0) * 1e3)
            cpus.append((time.process_time() - c0) * 1e3)
    stages = profile(model, img, reps=max(1, reps // 2))
    return {"wall_ms": statistics.median(walls), "cpu_ms": statistics.median(cpus), "segments": len(out.segments),
            "detections": len(out.detections), "stages_ms": {k: round(v, 1) for k, v in stages.items()
                                                               if isinstance(v, float)},
            "load": load()}


def section_timing(reps: int) -> None:
    from pvslam_plugins.segmenters.panoptic_fpn.categories import category_set
    from pvslam_plugins.segmenters.panoptic_fpn.config import preset
    from pvslam_plugins.segmenters.panoptic_fpn.model import PanopticFPN
    from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenterConfig, build_model

    print("== timing (ms per frame; wall is shared-machine sensitive, CPU is this process's) ==")
    small, kitti = frame_at(320, 240), frame_at(1224, 368)
    rows = {}
    reduced = build_model(PanopticFPNSegmenterConfig())
    for size, img in (("320x240", small), ("1224x368", kitti)):
        rows[f"reduced {size}"] = time_model(reduced, img, reps)
    torch.manual_seed(0)
    full = PanopticFPN(preset("coco_r50"), category_set("coco_panoptic")).eval()
    for resize in (False, True):
        full.cfg.input.min_size_test = 800 if resize else 0
        tag = "detectron2 resize (short side 800, long <= 1333)" if resize else "native size"
        for size, img in (("320x240", small), ("1224x368", kitti)):
            rows[f"coco_r50 {size} {tag}"] = time_model(full, img, max(2, reps // 3))
    for k, r in rows.items():
        print(f"  {k:62s} wall {r['wall_ms']:8.1f}  CPU {r['cpu_ms']:8.1f}  detections {r['detections']:3d}  "
              f"(load {r['load']})")
    RESULTS["timing"] = rows
    ms = rows["reduced 320x240"]["wall_ms"]
    target("reduced 320x240 keyframe", ms <= 150, f"{ms:.0f} ms wall ({rows['reduced 320x240']['cpu_ms']:.0f} ms CPU)",
           "<= 150 ms")


def section_pq(seeds: list[int], frames: int) -> None:
    from pvslam_plugins.segmenters.panoptic_fpn.data import render_samples
    from pvslam_plugins.segmenters.panoptic_fpn.evaluate import evaluate, format_table
    from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenterConfig, build_model
    from pvslam_plugins.segmenters.panoptic_fpn.train import TrainConfig

    print(f"== panoptic quality on held-out seeds {seeds} ({frames} frames per scenario and seed) ==")
    train_seeds = set(TrainConfig().train_seeds)
    if train_seeds & set(seeds):
        raise SystemExit(f"--pq-seeds {sorted(train_seeds & set(seeds))} were used for training")
    model = build_model(PanopticFPNSegmenterConfig())
    samples = []
    for scen in TrainConfig().scenarios:
        for seed in seeds:
            samples += render_samples(scen, seed, frames)
    res = evaluate(model, samples, min_gt_area=64)
    table = format_table(res)
    print(table)
    print(f"\n  with ground-truth segments under 64 px as void: PQ {100 * res['pq_min_area']['pq']:.1f} "
          f"(things {100 * res['pq_min_area']['things']['pq']:.1f}, stuff {100 * res['pq_min_area']['stuff']['pq']:.1f})")
    RESULTS["pq"] = {"seeds": seeds, "frames": len(samples), "result": res, "table": table}
    p = res["pq"]
    target("PQ on held-out seeds", p["pq"] >= 0.6, f"{100 * p['pq']:.1f} (things {100 * p['things']['pq']:.1f}, "
           f"stuff {100 * p['stuff']['pq']:.1f})", ">= 60")


def section_ate(seeds: list[int], repeats: int, out: Path, only: Optional[list[str]] = None,
                overrides: Optional[list[str]] = None) -> None:
    from pvslam_core.api import run_config

    # run r of a seed starts at raw frame r (dataset.start): the pipeline is deterministic, so repeating a run
    # repeats its number, and a start shifted by a frame is the cheapest independent sample of the run's chaos
    print(f"== ATE, configs/moving_vehicles.toml, seeds {seeds}, {repeats} runs each (start frames 0..{repeats - 1}) ==")
    variants = {"panoptic_fpn": ['segmenter.plugin="panoptic_fpn"'], "labels": ['segmenter.plugin="labels"'],
                "none": ['segmenter.plugin="none"']}
    if only:  # a subset (tuning one segmenter's post-processing); the targets need all three
        variants = {k: v for k, v in variants.items() if k in only}
    rows: dict = {v: [] for v in variants}
    for seed in seeds:
        for rep in range(repeats):
            for name, ov in variants.items():
                t0 = time.perf_counter()
                r = run_config(str(ROOT / "configs" / "moving_vehicles.toml"), overrides=[
                    f'run.output_dir="{out.as_posix()}"', "run.progress=false", f"dataset.seed={seed}",
                    f"dataset.start={rep}", f'run.name="mv-{name}-s{seed}-r{rep}"', *ov, *(overrides or [])])
                a = r.metrics.get("ate", {})
                pan = r.metrics.get("panoptic", {})
                row = {"seed": seed, "run": rep, "ate_m": a.get("rmse", float("nan")),
                       "ate_pct": a.get("rmse_percent_of_path", float("nan")), "seconds": time.perf_counter() - t0,
                       "keyframes": r.metrics["timing"]["keyframes"], "pq": pan.get("pq"), "vpq": pan.get("vpq"),
                       "segment_s": r.metrics["timing"]["stage_seconds"].get("segment"), "load": load()}
                rows[name].append(row)
                print(f"  seed {seed} run {rep} {name:13s} ATE {row['ate_m']:.4f} m ({row['ate_pct']:.3f} % of path)"
                      f"  PQ {row['pq'] if row['pq'] is None else round(row['pq'], 3)}  {row['seconds']:.0f} s"
                      f"  (load {row['load']})", flush=True)
    RESULTS["ate"] = rows

    def mean(name: str) -> float:
        vals = [r["ate_m"] for r in rows[name]]
        return float("nan") if any(v != v for v in vals) else statistics.mean(vals)

    m = {k: mean(k) for k in rows}
    per_seed = {}
    for seed in seeds:
        per_seed[seed] = {k: statistics.mean([r["ate_m"] for r in rows[k] if r["seed"] == seed]) for k in rows}
    RESULTS["ate_summary"] = {"mean_m": m, "per_seed_mean_m": per_seed}
    print("  mean ATE (m): " + ", ".join(f"{k} {v:.4f}" for k, v in m.items()))
    if repeats > 1:  # the spread of the mean over start frames (each start's mean over the seeds)
        by_start = {k: [statistics.mean([r["ate_m"] for r in rows[k] if r["run"] == rep]) for rep in range(repeats)]
                    for k in rows}
        RESULTS["ate_summary"]["per_start_mean_m"] = by_start
        print("  mean ATE per start frame (m): " + "; ".join(
            f"{k} " + " / ".join(f"{v:.3f}" for v in vals) for k, vals in by_start.items()))
    if len(m) < 3:
        return
    target("panoptic_fpn within 1.3x of labels", m["panoptic_fpn"] <= 1.3 * m["labels"],
           f"{m['panoptic_fpn'] / m['labels']:.2f}x", "<= 1.3x")
    target("panoptic_fpn better than none", m["panoptic_fpn"] < m["none"],
           f"{m['panoptic_fpn']:.4f} m vs {m['none']:.4f} m", "lower")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", choices=["timing", "pq", "ate"], default=["timing", "pq", "ate"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=9, help="timed calls per configuration (after one warm-up)")
    ap.add_argument("--pq-seeds", type=int, nargs="+", default=[0, 200, 201],
                    help="generator seeds for the PQ section (never used in training or validation)")
    ap.add_argument("--pq-frames", type=int, default=12, help="frames per scenario and seed for the PQ section")
    ap.add_argument("--seeds", type=int, nargs="+", default=[200, 201], help="moving_vehicles seeds for the ATE")
    ap.add_argument("--repeats", type=int, default=3,
                    help="ATE runs per seed, run r starting at raw frame r (deterministic runs: a plain repeat would "
                    "give the same number)")
    ap.add_argument("--variants", nargs="+", choices=["panoptic_fpn", "labels", "none"],
                    help="ATE: run only these segmenters (default all three; the targets need all three)")
    ap.add_argument("--override", action="append", default=[],
                    help="ATE: an extra `pvslam run --set` KEY=VALUE for every run (repeatable)")
    ap.add_argument("--out", help="run folder for the ATE runs (default: a temporary folder)")
    ap.add_argument("--json", default=str(provenance.RESULTS_DIR / "results_segmenter.json"),
                    help="result file (not into bench/)")
    args = ap.parse_args(argv)
    try:
        prov = provenance.check(args.json)
    except provenance.ProvenanceError as exc:
        return provenance.fail(exc)
    torch.set_num_threads(args.threads)
    RESULTS["meta"] = {"threads": args.threads, "torch": torch.__version__, "argv": sys.argv[1:],
                       "load_at_start": load()}
    t0 = time.perf_counter()
    if "timing" in args.only:
        section_timing(args.reps)
    if "pq" in args.only:
        section_pq(args.pq_seeds, args.pq_frames)
    if "ate" in args.only:
        with tempfile.TemporaryDirectory() as tmp:
            section_ate(args.seeds, args.repeats, Path(args.out) if args.out else Path(tmp), args.variants,
                        args.override)
    RESULTS["meta"]["seconds"] = time.perf_counter() - t0
    provenance.write_json(args.json, json.loads(json.dumps(RESULTS, default=float)), prov)
    print(f"results: {args.json} ({RESULTS['meta']['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
