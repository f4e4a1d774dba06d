"""Which pixels the ``flow`` frontend's dynamic masks take out of the BA, against the generator's exact dynamic masks.

    python bench/bench_dynamic_masks.py                                   # the sequences below, three segmenters
    python bench/bench_dynamic_masks.py --runs moving_vehicles:162 --segmenters panoptic_fpn --frames 150
    python bench/bench_dynamic_masks.py --runs kitti:06 --segmenters panoptic_fpn none   # ATE and masked share only
    python bench/bench_dynamic_masks.py --domain heldout --runs moving_vehicles:174 --segmenters panoptic_fpn none
    python bench/bench_dynamic_masks.py --report --jobs 2     # the held-out report of the current-figures page

For every edge the BA observes (each observation counted: an edge observed on 6 BA rounds counts 6 times), at the BA
resolution, each pixel of the edge's source keyframe is either *removed* (its eq. 4 mask is set: weight ~ c e^-eta)
or kept, and either *moving* (more than half of its block is moving in the generator's ``gt_dynamic``) or static.
Printed per ground-truth category (road, building, car, ...) and per segmenter:

  false dyn  removed pixels that do not move, as a share of that category's static pixels
  missed     moving pixels that are kept, as a share of that category's moving pixels
  w lost     the flow confidence taken out by eq. 4 on static pixels of the category, as a share of the confidence
             of all static pixels (what the masks cost the map; road and building hold the scale)
  by thing   share of the false-dynamic pixels that lie in a segment the segmenter called a movable thing (the
             segment vote) rather than in the geometric candidates alone

and the run's Sim(3) ATE.  ``--trace`` also prints, per keyframe in time order, the share of its view that moves and,
from the latest mask of each of its edges (averaged over them), the share of the moving pixels the masks hold and the
share of the view they mark that does not move: where a mover fills the view, a mask that lets go of it and marks the
background instead shows there.  Last, per segmenter, each run's ATE against ``none`` on the same sequence and how many
runs are more than 5 % worse (the target: none on held-out looks, ``--domain heldout``), each scenario's mean ATE per
segmenter and, on the scenarios whose vehicles move, the share of the oracle ``labels``' gain over ``none`` that the
segmenter reaches.  ``--report``: those figures on the ledger's ``segmenter`` seeds (bench/seeds.toml) of
``REPORT_SCENARIOS``, in the held-out looks, each scenario at its own length.  Results: ``--json`` (default
runs/bench/results_dynamic_masks.json) with the commit of the measured code (:mod:`bench.provenance`).  Torch runs with
one thread per process; ``--jobs`` runs that many at once.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import tempfile
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Optional

import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance, seeds  # noqa: E402

# held-out of panoptic_fpn's training (seeds 1-8) and of the seed ledger's tune/report sets (bench/seeds.toml)
DEFAULT_RUNS = ["moving_vehicles:162", "moving_vehicles:163", "moving_vehicles:164", "driving_block:162",
                "indoor_handheld:162"]
SCALE_BEARING = ("road", "sidewalk", "building", "wall", "floor", "terrain")
# the held-out report (--report): where a segmenter can only cost the map (parked cars; a room held in the hand) and
# where it should pay (streets whose vehicles move), in looks the shipped segmenter never saw
REPORT_SCENARIOS = ("driving_block", "indoor_handheld", "moving_vehicles", "busy_street")
MOVING = ("moving_vehicles", "busy_street")


class Tally:
    """Per ground-truth category: pixel counts and confidence sums of removed / kept, moving / static pixels."""

    def __init__(self) -> None:
        self.n = defaultdict(lambda: torch.zeros(6, dtype=torch.float64))
        # [static, static removed, moving, moving kept, static conf, static conf lost]
        self.kf: dict[int, tuple] = {}
        self.frame: dict[int, int] = {}  # keyframe id -> its frame index
        # (source id, target id) -> (share of the moving pixels removed or None, share of the view removed that does
        # not move) of the edge's latest observation
        self.last: dict[tuple[int, int], tuple[Optional[float], float]] = {}

    def add_keyframe(self, sid: int, frame, seg, h: int, w: int) -> None:
        from pvslam_plugins.frontends.flow.dynamic_masking import segment_info

        from pvslam_plugins.frontends.flow import flow_ops as F

        ids, things = segment_info(seg, h, w)
        self.frame[sid] = int(frame.index)
        in_thing = torch.zeros(h, w, dtype=torch.bool) if ids is None else torch.isin(ids, things)
        if frame.gt_dynamic is None or frame.gt_panoptic is None:  # no ground truth: the segmenter's word only
            self.kf[sid] = (None, None, in_thing)
            return
        dyn = torch.nn.functional.interpolate(frame.gt_dynamic[None, None].float(), size=(h, w), mode="area")[0, 0]
        cat = F.downsample_ids(frame.gt_panoptic.category_map(), h, w)
        self.kf[sid] = (dyn > 0.5, cat, in_thing)

    def observe(self, keys, dyn: torch.Tensor, conf: torch.Tensor, weight: torch.Tensor) -> None:
        for e, (sid, tgt) in enumerate(keys):
            if sid not in self.kf:
                continue
            moving, cat, in_thing = self.kf[sid]
            rem = dyn[e].cpu() > 0
            c, lost = conf[e].cpu().double(), (conf[e] - weight[e]).cpu().double()
            # every pixel, by the segmenter's word: [px, removed, removed in a movable thing, conf, lost, lost in one]
            self.n["all"] += torch.tensor([rem.numel(), float(rem.sum()), float((rem & in_thing).sum()),
                                           float(c.sum()), float(lost.sum()), float(lost[in_thing].sum())],
                                          dtype=torch.float64)
            if moving is None:
                continue
            n_mv = int(moving.sum())
            self.last[(sid, tgt)] = (float((rem & moving).sum()) / n_mv if n_mv else None,
                                     float((rem & ~moving).sum()) / rem.numel())
            for k in torch.unique(cat).tolist():
                m = cat == k
                st, mv = m & ~moving, m & moving
                self.n[k] += torch.stack([st.sum(), (st & rem).sum(), mv.sum(), (mv & ~rem).sum(),
                                          c[st].sum(), lost[st].sum()]).double()
                self.n[("thing", k)] += torch.tensor([float((st & rem & in_thing).sum()), 0, 0, 0, 0, 0],
                                                     dtype=torch.float64)


def instrument(tally: Tally):
    """Patch the flow frontend so that every keyframe and every observed edge reaches ``tally``.  Returns an undo."""
    from pvslam_plugins.frontends.flow.dynamic_masking import DynamicMasking
    from pvslam_plugins.frontends.flow.frontend import FlowFrontend

    orig_add, orig_obs = FlowFrontend.add_keyframe, DynamicMasking.observe

    def add_keyframe(self, kf_id, frame, seg):
        h, w = self._ba_shape_for(frame)
        tally.add_keyframe(int(kf_id), frame, seg, h, w)
        return orig_add(self, kf_id, frame, seg)

    def observe(self, graph, ii, jj, keys, target, conf):
        dyn, weight = orig_obs(self, graph, ii, jj, keys, target, conf)
        tally.observe(keys, dyn, conf, weight)
        return dyn, weight

    FlowFrontend.add_keyframe, DynamicMasking.observe = add_keyframe, observe

    def undo():
        FlowFrontend.add_keyframe, DynamicMasking.observe = orig_add, orig_obs
    return undo


def summarise(tally: Tally, names: dict[int, str]) -> dict:
    rows, tot_conf = {}, sum(float(v[4]) for k, v in tally.n.items() if isinstance(k, int))
    for k, v in sorted((k, v) for k, v in tally.n.items() if isinstance(k, int)):
        st, st_rem, mv, mv_kept, conf, lost = (float(x) for x in v)
        thing = float(tally.n[("thing", k)][0])
        rows[names.get(k, "void" if k < 0 else str(k))] = {
            "static_px": st, "false_dyn": st_rem / st if st else 0.0, "moving_px": mv,
            "missed": mv_kept / mv if mv else None, "w_lost_share": lost / tot_conf if tot_conf else 0.0,
            "by_thing": thing / st_rem if st_rem else None}
    lost_all = sum(r["w_lost_share"] for r in rows.values())
    scale = sum(r["w_lost_share"] for n, r in rows.items() if n in SCALE_BEARING)
    a = [float(x) for x in tally.n["all"]]
    every = {"removed": a[1] / a[0] if a[0] else 0.0, "removed_in_thing": a[2] / a[0] if a[0] else 0.0,
             "w_lost": a[4] / a[3] if a[3] else 0.0, "w_lost_in_thing": a[5] / a[3] if a[3] else 0.0}
    return {"categories": rows, "w_lost_static": lost_all, "w_lost_scale_bearing": scale, "all_pixels": every}


def trace(tally: Tally) -> list[dict]:
    """Per keyframe with ground truth, in frame order: ``frame``, ``moving`` (share of its view), ``held`` (share of
    its moving pixels removed, averaged over its edges' latest masks; None when nothing moves) and ``false`` (share
    of its view removed that does not move, averaged likewise)."""
    per: dict[int, list] = defaultdict(list)
    for (sid, _), v in tally.last.items():
        per[sid].append(v)
    rows = []
    for sid, vs in per.items():
        held = [v[0] for v in vs if v[0] is not None]
        rows.append({"frame": tally.frame.get(sid, -1), "moving": float(tally.kf[sid][0].float().mean()),
                     "held": sum(held) / len(held) if held else None, "false": sum(v[1] for v in vs) / len(vs)})
    return sorted(rows, key=lambda r: r["frame"])


def print_trace(rows: list[dict]) -> None:
    print(f"   {'frame':>5s} {'moving':>7s} {'held':>6s} {'false':>6s}")
    for r in rows:
        held = "-" if r["held"] is None else f"{100 * r['held']:.0f} %"
        print(f"   {r['frame']:5d} {100 * r['moving']:6.1f}% {held:>6s} {100 * r['false']:5.1f}%")


def print_summary(label: str, s: dict, ate: dict) -> None:
    print(f"-- {label}: ATE {ate.get('rmse', float('nan')):.4f} m ({ate.get('rmse_percent_of_path', float('nan')):.3f} "
          f"%); static confidence removed {100 * s['w_lost_static']:.2f} % (scale-bearing stuff "
          f"{100 * s['w_lost_scale_bearing']:.2f} %)")
    e = s["all_pixels"]
    print(f"   all pixels: removed {100 * e['removed']:.2f} % ({100 * e['removed_in_thing']:.2f} % in the segmenter's "
          f"movable things), confidence removed {100 * e['w_lost']:.2f} % ({100 * e['w_lost_in_thing']:.2f} % in them)")
    print(f"   {'category':11s} {'static px':>10s} {'false dyn':>9s} {'w lost':>7s} {'by thing':>8s} "
          f"{'moving px':>10s} {'missed':>7s}")
    for name, r in s["categories"].items():
        bt = "-" if r["by_thing"] is None else f"{100 * r['by_thing']:.0f} %"
        ms = "-" if r["missed"] is None else f"{100 * r['missed']:.1f} %"
        print(f"   {name:11s} {r['static_px']:10.0f} {100 * r['false_dyn']:8.2f}% {100 * r['w_lost_share']:6.2f}% "
              f"{bt:>8s} {r['moving_px']:10.0f} {ms:>7s}")


def run_one(scenario: str, seed: str, segmenter: str, frames: int, out: Path, overrides: list[str]) -> dict:
    """One run: ``scenario`` of the synthetic generator with ``seed`` (``frames`` 0: the scenario's own length), or
    ``kitti`` with ``seed`` the sequence of ``../shared/data/kitti-odometry`` (ATE only: no dynamic ground truth)."""
    from pvslam_core.api import run_config
    from pvslam_plugins.datasets.synthetic.scene import CATEGORIES

    common = [f'run.output_dir="{out.as_posix()}"', "run.progress=false", f'segmenter.plugin="{segmenter}"',
              f'run.name="dm-{scenario}-{seed}-{segmenter}"']
    if scenario == "kitti":
        cfg = ROOT / "configs" / "kitti.toml"
        data = ROOT.parent / "shared" / "data" / "kitti-odometry"
        ov = [f'dataset.path="{data.as_posix()}"', f'dataset.sequence="{seed}"']
    else:
        cfg = ROOT / "configs" / "moving_vehicles.toml"
        ov = [f'dataset.scenario="{scenario}"', f"dataset.seed={int(seed)}", 'dataset.gt_maps=["panoptic", "dynamic"]',
              *([f"dataset.num_frames={frames}"] if frames else [])]
    tally = Tally()
    undo = instrument(tally)
    try:
        r = run_config(str(cfg), overrides=[*common, *ov, *overrides])
    finally:
        undo()
    s = summarise(tally, {c.id: c.name for c in CATEGORIES})
    return {"scenario": scenario, "seed": seed, "segmenter": segmenter, "frames": frames,
            "ate": r.metrics.get("ate", {}), "keyframes": r.metrics["timing"]["keyframes"], **s,
            "trace": trace(tally)}


# a segmenter's run counts as worse than ``none`` beyond this ATE ratio: a run repeats exactly, but a small change of
# its weights moves it by a few per cent
WORSE = 1.05


def against_none(results: list[dict]) -> list[dict]:
    """Per segmenter other than ``none``: each run's ATE over ``none``'s on the same sequence (scenario and seed),
    how many runs are more than ``WORSE`` x worse, and the mean ATE of both over the sequences both ran.  The issue
    target is no run worse on held-out looks; sequences without a ``none`` run are left out."""
    ate = {(r["scenario"], str(r["seed"]), r["segmenter"]): float(r["ate"]["rmse"]) for r in results}
    rows = []
    for segm in dict.fromkeys(r["segmenter"] for r in results):
        if segm == "none":
            continue
        pairs = [(sc, sd, a, ate[(sc, sd, "none")]) for (sc, sd, s_), a in ate.items()
                 if s_ == segm and (sc, sd, "none") in ate]
        if not pairs:
            continue
        ratios = [a / n for _, _, a, n in pairs]
        rows.append({"segmenter": segm, "runs": [f"{sc}:{sd}" for sc, sd, _, _ in pairs], "ratios": ratios,
                     "worse": sum(r > WORSE for r in ratios), "mean_ate": sum(a for *_, a, _ in pairs) / len(pairs),
                     "mean_ate_none": sum(n for *_, n in pairs) / len(pairs)})
    return rows


def per_scenario(results: list[dict]) -> dict[str, dict[str, float]]:
    """Each scenario's mean ATE (m) per segmenter, over the seeds that every segmenter of the results ran."""
    ate = {(r["scenario"], str(r["seed"]), r["segmenter"]): float(r["ate"]["rmse"]) for r in results}
    segms = list(dict.fromkeys(r["segmenter"] for r in results))
    out: dict[str, dict[str, float]] = {}
    for sc in dict.fromkeys(r["scenario"] for r in results):
        both = [sd for sd in dict.fromkeys(str(r["seed"]) for r in results if r["scenario"] == sc)
                if all((sc, sd, g) in ate for g in segms)]
        if both:
            out[sc] = {g: sum(ate[(sc, sd, g)] for sd in both) / len(both) for g in segms}
    return out


def oracle_share(scenarios: dict[str, dict[str, float]], segmenter: str, moving=MOVING) -> Optional[float]:
    """The share of the oracle ``labels``' gain over ``none`` that ``segmenter`` reaches on the ``moving`` scenarios'
    mean ATE: 1 as good as the oracle, 0 no better than ``none``, negative worse; None where the oracle gains
    nothing or a scenario lacks a segmenter."""
    rows = [scenarios[sc] for sc in moving if sc in scenarios]
    if not rows or any(k not in r for r in rows for k in ("none", "labels", segmenter)):
        return None
    mean = {k: sum(r[k] for r in rows) / len(rows) for k in ("none", "labels", segmenter)}
    gain = mean["none"] - mean["labels"]
    return (mean["none"] - mean[segmenter]) / gain if gain > 0 else None


def print_against_none(rows: list[dict]) -> None:
    for r in rows:
        each = ", ".join(f"{run} {x:.2f}x" for run, x in zip(r["runs"], r["ratios"]))
        print(f"== {r['segmenter']} against none: {r['worse']} of {len(r['ratios'])} runs more than "
              f"{100 * (WORSE - 1):.0f} % worse; mean ATE {r['mean_ate']:.4f} m against {r['mean_ate_none']:.4f} m "
              f"({each})")


def report_problem(r: dict) -> Optional[str]:
    """What keeps a result file from being the current-figures report (bench/figures.py), or None."""
    if not r.get("report") or r.get("overrides"):
        return "not the held-out report (run with --report and no --set)"
    missing = [f"{sc}:{sd}" for sc, sd in (x.split(":") for x in report_runs())
               if {(sc, str(sd), g) for g in ("panoptic_fpn", "labels", "none")}
               - {(x["scenario"], str(x["seed"]), x["segmenter"]) for x in r.get("runs", [])}]
    return f"runs missing: {', '.join(missing)}" if missing else None


def figure(r: dict) -> tuple[str, str]:
    """The report as one row of the current-figures page: the shipped segmenter's mean ATE per scenario beside the
    oracle's and ``none``'s, its runs more than ``WORSE`` x worse than ``none``, and its share of the oracle's gain."""
    scen = r["scenarios"]
    each = "; ".join(f"{sc} {m['panoptic_fpn']:.3f} / {m['labels']:.3f} / {m['none']:.3f}" for sc, m in scen.items())
    row = next(x for x in r["against_none"] if x["segmenter"] == "panoptic_fpn")
    worse = [f"{run} {x:.2f}x" for run, x in zip(row["runs"], row["ratios"]) if x > WORSE]
    share = r["oracle_share"].get("panoptic_fpn")
    moving = " and ".join(MOVING)
    gain = (f"on {moving} it reaches {100 * share:.0f} % of the oracle's gain" if share is not None else
            f"on {moving} the oracle itself is no better than `none` on the mean")
    value = (f"mean ATE m, `panoptic_fpn` / oracle `labels` / `none`: {each}; `panoptic_fpn` more than "
             f"{100 * (WORSE - 1):.0f} % worse than `none` on **{row['worse']} of {len(row['ratios'])}** runs"
             f"{' (' + ', '.join(worse) + ')' if worse else ''}; {gain}")
    return value, "targets: no run worse than `none`; better than `none` on the moving-vehicle scenarios' mean"


def _summary(results: list[dict], segmenters: list[str]) -> dict:
    """The figures over ``results``: :func:`against_none`, :func:`per_scenario` and each learned segmenter's
    :func:`oracle_share`."""
    scen = per_scenario(results)
    return {"against_none": against_none(results), "scenarios": scen,
            "oracle_share": {g: oracle_share(scen, g) for g in segmenters if g not in ("none", "labels")}}


def report_runs() -> list[str]:
    """``--report``'s sequences: ``REPORT_SCENARIOS`` x the seed ledger's ``segmenter`` set."""
    return [f"{sc}:{sd}" for sc in REPORT_SCENARIOS for sd in seeds.load().sets["segmenter"]]


def run_cell(job: tuple) -> dict:
    """One (sequence, segmenter) run in its own temporary folder: ``job = (scenario, seed, segmenter, frames,
    overrides, threads)``; the result of :func:`run_one` with its process CPU seconds."""
    scenario, seed, segm, frames, overrides, threads = job
    torch.set_num_threads(threads)
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        res = run_one(scenario, seed, segm, frames, Path(tmp), overrides)
    res["cpu_s"] = time.process_time() - t0
    return res


def _cells(jobs: list[tuple], n: int):
    """The results of :func:`run_cell` over ``jobs`` as they finish, on ``n`` processes (1: this one)."""
    if n <= 1:
        for job in jobs:
            yield run_cell(job)
        return
    with ProcessPoolExecutor(n, mp_context=mp.get_context("spawn")) as ex:
        for fut in as_completed([ex.submit(run_cell, job) for job in jobs]):
            yield fut.result()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", default=DEFAULT_RUNS, help="scenario:seed of the synthetic generator")
    ap.add_argument("--segmenters", nargs="+", default=["panoptic_fpn", "labels", "none"])
    ap.add_argument("--frames", type=int, default=150, help="frames of a synthetic run (0: the scenario's own)")
    ap.add_argument("--domain", choices=["train", "heldout"], help="the generator's restyled looks (dataset.domain): "
                    "'heldout' are texture families and sizes the shipped segmenter never saw")
    ap.add_argument("--report", action="store_true", help="the held-out report: REPORT_SCENARIOS x the ledger's "
                    "'segmenter' seeds, held-out looks, each at its own length, the three segmenters")
    ap.add_argument("--trace", action="store_true", help="also print each keyframe's moving share and how much of "
                    "it the masks hold (the JSON has it always)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="extra config override")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=1, help="runs at once, each in its own process (default 1)")
    ap.add_argument("--json", default=str(provenance.RESULTS_DIR / "results_dynamic_masks.json"))
    args = ap.parse_args(argv)
    if args.report:
        args.runs, args.domain, args.frames = report_runs(), "heldout", 0
        args.segmenters = ["panoptic_fpn", "labels", "none"]
    try:
        prov = provenance.check(args.json)
    except provenance.ProvenanceError as exc:
        return provenance.fail(exc)
    overrides = [*([f'dataset.domain="{args.domain}"'] if args.domain else []), *args.overrides]
    jobs = [(sc, sd, segm, args.frames, overrides, args.threads)
            for sc, sd in (spec.split(":") for spec in args.runs) for segm in args.segmenters
            if not (sc == "kitti" and segm == "labels")]  # no panoptic ground truth
    order = {job[:3]: k for k, job in enumerate(jobs)}
    results, summary = [], _summary([], args.segmenters)
    for res in _cells(jobs, args.jobs):
        print_summary(f"{res['scenario']} seed {res['seed']}, segmenter {res['segmenter']} ({res['cpu_s']:.0f} CPU s)",
                      res, res["ate"])
        if args.trace:
            print_trace(res["trace"])
        results.append(res)
        results.sort(key=lambda r: order[(r["scenario"], r["seed"], r["segmenter"])])
        summary = _summary(results, args.segmenters)
        # written after every run: an interrupted bench keeps what it ran
        out = {"domain": args.domain, "report": args.report, "overrides": args.overrides, "runs": results, **summary}
        provenance.write_json(args.json, json.loads(json.dumps(out, default=float)), prov)
    print_against_none(summary["against_none"])
    for sc, means in summary["scenarios"].items():
        print(f"== {sc}: mean ATE " + ", ".join(f"{g} {a:.4f} m" for g, a in means.items()))
    for g, share in summary["oracle_share"].items():
        if share is not None:
            print(f"== {g}: {100 * share:.0f} % of the oracle labels' gain over none on {', '.join(MOVING)}")
    print(f"written {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
