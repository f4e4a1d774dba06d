"""Which pixels the ``flow`` frontend's dynamic masks take out of the BA, against the generator's exact dynamic masks.

    python bench/bench_dynamic_masks.py                                   # the sequences below, three segmenters
    python bench/bench_dynamic_masks.py --runs moving_vehicles:162 --segmenters panoptic_fpn --frames 150
    python bench/bench_dynamic_masks.py --runs kitti:06 --segmenters panoptic_fpn none   # ATE and masked share only
    python bench/bench_dynamic_masks.py --domain heldout --runs moving_vehicles:174 --segmenters panoptic_fpn none

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
runs are more than 5 % worse (the target: none on held-out looks, ``--domain heldout``).  Results: ``--json`` (default
runs/bench/results_dynamic_masks.json) with the commit of the measured code (:mod:`bench.provenance`).  Torch runs with
one thread.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Optional

import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance  # noqa: E402

# held-out of panoptic_fpn's training (seeds 1-8) and of the seed ledger's tune/report sets (bench/seeds.toml)
DEFAULT_RUNS = ["moving_vehicles:162", "moving_vehicles:163", "moving_vehicles:164", "driving_block:162",
                "indoor_handheld:162"]
SCALE_BEARING = ("road", "sidewalk", "building", "wall", "floor", "terrain")


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


def print_against_none(rows: list[dict]) -> None:
    for r in rows:
        each = ", ".join(f"{run} {x:.2f}x" for run, x in zip(r["runs"], r["ratios"]))
        print(f"== {r['segmenter']} against none: {r['worse']} of {len(r['ratios'])} runs more than "
              f"{100 * (WORSE - 1):.0f} % worse; mean ATE {r['mean_ate']:.4f} m against {r['mean_ate_none']:.4f} m "
              f"({each})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", default=DEFAULT_RUNS, help="scenario:seed of the synthetic generator")
    ap.add_argument("--segmenters", nargs="+", default=["panoptic_fpn", "labels", "none"])
    ap.add_argument("--frames", type=int, default=150, help="frames of a synthetic run (0: the scenario's own)")
    ap.add_argument("--domain", choices=["train", "heldout"], help="the generator's restyled looks (dataset.domain): "
                    "'heldout' are texture families and sizes the shipped segmenter never saw")
    ap.add_argument("--trace", action="store_true", help="also print each keyframe's moving share and how much of "
                    "it the masks hold (the JSON has it always)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="extra config override")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=str(provenance.RESULTS_DIR / "results_dynamic_masks.json"))
    args = ap.parse_args(argv)
    try:
        prov = provenance.check(args.json)
    except provenance.ProvenanceError as exc:
        return provenance.fail(exc)
    torch.set_num_threads(args.threads)
    overrides = [*([f'dataset.domain="{args.domain}"'] if args.domain else []), *args.overrides]
    results, rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.runs:
            scenario, seed = spec.split(":")
            for segm in args.segmenters:
                t0 = time.process_time()
                if scenario == "kitti" and segm == "labels":
                    continue  # no panoptic ground truth
                res = run_one(scenario, seed, segm, args.frames, Path(tmp), overrides)
                res["cpu_s"] = time.process_time() - t0
                print_summary(f"{scenario} seed {seed}, segmenter {segm} ({res['cpu_s']:.0f} CPU s, busy machine)",
                              res, res["ate"])
                if args.trace:
                    print_trace(res["trace"])
                results.append(res)
                rows = against_none(results)  # written after every run: an interrupted bench keeps what it ran
                out = {"domain": args.domain, "runs": results, "against_none": rows}
                provenance.write_json(args.json, json.loads(json.dumps(out, default=float)), prov)
    print_against_none(rows)
    print(f"written {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
