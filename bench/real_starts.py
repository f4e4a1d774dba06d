"""pvslam and ORB-SLAM3 started from several frames of each real excerpt: how much one excerpt's ATE owes to where
it starts.

    python bench/real_starts.py                                    # 00, 06, 01 from frames 0, 5, 10, 20
    python bench/real_starts.py --sequences 00 --starts 0 10 --orb-runs 1
    PVSLAM_ORB_PYTHON=... PVSLAM_ORB_VOCAB=00=VOC_A:VOC_B python bench/real_starts.py   # as bench/bench_real.py

A real excerpt scored from its first frame is one draw: a monocular map's scale is set by the few frames it
initialises on and drifts from there, so the same method started a few frames later can score very differently.
Per excerpt and start frame ``S``: pvslam exactly as a user runs it plus ``--set dataset.start=S`` (one run: it
repeats exactly), and ORB-SLAM3 ``--orb-runs`` times on a folder of the excerpt's frames from ``S`` on (links).
The scores begin at the first frame with measured ground truth (:func:`bench.matrix_jobs.measured_from`), or at
``S`` where that is later.  pvslam is scored over all its frames and over each ORB-SLAM3 run's posed frames
(aligned on those: an ATE over a part of a sequence is comparable only with one over the same part;
:func:`bench.bench_real.on_frames`).  Printed per
excerpt: a row per start, and on how many starts pvslam is at or below ORB-SLAM3's best run and its median run.
ORB-SLAM3 paces frames at 10 frames/s and loses them when the machine is busy: run this on a quiet machine.  The
result file (``--json``, default ``runs/bench/real_starts.json``) records the provenance.
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_real as R  # noqa: E402
from bench import provenance  # noqa: E402
from bench.matrix_jobs import KITTI, kitti_as_tum, measured_from, read_gt  # noqa: E402

STARTS = (0, 5, 10, 20)


def frames_from(seq: str, first: int, out: Path) -> Path:
    """A folder of links to excerpt ``seq``'s frames from frame ``first`` on (ORB-SLAM3's runner reads a folder)."""
    images = sorted((KITTI / "sequences" / seq / "image_0").glob("*.png"))
    if not 0 <= first < len(images) - 2:
        raise ValueError(f"start frame {first}: excerpt {seq} has {len(images)} frames")
    folder = out / "frames" / f"{seq}_from{first}"
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.iterdir():
        old.unlink()
    for img in images[first:]:
        (folder / img.name).symlink_to(img.resolve())
    return folder


def compare(pv_on: Sequence[float], orb: Sequence[float]) -> dict:
    """pvslam's ATE over each ORB-SLAM3 run's frames (``pv_on[k]``) against that run's (``orb[k]``): whether pvslam is
    at or below ORB-SLAM3's best run (compared on that run's frames) and its median run (medians of both)."""
    ok = [k for k in range(len(orb)) if np.isfinite(orb[k]) and np.isfinite(pv_on[k])]
    if not ok:
        return {"best": None, "median": None}
    best = min(ok, key=lambda k: orb[k])
    return {"best": bool(pv_on[best] <= orb[best]),
            "median": bool(statistics.median(pv_on[k] for k in ok) <= statistics.median(orb[k] for k in ok))}


def bench_start(seq: str, first: int, out: Path, args, vocab: Optional[str], seq_dir: Path, gt: tuple) -> dict:
    """Excerpt ``seq`` (its TUM folder ``seq_dir``, ground truth ``gt = (timestamps, poses)``) from frame ``first``:
    pvslam once, ORB-SLAM3 ``args.orb_runs`` times, pvslam scored on each ORB-SLAM3 run's frames."""
    gt_ts, gt_poses = gt
    total = len(gt_ts) - first
    scored = max(first, measured_from(gt_poses))  # the first frame with measured ground truth
    tag = f"_from{first}"
    print(f"[{seq} from {first}] pvslam ...", flush=True)
    pv = R.run_pvslam(seq, out, args.timeout, ["--set", f"dataset.start={first}", *R.variant_args(args)], tag)
    row = {"sequence": seq, "start": first, "pvslam": R.evaluate("pvslam", pv, gt_ts, gt_poses, total, scored),
           "orbslam3": [], "pvslam_on_orb": []}
    note = R.orb_missing(args.orb_python, vocab, R.PEERS / "orbslam3_traj.py")
    if note is not None:
        return {**row, "note": note}
    images = frames_from(seq, first, out)
    for k in range(args.orb_runs):
        print(f"[{seq} from {first}] ORB-SLAM3 run {k + 1}/{args.orb_runs} ...", flush=True)
        orb = R.run_orb(seq, seq_dir, args.orb_python, vocab, k, out, args.timeout, images, first, tag)
        row["orbslam3"].append(R.evaluate("orbslam3", orb, gt_ts, gt_poses, total, scored))
        on = R.on_frames(pv, orb["ts"], gt_ts, gt_poses, total, scored) if "ts" in orb and "ts" in pv else {}
        row["pvslam_on_orb"].append(on.get("ate_m", float("nan")))
    orb_ate = [r.get("ate_m", float("nan")) for r in row["orbslam3"]]
    return {**row, "ahead": compare(row["pvslam_on_orb"], orb_ate)}


def lines(rows: list[dict]) -> list[str]:
    out = ["| sequence | start | scored from | pvslam ATE m (its frames) | pvslam on ORB-SLAM3's frames | "
           "ORB-SLAM3 ATE m | ORB-SLAM3 frames | at or below ORB-SLAM3's best / median |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        orb = [x.get("ate_m", float("nan")) for x in r["orbslam3"]]
        posed = [x["posed"] for x in r["orbslam3"] if "posed" in x]
        ahead = r.get("ahead") or {}
        yes = {True: "yes", False: "no", None: "-"}
        out.append(f"| {r['sequence']} | {r['start']} | frame {r['pvslam'].get('first', r['start'])} | "
                   f"{R._cell(r['pvslam'].get('ate_m'), '.3f')} | "
                   f"{R.span(r['pvslam_on_orb'], '.3f')} | {R.span(orb, '.3f') if orb else r.get('note', '-')} | "
                   f"{R.span(posed, 'd')} / {r['pvslam'].get('total', '-')} | "
                   f"{yes[ahead.get('best')]} / {yes[ahead.get('median')]} |")
    for seq in dict.fromkeys(r["sequence"] for r in rows):
        got = [r["ahead"] for r in rows if r["sequence"] == seq and r.get("ahead", {}).get("best") is not None]
        if got:
            out.append(f"{seq}: pvslam at or below ORB-SLAM3's best run from {sum(a['best'] for a in got)} of "
                       f"{len(got)} starts, its median run from {sum(a['median'] for a in got)} of {len(got)}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", nargs="+", default=list(R.SEQUENCES), help="KITTI excerpts (default: 00 06 01)")
    ap.add_argument("--starts", type=int, nargs="+", default=list(STARTS), help="start frames (default 0 5 10 20)")
    R.add_peer_options(ap, "start")
    R.add_variant_option(ap)
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench" / "real_starts"), help="folder for run "
                    "directories, frame links, trajectories and logs (default runs/bench/real_starts)")
    ap.add_argument("--json", default=str(ROOT / "runs" / "bench" / "real_starts.json"),
                    help="result file with provenance (default runs/bench/real_starts.json)")
    args = R.peers_from_environment(ap.parse_args(argv))
    missing = R.excerpts_missing(args.sequences)
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
        seq_dir = kitti_as_tum(seq, out / "peers")
        gt = read_gt(seq_dir)
        for first in args.starts:
            rows.append(bench_start(seq, first, out, args, R.vocab_for(args.orb_vocab, seq), seq_dir, gt))
    text = lines(rows)
    print("\n".join(text))
    path = provenance.write_json(args.json, {"sequences": args.sequences, "starts": args.starts,
                                             "overrides": args.overrides,
                                             "orb_runs": args.orb_runs, "orb_vocab": args.orb_vocab,
                                             "rows": rows, "table": text}, prov)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
