"""Frames/s, CPU per frame and per stage, and keyframes per frame of every kind of run, in one table.

``python bench/bench_pipeline.py --only speed`` runs (``--quick``: the first report seed, a few frames each):

* the **default run** (``pvslam run``'s config, the built-in driving loop at 320x240);
* every synthetic **scenario's report seeds** (``bench/seeds.toml``) as the report matrix runs them
  (``bench/matrix_jobs.py``: the images reader, no segmenter), each scenario's mean after its seeds;
* the **real KITTI excerpts** exactly as a user runs them, ``pvslam run FOLDER --calib calib.txt`` in a child process
  (:func:`bench.bench_real.run_pvslam`), and on the same frames the **textbook VO** and **ORB-SLAM3**
  (:func:`bench.bench_real.run_vo`, :func:`bench.bench_real.run_orb`; ORB-SLAM3 only with ``--orb-python`` and a
  vocabulary), with pvslam's CPU per frame as a multiple of each peer's.

pvslam's figures come from its ``metrics.json`` timing (evaluation and start-up excluded): wall frames/s, the mean
wall time of a keyframe step and of any other step (``timing.steps``), the process's CPU per frame (every thread), and
per stage the pipeline thread's CPU per frame -- the mapping's parts
(track, a new keyframe's setup, edges, BA, loops, pose guess, fill, the rest of the map stage), then segment, VPS,
outputs and read -- and ``other threads`` (the process less the pipeline thread: reading ahead, writing behind, the
flow lanes).  The final
BA is a separate column (once per run, spread over its frames).  The peers have totals only: the textbook VO its
loop's process time, ORB-SLAM3 its child process's rusage less its vocabulary load (python start-up still in it;
one run, it is not reproducible: bench_real.py runs it three times).  CPU time does not depend on what else runs on
the machine; wall time does.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional, Sequence

# (column, where it comes from): "map:" a part of the map stage (timing.map_cpu_seconds), else a pipeline stage
# (timing.stage_cpu_seconds)
STAGES = (("track", "map:track"), ("new keyframe", "map:keyframe"), ("edges", "map:edges"), ("BA", "map:ba"),
          ("loops", "map:loops"), ("pose guess", "map:pose_guess"), ("fill", "map:fill"), ("map other", "map:"),
          ("segment", "segment"), ("VPS", "vps"), ("outputs", "outputs"), ("read", "read"), ("final BA", "finalize"))
HEAD = ("group", "run", "frames", "kf/frame", "frames/s wall", "ms/keyframe step", "ms/other step", "CPU ms/frame",
        *(s for s, _ in STAGES), "other threads")


def run_row(group: str, name: str, timing: dict) -> dict:
    """A pvslam run's row from its ``metrics.json`` ``timing``: per frame, milliseconds of CPU."""
    n = max(int(timing.get("frames") or 0), 1)
    stage = timing.get("stage_cpu_seconds") or {}
    parts = timing.get("map_cpu_seconds") or {}
    ms = {}
    for col, src in STAGES:
        if src == "map:":
            ms[col] = 1000 * (stage.get("map", 0.0) - sum(parts.values())) / n
        elif src.startswith("map:"):
            ms[col] = 1000 * parts.get(src[4:], 0.0) / n
        else:
            ms[col] = 1000 * stage.get(src, 0.0) / n
    thread = sum(stage.values())
    cpu = float(timing.get("cpu_seconds") or thread)
    ms["other threads"] = 1000 * (cpu - thread) / n
    steps = timing.get("steps") or {}
    return {"group": group, "run": name, "frames": int(timing.get("frames") or 0),
            "kf_per_frame": (timing.get("keyframes") or 0) / n, "fps": float(timing.get("fps") or math.nan),
            "step_ms": {k: float(v["wall_ms"]) if v.get("count") else math.nan for k, v in steps.items()},
            "cpu_ms": 1000 * cpu / n, "stage_ms": ms}


def peer_row(group: str, name: str, frames: int, cpu_s: float, wall_s: Optional[float]) -> dict:
    """A peer's row: totals only (``wall_s`` None: not a meaningful wall time, e.g. a paced real-time run)."""
    n = max(int(frames), 1)
    return {"group": group, "run": name, "frames": int(frames), "kf_per_frame": math.nan,
            "fps": n / wall_s if wall_s else math.nan, "step_ms": {}, "cpu_ms": 1000 * cpu_s / n, "stage_ms": {}}


def mean_row(rows: Sequence[dict], group: str, name: str) -> dict:
    """The mean of ``rows`` (a scenario's seeds): every figure averaged over the runs, frames summed."""
    cols = [c for c, _ in STAGES] + ["other threads"]
    avg = lambda vals: sum(vals) / len(vals) if vals else math.nan  # noqa: E731
    return {"group": group, "run": name, "frames": sum(r["frames"] for r in rows),
            "kf_per_frame": avg([r["kf_per_frame"] for r in rows]), "fps": avg([r["fps"] for r in rows]),
            "step_ms": {k: avg([r["step_ms"][k] for r in rows if k in r.get("step_ms", {})])
                        for k in ("keyframe", "other") if any(k in r.get("step_ms", {}) for r in rows)},
            "cpu_ms": avg([r["cpu_ms"] for r in rows]),
            "stage_ms": {c: avg([r["stage_ms"][c] for r in rows if c in r["stage_ms"]]) for c in cols
                         if any(c in r["stage_ms"] for r in rows)}}


def _num(v: Optional[float], fmt: str) -> str:
    return "-" if v is None or not math.isfinite(v) else format(v, fmt)


def table(rows: Sequence[dict]) -> list[str]:
    """Markdown lines, one per row in order (a missing figure: ``-``)."""
    out = ["| " + " | ".join(HEAD) + " |", "|" + "---|" * len(HEAD)]
    for r in rows:
        st = r["stage_ms"]
        steps = r.get("step_ms") or {}
        cells = [r["group"], r["run"], str(r["frames"]), _num(r["kf_per_frame"], ".2f"), _num(r["fps"], ".1f"),
                 _num(steps.get("keyframe"), ".1f"), _num(steps.get("other"), ".1f"), _num(r["cpu_ms"], ".1f"),
                 *(_num(st.get(c), ".1f") for c, _ in STAGES),
                 _num(st.get("other threads"), ".1f")]
        out.append("| " + " | ".join(cells) + " |")
    return out


def cpu_ratios(rows: Sequence[dict], group: str) -> list[str]:
    """Lines ``pvslam CPU/frame = Nx PEER's`` for the rows of ``group`` (the first row is pvslam's)."""
    mine = [r for r in rows if r["group"] == group]
    if len(mine) < 2 or not mine[0]["cpu_ms"] > 0:
        return []
    return [f"  {group}: pvslam's CPU per frame is {mine[0]['cpu_ms'] / r['cpu_ms']:.1f}x {r['run']}'s "
            f"({mine[0]['cpu_ms']:.1f} vs {r['cpu_ms']:.1f} ms)" for r in mine[1:] if r["cpu_ms"] > 0]


def real_groups(rows: Sequence[dict]) -> list[tuple[str, dict, Optional[dict]]]:
    """Per real excerpt (a ``KITTI ...`` group, in table order): the group, pvslam's row (the group's first) and
    ORB-SLAM3's row (None where it was not run)."""
    out = []
    for group in dict.fromkeys(r["group"] for r in rows if r["group"].startswith("KITTI")):
        mine = [r for r in rows if r["group"] == group]
        out.append((group, mine[0], next((r for r in mine[1:] if r["run"].startswith("ORB-SLAM3")), None)))
    return out


def targets(rows: Sequence[dict], target) -> None:
    """The speed targets as ``target(name, ok, measured, goal)`` lines: >= 30 frames/s at 320x240 (the default run and
    each scenario's mean), >= 15 frames/s on the real excerpts, CPU per frame within 3x of ORB-SLAM3's."""
    for r in rows:
        if r["group"] == "default" or r["run"] == "mean":
            target(f"speed 320x240 {r['group']}", r["fps"] >= 30, f"{r['fps']:.1f} frames/s wall", ">= 30 frames/s")
    for group, mine, orb in real_groups(rows):
        target(f"speed {group} as a user runs it", mine["fps"] >= 15, f"{mine['fps']:.1f} frames/s wall",
               ">= 15 frames/s")
        if orb is not None and orb["cpu_ms"] > 0:
            x = mine["cpu_ms"] / orb["cpu_ms"]
            target(f"CPU per frame {group} vs ORB-SLAM3", x <= 3, f"{x:.1f}x", "<= 3x")


# ---------------------------------------------------------------------------------------------------- runs
def synthetic_rows(run, out: Path, quick: bool) -> list[dict]:
    """Every scenario on its report seeds (``run(overrides, out)`` runs one config in this process), each scenario's
    rows followed by their mean."""
    from bench import seeds
    from bench.matrix_jobs import pvslam_overrides, synthetic_sequence
    from pvslam_plugins.datasets.synthetic.scenarios import SCENARIOS

    report = seeds.load().sets["report"]
    frames = 60 if quick else None
    rows = []
    for sc in SCENARIOS:
        mine = []
        for seed in report[:1] if quick else report:
            seq = synthetic_sequence(sc, seed, None)  # the cached sequence (--quick: its first frames)
            fps = float(json.loads((seq / "meta.json").read_text())["fps"])
            r = run(pvslam_overrides("synthetic", seq, fps, frames, labels=False) + _quiet(), out)
            mine.append(run_row(sc, f"seed {seed}", r.metrics["timing"]))
        rows += mine + [mean_row(mine, sc, "mean")]
    return rows


def real_rows(out: Path, quick: bool, orb_python: Optional[str], orb_vocab: Sequence[str],
              timeout: float = 1800.0) -> list[dict]:
    """Per KITTI excerpt: pvslam as a user runs it, the textbook VO and ORB-SLAM3 (once) on the same frames."""
    from bench import bench_real as B
    from bench.matrix_jobs import KITTI, kitti_as_tum

    rows = []
    for seq in B.SEQUENCES:
        if not (KITTI / "sequences" / seq / "image_0").is_dir():
            print(f"  KITTI {seq} skipped: not in {KITTI / 'sequences'}")
            continue
        group = f"KITTI {seq}"
        extra = ["--set", "run.max_frames=20"] if quick else []
        pv = B.run_pvslam(seq, out, timeout, extra=extra)
        if "run_dir" not in pv:
            print(f"  {group} pvslam: {pv.get('error')}")
            continue
        timing = json.loads((Path(pv["run_dir"]) / "metrics.json").read_text())["timing"]
        rows.append(run_row(group, "pvslam run FOLDER --calib", timing))
        seq_dir = kitti_as_tum(seq, out / "peers")
        vo = B.run_vo(seq_dir)
        rows.append(peer_row(group, "textbook VO", len(vo["ts"]), vo["cpu_s"], vo["wall_s"]))
        vocab = B.vocab_for(list(orb_vocab), seq)
        note = B.orb_missing(orb_python, vocab, B.PEERS / "orbslam3_traj.py")
        if note is not None:
            print(f"  {group} ORB-SLAM3 skipped: {note}")
            continue
        orb = B.run_orb(seq, seq_dir, orb_python, vocab, 0, out, timeout)
        # paced at the sequence's frame rate (--realtime): its wall time is the pacing's, not its speed; its CPU less
        # the vocabulary load (the seconds it reports for that one-thread load), as pvslam's leaves out its start-up
        cpu = orb["cpu_s"] - float(orb.get("vocab_load_s") or 0.0)
        rows.append(peer_row(group, "ORB-SLAM3 (less vocabulary load)", len(B.read_gt(seq_dir)[0]), cpu, None))
    return rows


def _quiet() -> list[str]:
    """What the speed runs do not need (all of it written after the timed part)."""
    return ["outputs.ply=false", "outputs.plots=false", "evaluation.enabled=false"]


def section(run, out: Path, quick: bool, orb_python: Optional[str] = None, orb_vocab: Sequence[str] = (),
            results: Optional[dict] = None, target=None) -> list[dict]:
    """The whole table (module docstring): runs everything, prints the table, the CPU ratios to the peers and, with
    ``target`` (bench_pipeline's), the target lines."""
    print("\n== speed: frames/s, CPU ms/frame per stage, keyframes/frame (evaluation excluded) ==")
    r = run(_quiet() + (["run.max_frames=60"] if quick else []), out)
    rows = [run_row("default", "pvslam run", r.metrics["timing"])]
    rows += synthetic_rows(run, out, quick)
    real = real_rows(out, quick, orb_python, orb_vocab)
    rows += real
    print("\n".join(table(rows)))
    for group in dict.fromkeys(r_["group"] for r_ in real):
        print("\n".join(cpu_ratios(rows, group)))
    if target is not None:
        targets(rows, target)
    if results is not None:
        results["speed"] = rows
    return rows
