"""pvslam beside ORB-SLAM3 and the textbook VO on every real sequence, in one command.

    python bench/bench_real.py --orb-python /work/venv-orb/bin/python --orb-vocab runs/orbvoc/voc.txt
    python bench/bench_real.py --orb-vocab 00=runs/orbvoc/voc_06_01.txt --orb-vocab runs/orbvoc/voc_00.txt
    PVSLAM_ORB_PYTHON=... PVSLAM_ORB_VOCAB=00=VOC_A:VOC_B python bench/bench_real.py   # as bench/figures.py runs it
    python bench/bench_real.py --orb-runs 0 --set frontend.road.enabled=false --json runs/bench/variant.json  # screen

Per KITTI excerpt in ``../shared/data/kitti-odometry`` (00, 06, 01; ``--sequences``):

* **pvslam** exactly as a user runs it: ``pvslam run SEQUENCE_FOLDER --calib SEQUENCE_FOLDER/calib.txt`` in a child
  process (the default config; ``--output-dir``/``--name``/``--quiet`` only choose where the run goes);
* **ORB-SLAM3** (``../shared/peers/orbslam3_traj.py`` with the python of its own venv, ``--realtime`` at 10 frames/s)
  ``--orb-runs`` times (default 3; it is not reproducible): the range and the frames each run returned.  It needs
  a vocabulary trained on images that are not evaluated (``--orb-vocab PATH`` for every sequence, ``SEQ=PATH`` for
  one); without its python or a vocabulary the peer is skipped with a note;
* the **textbook VO** (``bench/peers/textbook_vo.py``, in this process).

Scores, all against ``poses/NN.txt`` from its first frame with measured ground truth on (KITTI's poses begin 00
and 06 with a constant-velocity extrapolation that no camera motion follows: :func:`bench.matrix_jobs.measured_from`;
the ATE over every frame is printed beside): ATE RMSE after Sim(3) alignment (metres and % of the path length), RPE
between consecutive posed frames (translation in metres, rotation in degrees; evo's RPE with ``delta = 1`` frame
through ``pvslam_core.evaluation``, after the same Sim(3) alignment), frames posed / total (pvslam: the trajectory's
rows less its tracking failures; ORB-SLAM3: the frames of its largest map), and CPU milliseconds per frame (the
child process's rusage, start-up included: python imports, ORB-SLAM3's vocabulary load; the textbook VO: the
process time of its loop).  ORB-SLAM3's ATE covers only the frames of its largest map, and an ATE over part of a
sequence is not comparable with one over all of it: the row *pvslam on ORB-SLAM3's frames* scores pvslam's trajectory
over each ORB-SLAM3 run's posed frames alone (aligned on those).  pvslam repeats exactly but moves with the input's
size, so it also runs with the processing area 2 % per side smaller and larger (``--size-spread``): its rows show
that range as ORB-SLAM3's show its run-to-run spread.  The result file (``--json``, default
``runs/bench/real.json``) records the provenance.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import resource
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import provenance  # noqa: E402
from bench.matrix_jobs import KITTI, kitti_as_tum, measured_from, read_gt  # noqa: E402

PEERS = Path(os.environ.get("PVSLAM_PEERS", ROOT.parent / "shared" / "peers"))
SEQUENCES = ("00", "06", "01")
ORB_FPS = 10.0
MAX_DIFF = 0.02  # seconds: timestamp association of estimates and ground truth
SAME_FRAMES = "pvslam on ORB-SLAM3's frames"  # the table row: pvslam scored over each ORB-SLAM3 run's posed frames


# ------------------------------------------------------------------------------------------------ scores
def score(ts: np.ndarray, poses: np.ndarray, gt_ts: np.ndarray, gt: np.ndarray, total: int,
          posed: Optional[int] = None, first: int = 0) -> dict:
    """ATE (Sim(3), m and %), RPE per frame (translation m, rotation deg), frames posed of ``total``, over the frames
    from ``first`` on (aligned on those; the first with measured ground truth: :func:`bench.matrix_jobs.measured_from`),
    and the ATE over every frame (``ate_all_m``, ``ate_all_pct``).  ``poses`` [N, 7] T_wc (rows with NaN are not
    posed); ``posed`` overrides the count of finite rows."""
    from bench.peers.common import ate_sim3
    from pvslam_core.evaluation.trajectory import rpe

    ts = np.asarray(ts, np.float64).reshape(-1)
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    finite = np.all(np.isfinite(poses), axis=1)
    out = {"posed": int(finite.sum()) if posed is None else int(posed), "total": int(total), "first": int(first)}
    scored = finite & (ts >= gt_ts[first] - MAX_DIFF) if first else finite
    if scored.sum() < 3:
        return {**out, "ate_m": math.nan, "ate_pct": math.nan, "ate_all_m": math.nan, "ate_all_pct": math.nan,
                "rpe_t_m": math.nan, "rpe_r_deg": math.nan, "error": f"{int(scored.sum())} poses: nothing to align"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a_all = ate_sim3(ts, poses, gt_ts, gt, max_diff=MAX_DIFF)
        a = ate_sim3(ts, poses, gt_ts[first:], gt[first:], max_diff=MAX_DIFF) if first else a_all
        r = rpe(ts[scored], poses[scored], gt_ts[first:], gt[first:], delta=1, delta_unit="frames", align="sim3",
                max_diff=MAX_DIFF)
    return {**out, "ate_m": float(a["rmse"]), "ate_pct": float(a["rmse_percent_of_path"]),
            "ate_all_m": float(a_all["rmse"]), "ate_all_pct": float(a_all["rmse_percent_of_path"]),
            "path_m": float(a["path_length"]), "rpe_t_m": r["trans_rmse"], "rpe_r_deg": r["rot_rmse"],
            "rpe_pairs": r["num_pairs"]}


def child_cpu() -> float:
    """CPU seconds (user + system) of the waited-for child processes so far."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_child(cmd: list[str], log: Path, timeout: float) -> tuple[int, float, float, str]:
    """Run ``cmd`` -> (exit status, CPU seconds from its rusage, wall seconds, its output); output also to ``log``."""
    c0, t0 = child_cpu(), time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        rc, text = p.returncode, p.stdout + p.stderr
    except subprocess.TimeoutExpired as exc:
        rc, text = -1, f"timed out after {timeout:.0f} s\n{exc.stdout or ''}{exc.stderr or ''}"
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(text)
    return rc, child_cpu() - c0, time.perf_counter() - t0, text


def _ms(cpu_s: float, frames: int) -> float:
    return 1000.0 * cpu_s / frames if frames else math.nan


# ------------------------------------------------------------------------------------------------ methods
def run_pvslam(seq: str, out: Path, timeout: float, extra: Sequence[str] = (), tag: str = "") -> dict:
    """``pvslam run`` on excerpt ``seq`` in a child process (``extra``: more command-line arguments; ``tag``: a
    suffix of the run's name and log)."""
    from pvslam_core.outputs.trajectory_io import read_tum

    src = KITTI / "sequences" / seq
    exe = shutil.which("pvslam", path=str(Path(sys.executable).parent)) or shutil.which("pvslam")
    if exe is None:
        return {"error": "the pvslam command is not installed (pip install -e .)"}
    cmd = [exe, "run", str(src), "--calib", str(src / "calib.txt"), "--output-dir", str(out / "pvslam"),
           "--name", f"kitti_{seq}{tag}", "--quiet", *extra]
    rc, cpu, wall, text = run_child(cmd, out / "logs" / f"pvslam_{seq}{tag}.log", timeout)
    m = re.search(r"^run directory: (.+)$", text, re.M)
    if m is None or not (Path(m.group(1)) / "trajectory.txt").is_file():
        return {"error": f"pvslam exited with {rc} and no trajectory (log: {out / 'logs'})", "cpu_s": cpu}
    run_dir = Path(m.group(1).strip())
    ts, poses = read_tum(run_dir / "trajectory.txt")
    timing = json.loads((run_dir / "metrics.json").read_text()).get("timing", {})
    failures = int(timing.get("tracking_failures", 0))
    posed = 0 if rc != 0 else int(np.all(np.isfinite(poses), axis=1).sum()) - failures
    return {"ts": np.asarray(ts), "poses": np.asarray(poses), "posed": posed, "cpu_s": cpu, "wall_s": wall,
            "exit": rc, "run_dir": str(run_dir), "command": cmd, "reinits": int(timing.get("reinitialisations", 0))}


def size_variants(spread_pct: float) -> list[tuple[str, list[str]]]:
    """pvslam's runs per excerpt: ``(tag, extra arguments)``, as a user runs it and, with ``spread_pct`` > 0, with
    the processing area ``spread_pct`` % per side smaller and larger (``dataset.max_pixels``).  pvslam repeats
    exactly, ORB-SLAM3 does not: its runs show its spread, these how much pvslam's result moves with the size."""
    from pvslam_core.datasets.base import MAX_PIXELS

    out = [("", [])]
    if spread_pct > 0:
        for tag, f in (("_smaller", 1.0 - spread_pct / 100.0), ("_larger", 1.0 + spread_pct / 100.0)):
            out.append((tag, ["--set", f"dataset.max_pixels={round(MAX_PIXELS * f * f)}"]))
    return out


def orb_timestamps(orb_ts: np.ndarray, seq_ts: np.ndarray, fps: float = ORB_FPS) -> np.ndarray:
    """ORB-SLAM3's timestamps (frame index / fps) -> the sequence's own timestamps (``times.txt`` or 10 Hz)."""
    idx = np.rint(np.asarray(orb_ts, np.float64) * fps).astype(np.int64)
    if len(idx) and (idx.min() < 0 or idx.max() >= len(seq_ts)):
        raise ValueError(f"ORB-SLAM3 returned frame {idx.max()} of a {len(seq_ts)}-frame sequence")
    return np.asarray(seq_ts, np.float64)[idx]


def orb_missing(python: Optional[str], vocab: Optional[str], runner: Path) -> Optional[str]:
    """Why the ORB-SLAM3 peer cannot run (a note), or None."""
    if not python:
        return "no --orb-python (the python of a venv with pyorbslam3, see ../shared/peers/README.md)"
    if not Path(python).is_file():
        return f"--orb-python {python}: no such file"
    probe = subprocess.run([python, "-c", "import pyorbslam3, scipy, cv2, numpy"], capture_output=True, text=True)
    if probe.returncode != 0:
        lines = probe.stderr.strip().splitlines() or ["no output"]
        return f"--orb-python {python} cannot run the ORB-SLAM3 runner ({lines[-1]}; it needs pyorbslam3, scipy, " \
               "opencv-python-headless, numpy)"
    if not runner.is_file():
        return f"{runner}: the ORB-SLAM3 runner is missing (../shared/peers)"
    if not vocab:
        return "no --orb-vocab for this sequence (train one with ../shared/peers/make_orb_vocab.py on other images)"
    if not Path(vocab).is_file():
        return f"--orb-vocab {vocab}: no such file"
    return None


def run_orb(seq: str, seq_dir: Path, python: str, vocab: str, run: int, out: Path, timeout: float,
            images: Optional[Path] = None, first: int = 0, tag: str = "") -> dict:
    """ORB-SLAM3's run ``run`` on excerpt ``seq`` (``images``: a folder of its frames from frame ``first`` on instead
    of all of them; ``tag``: a suffix of the trajectory's and log's names)."""
    from bench.peers.common import load_sequence, read_tum_trajectory

    s = load_sequence(seq_dir)
    fx, fy, cx, cy = s.intrinsics
    traj = out / "orbslam3" / f"{seq}{tag}_run{run}.tum"
    traj.parent.mkdir(parents=True, exist_ok=True)
    traj.unlink(missing_ok=True)
    images = images or KITTI / "sequences" / seq / "image_0"
    cmd = [python, str(PEERS / "orbslam3_traj.py"), str(images), "--fx", str(fx),
           "--fy", str(fy), "--cx", str(cx), "--cy", str(cy), "--vocab", str(vocab), "--fps", str(ORB_FPS),
           "--realtime", "--out", str(traj)]
    rc, cpu, wall, text = run_child(cmd, out / "logs" / f"orbslam3_{seq}{tag}_run{run}.log", timeout)
    last = re.search(r"tracked=(\d+)/(\d+) saved=(\d+).*?vocab_load_s=([\d.]+)", text)
    res = {"cpu_s": cpu, "wall_s": wall, "exit": rc, "command": cmd, "vocab": str(vocab),
           "vocab_load_s": float(last.group(4)) if last else None}
    if not traj.is_file() or traj.stat().st_size == 0:
        tail = text.strip().splitlines()[-1:] or ["no output"]
        return {**res, "note": f"no trajectory (exit {rc}): {tail[0][:200]}"}
    ts, poses = read_tum_trajectory(traj)
    return {**res, "ts": orb_timestamps(ts, s.timestamps[first:]), "poses": poses}


def run_vo(seq_dir: Path) -> dict:
    from bench.peers.textbook_vo import run_textbook_vo

    r = run_textbook_vo(seq_dir)
    return {"ts": r["timestamps"], "poses": r["poses"], "cpu_s": r["cpu_seconds"], "wall_s": r["seconds"]}


# ------------------------------------------------------------------------------------------------ table
def _cell(v: float, fmt: str) -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, fmt)


def span(vals: list[float], fmt: str) -> str:
    vals = [v for v in vals if v is not None and np.isfinite(v)]
    if not vals:
        return "-"
    lo, hi = min(vals), max(vals)
    return format(lo, fmt) if len(vals) == 1 or format(lo, fmt) == format(hi, fmt) else \
        f"{format(lo, fmt)}-{format(hi, fmt)}"


def table(rows: list[dict]) -> list[str]:
    """Markdown rows: one per (sequence, method); a method with several runs shows each figure's range.  ATE and RPE
    from the first frame with measured ground truth on (``scored from``), the ATE over every frame beside them."""
    out = ["| sequence | method | runs | scored from | ATE m | ATE % | ATE m, all frames | RPE m/frame | RPE deg/frame "
           "| posed / total | CPU ms/frame |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        runs = r.get("runs") or []
        if not runs:
            out.append(f"| {r['sequence']} | {r['method']} | 0 | | {r.get('note', '-')} | | | | | | |")
            continue
        posed = span([x["posed"] for x in runs], "d")
        tried = r.get("attempted", len(runs))
        n = str(len(runs)) if tried == len(runs) else f"{len(runs)} of {tried}"
        out.append(f"| {r['sequence']} | {r['method']} | {n} | frame {runs[0].get('first', 0)} | "
                   f"{span([x['ate_m'] for x in runs], '.3f')} | {span([x['ate_pct'] for x in runs], '.2f')} | "
                   f"{span([x.get('ate_all_m') for x in runs], '.3f')} | {span([x['rpe_t_m'] for x in runs], '.3f')} | "
                   f"{span([x['rpe_r_deg'] for x in runs], '.3f')} | {posed} / {runs[0]['total']} | "
                   f"{span([x['cpu_ms_per_frame'] for x in runs], '.0f')} |")
    return out


def _labels(run: dict) -> str:
    """``; size smaller, ORB-SLAM3 run 2``: which pvslam size and which ORB-SLAM3 run a figure is of, if any."""
    parts = ([f"size {run['size']}"] if "size" in run else []) + \
        ([f"ORB-SLAM3 run {run['orb_run'] + 1}"] if "orb_run" in run else [])
    return "".join(f"; {p}" for p in parts)


def run_details(rows: list[dict]) -> list[str]:
    """One line per method with several runs: each run's ATE and frames posed (ranges hide which run posed what)."""
    out = []
    for r in rows:
        if len(r.get("runs") or []) > 1:
            runs = ", ".join(f"{x['ate_m']:.3f} m = {x['ate_pct']:.2f} % (all frames "
                             f"{x.get('ate_all_m', math.nan):.3f} m; {x['posed']}/{x['total']} frames{_labels(x)})"
                             for x in r["runs"])
            out.append(f"{r['sequence']} {r['method']}, each run: {runs}")
    return out


def evaluate(method: str, res: dict, gt_ts: np.ndarray, gt: np.ndarray, total: int, first: int = 0) -> dict:
    """One run's scores (or its error; ``first``: :func:`score`'s) plus CPU per frame of the sequence's ``total``
    frames."""
    keep = {k: v for k, v in res.items() if k not in ("ts", "poses")}
    if "ts" not in res:
        return {**keep, "method": method}
    s = score(res["ts"], res["poses"], gt_ts, gt, total, res.get("posed"), first)
    return {**keep, **s, "method": method, "cpu_ms_per_frame": _ms(res.get("cpu_s", math.nan), total)}


def on_frames(res: dict, ts: np.ndarray, gt_ts: np.ndarray, gt: np.ndarray, total: int, first: int = 0) -> dict:
    """``res``'s scores over the frames at timestamps ``ts`` only (another method's posed frames), aligned on those:
    an ATE over a part of a sequence is comparable only with an ATE over the same part."""
    from bench.peers.common import _associate

    own, ts = np.asarray(res["ts"], np.float64), np.asarray(ts, np.float64)
    sel = _associate(own, ts, MAX_DIFF)[0] if len(ts) else np.zeros(0, dtype=np.int64)
    s = score(own[sel], np.asarray(res["poses"])[sel], gt_ts, gt, total, first=first)
    return {**s, "cpu_ms_per_frame": math.nan}


def bench_sequence(seq: str, out: Path, args, vocab: Optional[str]) -> list[dict]:
    seq_dir = kitti_as_tum(seq, out / "peers")
    gt_ts, gt = read_gt(seq_dir)
    total, first = len(gt_ts), measured_from(gt)
    if first:
        print(f"[{seq}] ground truth of frames 0-{first - 1} is extrapolated: scored from frame {first} on, "
              "all frames beside", flush=True)
    rows = []
    pv_res, pv = [], []
    for tag, extra in size_variants(args.size_spread):
        print(f"[{seq}] pvslam{tag.replace('_', ', processing area ')} ...", flush=True)
        pv_res.append(run_pvslam(seq, out, args.timeout, [*extra, *variant_args(args)], tag))
        pv.append({**evaluate("pvslam", pv_res[-1], gt_ts, gt, total, first), "size": tag.strip("_") or "default"})
    rows.append({"sequence": seq, "method": "pvslam", "runs": [r for r in pv if "ate_m" in r],
                 "note": "; ".join(r["error"] for r in pv if "error" in r)})
    note = orb_missing(args.orb_python, vocab, PEERS / "orbslam3_traj.py")
    orb_runs, same = [], []
    if note is None:
        for k in range(args.orb_runs):
            print(f"[{seq}] ORB-SLAM3 run {k + 1}/{args.orb_runs} ...", flush=True)
            orb = run_orb(seq, seq_dir, args.orb_python, vocab, k, out, args.timeout)
            orb_runs.append(evaluate("orbslam3", orb, gt_ts, gt, total, first))
            if "ts" in orb and "ate_m" in orb_runs[-1]:
                same += [{**on_frames(r, orb["ts"], gt_ts, gt, total, first), "method": "pvslam", "orb_run": k,
                          "size": p["size"]} for r, p in zip(pv_res, pv) if "ts" in r]
    else:
        print(f"[{seq}] ORB-SLAM3 skipped: {note}", flush=True)
    rows.append({"sequence": seq, "method": "orbslam3", "runs": [r for r in orb_runs if "ate_m" in r],
                 "failed_runs": [r for r in orb_runs if "ate_m" not in r], "attempted": len(orb_runs), "vocab": vocab,
                 "note": note or "; ".join(r.get("note", "") for r in orb_runs if "ate_m" not in r)})
    rows.append({"sequence": seq, "method": SAME_FRAMES, "runs": [r for r in same if np.isfinite(r["ate_m"])],
                 "note": "no ORB-SLAM3 trajectory" if not same else ""})
    print(f"[{seq}] textbook VO ...", flush=True)
    rows.append({"sequence": seq, "method": "textbook_vo", "runs": [evaluate("textbook_vo", run_vo(seq_dir), gt_ts,
                                                                             gt, total, first)], "note": ""})
    return rows


def vocab_for(specs: list[str], seq: str) -> Optional[str]:
    """``--orb-vocab`` values (``PATH`` for every sequence, ``SEQ=PATH`` for one, the latter first)."""
    for s in specs:
        if "=" in s and s.split("=", 1)[0] == seq:
            return s.split("=", 1)[1]
    plain = [s for s in specs if not re.match(r"^\d\d=", s)]
    return plain[-1] if plain else None


def add_peer_options(ap: argparse.ArgumentParser, per: str) -> None:
    """The ORB-SLAM3 options (``per``: what ``--orb-runs`` counts runs of) and the child processes' timeout."""
    ap.add_argument("--orb-python", help="python of the venv with pyorbslam3 (default: $PVSLAM_ORB_PYTHON; "
                    "skipped without it)")
    ap.add_argument("--orb-vocab", action="append", default=[], metavar="[SEQ=]PATH",
                    help="ORB vocabulary trained on other images: PATH for every sequence, SEQ=PATH for one "
                    f"(repeatable; default: $PVSLAM_ORB_VOCAB, the same separated by '{os.pathsep}')")
    ap.add_argument("--orb-runs", type=int, default=3, help=f"ORB-SLAM3 runs per {per} (default 3)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per child process (default 1800)")


def add_variant_option(ap: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE``: a config override for every pvslam run, to screen a variant on the real excerpts (with
    ``--orb-runs 0`` in minutes); the result file records it and ``figures.py`` refuses such a file."""
    ap.add_argument("--set", action="append", default=[], dest="overrides", metavar="KEY=VALUE",
                    help="config override for every pvslam run (repeatable; a variant, not the figures)")


def variant_args(args: argparse.Namespace) -> list[str]:
    """pvslam's command-line arguments for ``args.overrides``."""
    return [a for kv in getattr(args, "overrides", []) for a in ("--set", kv)]


def peers_from_environment(args: argparse.Namespace) -> argparse.Namespace:
    """``args`` with the ORB-SLAM3 python and vocabularies from the environment where the options gave none: where
    ORB-SLAM3 lives is the machine's business, and figures.py runs the tools without options."""
    args.orb_python = args.orb_python or os.environ.get("PVSLAM_ORB_PYTHON") or None
    args.orb_vocab = args.orb_vocab or [v for v in os.environ.get("PVSLAM_ORB_VOCAB", "").split(os.pathsep) if v]
    return args


def excerpts_missing(sequences: Sequence[str]) -> Optional[str]:
    """What is missing of the KITTI excerpts ``sequences`` (a message), or None."""
    if not (KITTI / "sequences").is_dir():
        return f"no KITTI excerpts at {KITTI} (../shared/data, or set PVSLAM_KITTI)"
    missing = [s for s in sequences if not (KITTI / "sequences" / s / "image_0").is_dir()]
    return f"KITTI excerpt(s) {missing} not in {KITTI / 'sequences'}" if missing else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", nargs="+", default=list(SEQUENCES), help="KITTI excerpts (default: 00 06 01)")
    add_peer_options(ap, "sequence")
    add_variant_option(ap)
    ap.add_argument("--size-spread", type=float, default=2.0, metavar="PCT",
                    help="pvslam also with the processing area PCT %% per side smaller and larger: how much its "
                    "result moves with the input's size (default 2; 0: one run)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench" / "real"), help="folder for run directories, "
                    "ORB-SLAM3 trajectories and logs (default runs/bench/real)")
    ap.add_argument("--json", default=str(ROOT / "runs" / "bench" / "real.json"),
                    help="result file with provenance (default runs/bench/real.json; not into bench/)")
    ap.add_argument("--reprint", metavar="JSON", help="print the table of a saved result file and stop")
    args = peers_from_environment(ap.parse_args(argv))
    if args.reprint:
        saved = provenance.read_json(args.reprint)
        print(f"commit {saved['provenance']['commit']} (dirty: {saved['provenance'].get('dirty')})")
        print("\n".join(table(saved["rows"]) + run_details(saved["rows"])))
        return 0
    missing = excerpts_missing(args.sequences)
    if missing:
        print(f"pvslam: error: {missing}", file=sys.stderr)
        return 2
    try:
        prov = provenance.check(args.json)
    except provenance.ProvenanceError as exc:
        return provenance.fail(exc)
    out = Path(args.out).resolve()
    rows = []
    for seq in args.sequences:
        rows += bench_sequence(seq, out, args, vocab_for(args.orb_vocab, seq))
    lines = table(rows) + run_details(rows)
    print("\n".join(lines))
    for r in rows:
        if r["method"] == "orbslam3" and r.get("note"):
            print(f"note: {r['sequence']} ORB-SLAM3: {r['note']}")
    path = provenance.write_json(args.json, {"sequences": args.sequences, "overrides": args.overrides,
                                             "orb_runs": args.orb_runs,
                                             "orb_vocab": args.orb_vocab, "orb_python": args.orb_python,
                                             "size_spread": args.size_spread, "rows": rows, "table": lines}, prov)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
