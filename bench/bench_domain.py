"""Panoptic quality of ``panoptic_fpn`` weights off their training renderer: frames of the generator's held-out
domain (texture families, thing sizes no training frame shows; see the synthetic plugin's ``domain.py``) against
frames of the plain generator's validation seeds (and, between them, frames of its training domain on unseen seeds).

    python bench/bench_domain.py --model old=runs/old_reduced_synthetic.pth --model new=runs/pfpn_dr/model_final.pth
    python bench/bench_domain.py                      # the shipped weights only
    python bench/bench_domain.py --set segmenter --vps   # the current figure: the ledger's segmenter seeds, with VPQ

Prints one table per frame set (a row per model: PQ, SQ, RQ, things, stuff, PQ with ground-truth segments under
64 px as void); with ``--vps``, also the VPS heads' VPQ on the held-out looks of the scenes with moving vehicles (the
shipped weights through :func:`bench.bench_vps.run_sequence`).  It writes them with the commit of the measured code
(:mod:`bench.provenance`) to ``--json`` (default ``runs/bench/domain_pq.json``) and the PQ tables beside it.  Torch
runs with one thread (``--threads``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Mapping, Optional, Sequence

import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import bench_vps, provenance, seeds  # noqa: E402

HELD_OUT = "heldout"
SEEN = "train_split"
PLAIN = "plain"
FIGURE_SET = "segmenter"  # the ledger's set of the current figure (bench/figures.py): seeds no choice was made on
FRAMES = 8  # frames per scenario and seed
TARGET_PQ = 0.55  # the held-out families' PQ the shipped segmenter should reach


def frame_sets(heldout_seeds: Sequence[int], plain_seeds: Sequence[int], frames: int,
               scenarios: Optional[Sequence[str]] = None, width: int = 320, height: int = 240) -> dict[str, list]:
    """``{"heldout": samples, "train_split": samples, "plain": samples}``: ``frames`` evenly spaced frames of every
    scenario per seed, rendered in the generator's held-out domain, in its training domain (seen families, unseen
    seeds: how much of the gap is the families') with ``heldout_seeds``, and by the plain generator with
    ``plain_seeds``.  Seeds the trainer's defaults train on are refused for every set."""
    from pvslam_plugins.segmenters.panoptic_fpn.data import render_samples
    from pvslam_plugins.segmenters.panoptic_fpn.train import TrainConfig

    cfg = TrainConfig()
    trained = set(cfg.train_seeds) | set(cfg.domain_seeds)
    if trained & (set(heldout_seeds) | set(plain_seeds)):
        raise ValueError(f"seeds {sorted(trained & (set(heldout_seeds) | set(plain_seeds)))} are training seeds")
    scenarios = list(scenarios or cfg.scenarios)
    out: dict[str, list] = {HELD_OUT: [], SEEN: [], PLAIN: []}
    for name, seeds, domain in ((HELD_OUT, heldout_seeds, "heldout"), (SEEN, heldout_seeds, "train"),
                                (PLAIN, plain_seeds, None)):
        for scen in scenarios:
            for seed in seeds:
                out[name] += render_samples(scen, seed, frames, width, height, domain=domain)
    return out


def compare(models: Mapping[str, torch.nn.Module], sets: Mapping[str, list], min_gt_area: int = 64) -> dict:
    """``{set: {model: evaluate(...) result}}`` of every model on every frame set."""
    from pvslam_plugins.segmenters.panoptic_fpn.evaluate import evaluate

    return {s: {m: evaluate(model, samples, min_gt_area) for m, model in models.items()} for s, samples in sets.items()}


def format_tables(results: Mapping[str, Mapping[str, dict]]) -> str:
    """One Markdown table per frame set, one row per model."""
    blocks = []
    for s, by_model in results.items():
        n = next(iter(by_model.values()))["num_frames"] if by_model else 0
        lines = [f"### {s} ({n} frames)", "",
                 "| weights | PQ | SQ | RQ | PQ things | PQ stuff | PQ, GT >= 64 px |", "|---|---|---|---|---|---|---|"]
        for m, r in by_model.items():
            p = r["pq"]
            small = f"{100 * r['pq_min_area']['pq']:.1f}" if "pq_min_area" in r else "-"
            lines.append(f"| {m} | {100 * p['pq']:.1f} | {100 * p['sq']:.1f} | {100 * p['rq']:.1f} | "
                         f"{100 * p['things']['pq']:.1f} | {100 * p['stuff']['pq']:.1f} | {small} |")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def load_models(specs: Sequence[str]) -> dict[str, torch.nn.Module]:
    """``NAME=PATH`` specs -> models built as the segmenter builds them (its thresholds); none: the shipped file."""
    from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenterConfig, build_model

    if not specs:
        return {"shipped": build_model(PanopticFPNSegmenterConfig())}
    out = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"pvslam: error: --model {spec!r}: expected NAME=PATH")
        out[name] = build_model(PanopticFPNSegmenterConfig(weights=path))
    return out


def vps_section(heldout_seeds: Sequence[int], frames: int = bench_vps.FRAMES) -> dict:
    """VPQ of each VPS head (``bench_vps.HEADS``) on ``bench_vps.SCENARIOS`` x ``heldout_seeds`` in the held-out
    looks, per run and its mean over the runs."""
    runs = [bench_vps.run_sequence(sc, seed, frames, {}, "heldout") for sc in bench_vps.SCENARIOS
            for seed in heldout_seeds]
    for r in runs:
        print(f"{r['scenario']:16s} seed {r['seed']}: " + "  ".join(
            f"{h} VPQ {100 * r['heads'][h]['vpq']:.1f}" for h in bench_vps.HEADS), flush=True)
    return {"scenarios": list(bench_vps.SCENARIOS), "frames": frames, "runs": runs,
            "vpq": {h: statistics.mean(r["heads"][h]["vpq"] for r in runs) for h in bench_vps.HEADS}}


def report_problem(r: dict) -> Optional[str]:
    """What keeps a result file from being the current figure (bench/figures.py), or None."""
    want = list(seeds.load().sets[FIGURE_SET])
    if r.get("models") != ["shipped"] or r.get("set") != FIGURE_SET or list(r.get("heldout_seeds") or []) != want \
            or r.get("frames_per_sequence") != FRAMES or not r.get("vps"):
        return (f"not the shipped weights on the ledger's {FIGURE_SET!r} seeds {want} with VPQ (run with --set "
                f"{FIGURE_SET} --vps)")
    return None


def figure(r: dict) -> tuple[str, str]:
    """The shipped weights' PQ (things / stuff) on the held-out families, on the training families at the same
    seeds and on the plain generator, and the VPS heads' mean VPQ, as one row of the current-figures page."""
    def pq(name: str) -> str:
        p = r["results"][name]["shipped"]["pq"]
        return f"{100 * p['pq']:.1f} ({100 * p['things']['pq']:.1f} / {100 * p['stuff']['pq']:.1f})"

    v = r["vps"]["vpq"]
    value = (f"PQ (things / stuff): held-out families and sizes **{pq(HELD_OUT)}**; training families, the same "
             f"seeds {pq(SEEN)}; plain generator, validation seeds {', '.join(map(str, r['plain_seeds']))} "
             f"{pq(PLAIN)}. VPQ in the held-out looks ({' and '.join(r['vps']['scenarios'])}, "
             f"{r['vps']['frames']} frames): `fusion` {100 * v['fusion']:.1f}, `warp_iou` {100 * v['warp_iou']:.1f}, "
             f"per-frame ids {100 * v['none']:.1f}")
    return value, (f"targets: PQ >= {100 * TARGET_PQ:.0f} and VPQ `fusion` >= `warp_iou` on the held-out "
                   "families")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", default=[], help="NAME=PATH of weights to compare (repeatable)")
    ap.add_argument("--heldout-seeds", type=int, nargs="+", default=[400, 401])
    ledger = seeds.load()
    ap.add_argument("--set", choices=sorted(ledger.sets), default=None,
                    help="held-out seeds from this set of bench/seeds.toml instead of --heldout-seeds")
    ap.add_argument("--plain-seeds", type=int, nargs="+", default=[100, 101],
                    help="the trainer's validation seeds by default")
    ap.add_argument("--frames", type=int, default=FRAMES, help="frames per scenario and seed")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--vps", action="store_true",
                    help="also the VPS heads' VPQ on the held-out looks (the shipped weights)")
    ap.add_argument("--json", default=str(provenance.RESULTS_DIR / "domain_pq.json"), help="result file")
    args = ap.parse_args(argv)
    if args.vps and args.model:
        ap.error("--vps measures the shipped weights only: leave out --model")
    if args.set:
        args.heldout_seeds = list(ledger.sets[args.set])
    try:
        prov = provenance.check(args.json)
    except provenance.ProvenanceError as exc:
        return provenance.fail(exc)
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    models = load_models(args.model)
    sets = frame_sets(args.heldout_seeds, args.plain_seeds, args.frames)
    results = compare(models, sets)
    table = format_tables(results)
    print(table)
    vps = vps_section(args.heldout_seeds) if args.vps else None
    payload = {"models": args.model or ["shipped"], "set": args.set, "heldout_seeds": args.heldout_seeds,
               "plain_seeds": args.plain_seeds, "frames_per_sequence": args.frames, "results": results, "vps": vps,
               "seconds": time.perf_counter() - t0}
    provenance.write_json(args.json, payload, prov)
    provenance.write_text(Path(args.json).with_suffix(".md"), table + "\n", prov)
    print(f"results: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
