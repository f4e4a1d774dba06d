"""The loop detectors on real frames: no false loop on the KITTI excerpts, and a real revisit's precision and recall.

    python bench/loops_real.py                      # classical and deit, every excerpt + the revisit
    python bench/loops_real.py --plugins classical --json runs/bench/loops_real.json

The detectors are fed as the mapper feeds them (``add_keyframe`` of every keyframe, then ``query`` with geometric
verification), on frames read by the ``kitti`` reader at the processing size of ``configs/kitti.toml`` (half size,
616x184), without a SLAM run:

* **excerpts** (none revisits a place): every ``stride``-th frame is a keyframe.  The temporal exclusion keeps the
  detector's ``exclude_recent`` (keyframes) but drops ``min_time_gap`` (10 s: longer than the 06 and 01 excerpts,
  so nothing would be compared there), so every pair more than ``exclude_recent`` keyframes apart is compared.
  Reported: the retrieved and the verified candidates (every verified one is a false loop unless the ground truth
  puts the two frames at one place), and the best-scoring pair of different places against its threshold, with
  the verification's result on it;
* **revisit** (KITTI 00): a first pass over frames 0-159, then, after ``REVISIT_GAP_S`` seconds (the drive back),
  a second pass starting from an earlier frame on frames the first pass skipped (never the same image).  A verified
  pair is a true loop when the ground truth puts the cameras within ``SAME_PLACE_M`` metres and ``SAME_PLACE_DEG``
  degrees (one street view); a query is a revisit when a stored keyframe outside the exclusion is within
  ``REVISIT_M`` metres and ``SAME_PLACE_DEG`` degrees.  Precision: true verified pairs / all verified pairs;
  recall: revisits with a true verified pair / revisits.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path
from typing import Any, Optional

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import provenance  # noqa: E402
from bench.matrix_jobs import KITTI  # noqa: E402

SIZE = (616, 184)  # (width, height): KITTI at half size, configs/kitti.toml's processing size
SAME_PLACE_M = 10.0  # ground truth: two cameras within this distance ...
SAME_PLACE_DEG = 30.0  # ... and this difference of orientation see one place (a verified pair there is true)
REVISIT_M = 5.0  # a query whose place a stored keyframe this close shows is a revisit (recall counts it)
REVISIT_GAP_S = 10.0  # seconds between the end of the first pass and the start of the second (the drive back)
# keyframe spacing on the excerpts in frames (the default run makes nearly every frame a keyframe)
EXCERPT_STRIDE = {"00": 1, "06": 1, "01": 1}
REVISIT = {"first_stride": 2, "second_start": 21, "second_stride": 4}
PLUGINS = ("classical", "deit")  # the detectors of the current figure: the default and the paper's
SEQUENCES = ("00", "06", "01")  # the KITTI excerpts in ../shared/data


def read_frames(seq: str, indices: list[int]) -> list[Any]:
    """The frames ``indices`` of a KITTI excerpt as the ``kitti`` reader yields them at :data:`SIZE`."""
    from pvslam_plugins.datasets.kitti.config import KittiConfig
    from pvslam_plugins.datasets.kitti.reader import make_reader

    kitti_log = logging.getLogger("pvslam_plugins.datasets.kitti")
    level = kitti_log.level
    kitti_log.setLevel(logging.ERROR)  # "no times.txt: 10 Hz", for this reader only
    try:
        reader = make_reader(KittiConfig(path=str(KITTI), sequence=seq, resize=list(SIZE)))
    finally:
        kitti_log.setLevel(level)
    return [reader[i] for i in indices]


def make_detector(plugin: str, **overrides: Any):
    """The ``plugin`` loop detector with its default config (plus ``overrides``)."""
    if plugin == "classical":
        from pvslam_plugins.loops.classical.config import ClassicalLoopConfig
        from pvslam_plugins.loops.classical.detector import ClassicalLoopDetector

        return ClassicalLoopDetector(ClassicalLoopConfig(**overrides))
    if plugin == "deit":
        from pvslam_plugins.loops.deit.config import DeitLoopConfig
        from pvslam_plugins.loops.deit.detector import DeitLoopDetector

        return DeitLoopDetector(DeitLoopConfig(**overrides))
    raise ValueError(f"unknown loop plugin {plugin!r} (classical, deit)")


def same_place(a: np.ndarray, b: np.ndarray, radius_m: float = SAME_PLACE_M) -> np.ndarray:
    """[n, m] bool: the ground-truth poses ``a`` [n, 7] and ``b`` [m, 7] (T_wc) are within ``radius_m`` metres and
    ``SAME_PLACE_DEG`` degrees of each other."""
    from scipy.spatial.transform import Rotation

    d = np.linalg.norm(a[:, None, :3] - b[None, :, :3], axis=2)
    qa, qb = a[:, 3:] / np.linalg.norm(a[:, 3:], axis=1, keepdims=True), b[:, 3:] / np.linalg.norm(b[:, 3:], axis=1,
                                                                                                    keepdims=True)
    ang = np.degrees(2 * np.arccos(np.clip(np.abs(qa @ qb.T), 0.0, 1.0)))
    return (d <= radius_m) & (ang <= SAME_PLACE_DEG)


def play(detector, frames: list[Any], timestamps: list[float]) -> list[dict]:
    """Feed ``frames`` as keyframes 0..n-1 (at ``timestamps``), query each after adding it: every verified pair
    ``{i, j, score, accepted, inliers, matches}`` (keyframe numbers)."""
    out = []
    for k, (f, t) in enumerate(zip(frames, timestamps)):
        detector.add_keyframe(k, dataclasses.replace(f, index=k, timestamp=float(t)))
        detector.query(k)
        out += [{"i": int(i), "j": int(j), "score": float(s), "accepted": bool(v.accepted), "inliers": int(v.inliers),
                 "matches": int(v.matches)} for i, j, s, v in detector.last_verifications]
    return out


def _similarity(detector) -> np.ndarray:
    s = detector.similarity_matrix()
    return s.numpy() if hasattr(s, "numpy") else np.asarray(s)


def _eligible(n: int, times: np.ndarray, exclude_recent: int, min_time_gap: float) -> np.ndarray:
    """[n, n] bool: (i, j) with j more than ``exclude_recent`` keyframes and ``min_time_gap`` seconds before i."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return (i - j > exclude_recent) & (times[:, None] - times[None, :] >= min_time_gap)


def _threshold(detector, k: int) -> float:
    """The retrieval threshold keyframe ``k`` met (the classical detector's adaptive one, or the config's)."""
    if hasattr(detector, "_threshold"):
        return float(detector._threshold(detector._row(k)))
    return float(detector.config.threshold)


def _verdict(detector, i: int, j: int) -> dict:
    v = detector.verifier.verify(i, j)
    return {"accepted": bool(v.accepted), "inliers": int(v.inliers), "matches": int(v.matches)}


def excerpt_report(plugin: str, seq: str, stride: Optional[int] = None, **overrides: Any) -> dict:
    """The detector on one excerpt (no revisit): its candidates, false loops and best wrong pair (module doc);
    ``overrides`` of the detector's config (e.g. ``exclude_recent`` for a larger ``stride``)."""
    det = make_detector(plugin, **{"min_time_gap": 0.0, **overrides})
    n_frames = len(sorted((KITTI / "sequences" / seq / "image_0").glob("*.png")))
    idx = list(range(0, n_frames, stride or EXCERPT_STRIDE.get(seq, 1)))
    frames = read_frames(seq, idx)
    times = np.array([f.timestamp for f in frames])
    gt = np.stack([f.gt_pose.double().numpy() for f in frames])
    verified = play(det, frames, times)
    place = same_place(gt, gt)
    wrong = _eligible(len(frames), times, det.config.exclude_recent, 0.0) & ~place
    sim = _similarity(det)
    out: dict[str, Any] = {"plugin": plugin, "sequence": seq, "keyframes": len(frames), "stride": idx[1] - idx[0],
                           "retrieved": len(verified), "false_loops": [v for v in verified
                                                                        if v["accepted"] and not place[v["i"], v["j"]]]}
    if wrong.any():
        i, j = np.unravel_index(np.argmax(np.where(wrong, sim, -np.inf)), sim.shape)
        out["best_wrong"] = {"frame_i": idx[i], "frame_j": idx[j], "score": float(sim[i, j]),
                             "threshold": _threshold(det, int(i)), "distance_m": float(np.linalg.norm(
                                 gt[i, :3] - gt[j, :3])), **_verdict(det, int(i), int(j))}
    return out


def revisit_frames(first_stride: int, second_start: int, second_stride: int, end: Optional[int] = None
                   ) -> tuple[list[int], list[float]]:
    """Frame numbers and timestamps of the KITTI 00 revisit: two passes over frames ``[0, end)`` (module doc)."""
    n = len(sorted((KITTI / "sequences" / "00" / "image_0").glob("*.png")))
    n = n if end is None else min(n, end)
    first = list(range(0, n, first_stride))
    second = list(range(second_start, n, second_stride))
    t_first = [0.1 * i for i in first]
    t0 = t_first[-1] + REVISIT_GAP_S
    return first + second, t_first + [t0 + 0.1 * (i - second[0]) for i in second]


def revisit_report(plugin: str, first_stride: int = REVISIT["first_stride"],
                   second_start: int = REVISIT["second_start"], second_stride: int = REVISIT["second_stride"],
                   end: Optional[int] = None) -> dict:
    """Precision and recall of the verified candidates on the KITTI 00 revisit (module doc): the first pass on every
    ``first_stride``-th frame, the second from ``second_start`` on every ``second_stride``-th, both before ``end``."""
    det = make_detector(plugin)
    order, times = revisit_frames(first_stride, second_start, second_stride, end)
    frames = read_frames("00", order)
    gt = np.stack([f.gt_pose.double().numpy() for f in frames])
    verified = play(det, frames, times)
    c = det.config
    eligible = _eligible(len(order), np.asarray(times), c.exclude_recent, c.min_time_gap)
    place = same_place(gt, gt) & eligible
    accepted = [v for v in verified if v["accepted"]]
    true = [v for v in accepted if place[v["i"], v["j"]]]
    queries = np.nonzero((same_place(gt, gt, REVISIT_M) & eligible).any(axis=1))[0]
    found = {v["i"] for v in true}
    wrong = [dict(v, frame_i=order[v["i"]], frame_j=order[v["j"]]) for v in accepted if not place[v["i"], v["j"]]]
    missed = [order[q] for q in queries if q not in found]
    return {"plugin": plugin, "keyframes": len(order), "queries_with_a_revisit": len(queries),
            "verified": len(accepted), "verified_true": len(true),
            "precision": len(true) / len(accepted) if accepted else float("nan"),
            "recall": len(found & set(queries.tolist())) / len(queries) if len(queries) else float("nan"),
            "false_loops": wrong, "missed_frames": missed, "seconds": det.timings}


def _lines(excerpts: list[dict], revisits: list[dict]) -> list[str]:
    out = ["| detector | excerpt | keyframes | retrieved | false loops | best wrong pair (frames) | "
           "score / threshold | its verification |", "|---|---|---|---|---|---|---|---|"]
    for e in excerpts:
        b = e.get("best_wrong")
        pair = f"{b['frame_i']} - {b['frame_j']} ({b['distance_m']:.0f} m apart)" if b else "none"
        score = f"{b['score']:.3f} / {b['threshold']:.3f}" if b else "-"
        ver = (f"{'accepted' if b['accepted'] else 'rejected'}: {b['inliers']} inliers of {b['matches']} matches"
               if b else "-")
        out.append(f"| {e['plugin']} | {e['sequence']} | {e['keyframes']} | {e['retrieved']} | {len(e['false_loops'])} "
                   f"| {pair} | {score} | {ver} |")
    out += ["", "| detector | revisit keyframes | queries with a revisit | verified | true | precision | recall |",
            "|---|---|---|---|---|---|---|"]
    for r in revisits:
        out.append(f"| {r['plugin']} | {r['keyframes']} | {r['queries_with_a_revisit']} | {r['verified']} | "
                   f"{r['verified_true']} | {r['precision']:.3f} | {r['recall']:.3f} |")
    return out


def report_problem(r: dict) -> Optional[str]:
    """What keeps a result file from being the current figure (bench/figures.py), or None."""
    plugins, seqs = tuple(r.get("plugins") or ()), tuple(r.get("sequences") or ())
    if plugins != PLUGINS or seqs != SEQUENCES:
        return (f"not every detector {list(PLUGINS)} on every excerpt {list(SEQUENCES)} (run without --plugins, "
                "--sequences)")
    return None


def figure(r: dict) -> tuple[str, str]:
    """False loops per detector on the excerpts, the best-scoring pair of different places against the threshold,
    and the revisit's precision and recall, as one row of the current-figures page."""
    parts = []
    for plugin in PLUGINS:
        ex = [e for e in r["excerpts"] if e["plugin"] == plugin]
        false = " / ".join(str(len(e["false_loops"])) for e in ex)
        best = max((e["best_wrong"] for e in ex if e.get("best_wrong")), key=lambda b: b["score"] - b["threshold"],
                   default=None)
        closest = ("no pair of different places scored" if best is None else
                   f"best wrong pair {best['score']:.3f} against its threshold {best['threshold']:.3f} "
                   f"({'accepted' if best['accepted'] else 'rejected by verification'})")
        rv = next(x for x in r["revisits"] if x["plugin"] == plugin)
        parts.append(f"`{plugin}`: false loops {false}, {closest}; "
                     f"revisit precision {rv['precision']:.2f}, recall {rv['recall']:.2f} "
                     f"({rv['queries_with_a_revisit']} revisiting keyframes)")
    return "; ".join(parts), "targets: no false loop on any excerpt; revisit precision 1.0, recall >= 0.8"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plugins", nargs="+", default=list(PLUGINS), help="loop detectors (default both)")
    ap.add_argument("--sequences", nargs="+", default=list(SEQUENCES), help="KITTI excerpts (default 00 06 01)")
    ap.add_argument("--json", help="result file with provenance (not into bench/)")
    args = ap.parse_args(argv)
    if not (KITTI / "sequences").is_dir():
        print(f"pvslam: error: no KITTI excerpts at {KITTI} (../shared/data, or set PVSLAM_KITTI)", file=sys.stderr)
        return 2
    prov = None
    if args.json:
        try:
            prov = provenance.check(args.json)
        except provenance.ProvenanceError as exc:
            return provenance.fail(exc)
    excerpts = [excerpt_report(p, s) for p in args.plugins for s in args.sequences]
    revisits = [revisit_report(p) for p in args.plugins]
    lines = _lines(excerpts, revisits)
    print("\n".join(lines))
    if args.json:
        path = provenance.write_json(args.json, {"plugins": list(args.plugins), "sequences": list(args.sequences),
                                                 "excerpts": excerpts, "revisits": revisits, "table": lines}, prov)
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
