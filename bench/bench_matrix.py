"""The benchmark matrix: pvslam's default pipeline, as a new user runs it, on every built-in synthetic scenario x
seeds plus the KITTI excerpts, beside the textbook VO peer (and COLMAP with ``--colmap``).

    python bench/bench_matrix.py --set report --jobs 2 --json runs/bench/report.json   # the report figures
    python bench/bench_matrix.py --set tune --jobs 2           # the seeds to choose parameters on
    python bench/bench_matrix.py --seeds $(python bench/seeds.py --fresh 3) --jobs 2    # a decision's fresh seeds
    python bench/bench_matrix.py --scenarios busy_street kitti_06 --seeds 3 --frames 60   # a smoke run
    python bench/bench_matrix.py --set report --override optimizer.iters=5   # a variant on the same cells
    python bench/bench_matrix.py --reprint runs/bench/report.json [--markdown] [--compare BEFORE.json]

**Seed sets** come from the ledger ``bench/seeds.toml`` (:mod:`bench.seeds`): ``tune`` (choose parameters on
these), ``report`` (report on these, never tune on them), ``heldout`` (run once on the final default), ``default``
(seed 0, the sequences ``pvslam run`` uses); ``all`` = default + tune + report.  Every printed row and the JSON say
which set a seed belongs to (``used``: spent on an earlier decision; ``fresh``: never run).  The KITTI excerpts (06
and 01, 51 frames each) have no seeds: they run with every set.  ``--json`` records the commit of the measured code
(:mod:`bench.provenance`) and refuses to write without one.

**What runs per cell** (see :mod:`bench.matrix_jobs`): the synthetic folder is generated (cached); pvslam runs
with the default config and the ``images`` reader (no labels: ``segmenter.plugin = "none"``, ``vps.plugin =
"none"``; ``--labels`` adds a run with the ``synthetic`` reader, oracle ``labels`` and the VPS); the textbook VO
(``bench/peers/textbook_vo.py``); a constant-velocity straight line fitted to the ground truth (the trivial
baseline, meaningful on the short KITTI excerpts); COLMAP (``bench/peers/colmap_peer.py``, pycolmap) with
``--colmap`` only: it is slow.  ATE is Sim(3)-aligned over every frame, as % of the ground-truth path length.

Columns: ``posed`` frames with a pose estimate (not a placeholder: tracking did not fail and the map fragment
initialised), ``init`` the frame where the map first initialised and the seconds of camera motion before it,
``reinit`` re-initialisations, ``fps`` pvslam's frames per second (one torch thread; wall time, so a loaded machine
lowers it), ``VO %`` with ``*`` when the textbook VO never initialised (identity poses), ``VO/pv`` textbook VO ATE /
pvslam ATE (the target is >= 3), ``line`` the straight line.  Below the table, the summary's "map at
initialisation" line: the median rotation and translation-direction errors of each run's first map against the
ground truth (``matrix_jobs.init_errors``) and the cells whose map started wrong (R > 3 deg or t > 20 deg).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Optional

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import provenance, seeds as seed_ledger  # noqa: E402
from bench.matrix_jobs import KITTI, run_cell  # noqa: E402

LEDGER = seed_ledger.load()
SEED_SETS = LEDGER.sets  # name -> seeds: default, tune, report, heldout (bench/seeds.toml)
USED_SEEDS = LEDGER.spent_seeds  # seeds already spent on decisions
KITTI_SEQS = ("kitti_06", "kitti_01")
INIT_TARGET_S = 2.0


def synthetic_scenarios() -> list[str]:
    from pvslam_plugins.datasets.synthetic.scenarios import SCENARIOS

    return list(SCENARIOS)


def seed_set_of(seed: int) -> str:
    """``default``, ``tune``, ``report``, ``heldout``, ``used`` (spent) or ``fresh`` (bench/seeds.toml)."""
    return LEDGER.set_of(seed)


def plan(scenarios: list[str], seeds: list[int], frames, out: Path, labels: bool, colmap: bool,
         jobs: int, overrides: tuple[str, ...] = (), size: tuple[int, int] = (320, 240),
         exposure: bool = False, hfov_deg: Optional[float] = None) -> list[dict]:
    """One job per (synthetic scenario, seed) and one per KITTI excerpt, longest first (parallel efficiency)."""
    default_len = {"driving_city": 550, "driving_loop": 488, "handheld_fast": 360, "indoor_handheld": 330}
    cells = []
    for sc in scenarios:
        for seed in ([0] if sc.startswith("kitti_") else seeds):
            cells.append({"scenario": sc, "seed": None if sc.startswith("kitti_") else seed, "frames": frames,
                          "out": str(out), "labels": labels, "colmap": colmap,
                          "colmap_threads": 1 if jobs > 1 else -1, "overrides": list(overrides), "size": list(size),
                          "exposure": exposure and not sc.startswith("kitti_"), "hfov_deg": hfov_deg,
                          "set": "shared" if sc.startswith("kitti_") else seed_set_of(seed)})
    return sorted(cells, key=lambda c: -(min(frames or 10 ** 9, default_len.get(c["scenario"], 300))))


# ------------------------------------------------------------------------------------------------ formatting
def _f(x, fmt="{:.2f}", none="-") -> str:
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def _get(row, key, field):
    v = row.get(key) or {}
    return None if "error" in v else v.get(field)


def ratio(row):
    pv, vo = _get(row, "pvslam", "ate_pct"), _get(row, "vo", "ate_pct")
    return vo / pv if pv and vo is not None and pv > 0 else None


def table(rows: list[dict], labels: bool, colmap: bool) -> list[str]:
    head = (f"{'scenario':<21}{'seed':>5}{'frames':>7}{'path m':>8} | {'pvslam %':>9}{'posed':>9}{'init (s)':>14}"
            f"{'reinit':>7}{'fps':>6} | {'VO %':>7}{'VO/pv':>7} | {'line %':>7}")
    if colmap:
        head += f" | {'COLMAP %':>9}{'reg':>5}"
    if labels:
        head += f" | {'labels %':>9}{'init':>6}"
    lines = [head, "-" * len(head)]
    for r in rows:
        seed = "-" if r["seed"] is None else str(r["seed"])
        if "error" in r:
            lines.append(f"{r['scenario']:<21}{seed:>5}  ERROR {r['error']}")
            continue
        pv = r.get("pvslam", {})
        if "error" in pv:
            mid = f"{'ERROR':>9} {pv['error'][:60]}"
        else:
            init = "never" if pv["init_frame"] is None else f"{pv['init_frame']} ({pv['init_s']:.1f})"
            mid = (f"{_f(pv['ate_pct']):>9}{str(pv['posed']) + '/' + str(pv['frames']):>9}{init:>14}"
                   f"{pv['reinits']:>7}{_f(pv['fps'], '{:.1f}'):>6}")
        vo = _f(_get(r, "vo", "ate_pct")) + ("*" if _get(r, "vo", "init_frame") == -1 else " ")
        line = (f"{r['scenario']:<21}{seed:>5}{r['frames']:>7}{r['path_m']:>8.1f} | {mid} | "
                f"{vo:>8}{_f(ratio(r), '{:.1f}x'):>6} | {_f(r['line']['ate_pct']):>7}")
        if colmap:
            line += f" | {_f(_get(r, 'colmap', 'ate_pct')):>9}{_f(_get(r, 'colmap', 'registered'), '{}'):>5}"
        if labels:
            lf = _get(r, "labels", "init_frame")
            lf = "-" if _get(r, "labels", "ate_pct") is None else ("never" if lf is None else str(lf))
            line += f" | {_f(_get(r, 'labels', 'ate_pct')):>9}{lf:>6}"
        lines.append(line)
    return lines


def table_md(rows: list[dict], labels: bool, colmap: bool) -> list[str]:
    """The same table as Markdown."""
    cols = ["scenario", "seed", "frames", "path m", "pvslam ATE %", "posed", "init frame (s)", "reinit", "fps",
            "textbook VO ATE %", "VO / pvslam", "line %"] + (["COLMAP ATE % (registered)"] if colmap else []) + (
        ["pvslam + labels ATE % (init)"] if labels else [])
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * 3 + "---:|" * (len(cols) - 3)]
    for r in rows:
        if "error" in r or "error" in r.get("pvslam", {}):
            out.append(f"| {r['scenario']} | {r['seed']} | error: {r.get('error') or r['pvslam']['error']} |")
            continue
        pv = r["pvslam"]
        init = "never" if pv["init_frame"] is None else f"{pv['init_frame']} ({pv['init_s']:.1f})"
        vo = _f(_get(r, "vo", "ate_pct")) + (" *" if _get(r, "vo", "init_frame") == -1 else "")
        cells = [r["scenario"], "-" if r["seed"] is None else str(r["seed"]), str(r["frames"]), f"{r['path_m']:.1f}",
                 _f(pv["ate_pct"]), f"{pv['posed']}/{pv['frames']}", init, str(pv["reinits"]), _f(pv["fps"], "{:.1f}"),
                 vo, _f(ratio(r), "{:.2f}x"), _f(r["line"]["ate_pct"])]
        if colmap:
            cm = _get(r, "colmap", "registered")
            cells.append("-" if cm is None else f"{_f(_get(r, 'colmap', 'ate_pct'))} ({cm})")
        if labels:
            lf = _get(r, "labels", "init_frame")
            cells.append("-" if "labels" not in r else f"{_f(_get(r, 'labels', 'ate_pct'))} "
                         f"({'never' if lf is None else lf})")
        out.append("| " + " | ".join(cells) + " |")
    return out


def compare_md(before: list[dict], after: list[dict]) -> list[str]:
    """Per scenario: pvslam before / after (mean ± std over the seeds both runs have, and the worst seed), the
    textbook VO, the worst VO / pvslam ratio after, and the medians over the cells both runs have (Markdown)."""
    key = lambda r: (r["scenario"], r["seed"])  # noqa: E731
    b = {key(r): r for r in before if "error" not in r}
    a = {key(r): r for r in after if "error" not in r}
    both = [k for k in a if k in b]
    out = ["| scenario | cells | pvslam before (worst) | pvslam after (worst) | textbook VO | worst VO / pvslam after |",
           "|---|---:|---:|---:|---:|---:|"]
    for sc in dict.fromkeys(k[0] for k in both):
        ks = [k for k in both if k[0] == sc]
        pb = [_get(b[k], "pvslam", "ate_pct") for k in ks]
        pa = [_get(a[k], "pvslam", "ate_pct") for k in ks]
        vo = [_get(a[k], "vo", "ate_pct") for k in ks]
        rat = [x for x in (ratio(a[k]) for k in ks) if x is not None]
        worst = lambda v: _f(max((x for x in v if x is not None), default=None))  # noqa: E731
        out.append(f"| {sc} | {len(ks)} | {_ms(pb)} ({worst(pb)}) | {_ms(pa)} ({worst(pa)}) | {_ms(vo)} | "
                   f"{_f(min(rat) if rat else None, '{:.2f}x')} |")
    med = lambda src, f: float(np.median([_get(src[k], f[0], f[1]) for k in both  # noqa: E731
                                          if _get(src[k], f[0], f[1]) is not None]))
    out.append(f"| **median over the {len(both)} cells** | {len(both)} | {med(b, ('pvslam', 'ate_pct')):.2f} | "
               f"{med(a, ('pvslam', 'ate_pct')):.2f} | {med(a, ('vo', 'ate_pct')):.2f} | |")
    return out


def _ms(v: list[float]) -> str:
    v = [x for x in v if x is not None and math.isfinite(x)]
    if not v:
        return "-"
    return f"{np.mean(v):.2f} ± {np.std(v):.2f}" if len(v) > 1 else f"{v[0]:.2f}"


def summary(rows: list[dict]) -> tuple[list[str], dict]:
    lines, out = [], {}
    ok = [r for r in rows if "error" not in r]
    for sc in dict.fromkeys(r["scenario"] for r in ok):
        rs = [r for r in ok if r["scenario"] == sc]
        pv = [_get(r, "pvslam", "ate_pct") for r in rs]
        vo = [_get(r, "vo", "ate_pct") for r in rs]
        rat = [x for x in (ratio(r) for r in rs) if x is not None]
        never = sum(_get(r, "pvslam", "init_frame") is None for r in rs)
        out[sc] = {"pvslam_mean": float(np.nanmean([x if x is not None else np.nan for x in pv])),
                   "pvslam_std": float(np.nanstd([x if x is not None else np.nan for x in pv])),
                   "vo_mean": float(np.nanmean([x if x is not None else np.nan for x in vo])), "n": len(rs),
                   "min_ratio": min(rat) if rat else None, "never_initialised": never}
        worst = _f(min(rat) if rat else None, "{:.1f}x")
        lines.append(f"  {sc:<21} n={len(rs)}  pvslam {_ms(pv):>15} %   VO {_ms(vo):>15} %   worst VO/pv {worst:>6}"
                     + (f"   never initialised: {never}" if never else ""))
    errors = [(r["scenario"], r["seed"], k, (r.get(k) or {}).get("error")) for r in rows
              for k in ("pvslam", "labels", "vo", "colmap") if (r.get(k) or {}).get("error")]
    errors += [(r["scenario"], r["seed"], "sequence", r["error"]) for r in rows if "error" in r]
    for sc, seed, k, e in errors:
        lines.append(f"  ERROR {sc} seed {seed} {k}: {e}")
    allpv = [x for x in (_get(r, "pvslam", "ate_pct") for r in ok) if x is not None]
    out["median_pvslam_pct"] = float(np.median(allpv)) if allpv else None
    allvo = [x for x in (_get(r, "vo", "ate_pct") for r in ok) if x is not None]
    out["median_vo_pct"] = float(np.median(allvo)) if allvo else None
    lines.append(f"  median over the matrix ({len(allpv)} sequences): pvslam {_f(out['median_pvslam_pct'])} %, "
                 f"textbook VO {_f(out['median_vo_pct'])} %")
    lines += init_summary(ok, out)
    return lines, out


INIT_BAD_ROT_DEG, INIT_BAD_T_DEG = 3.0, 20.0  # a map that started in the wrong valley (matrix_jobs.init_errors)


def init_summary(rows: list[dict], out: dict) -> list[str]:
    """The map at initialisation (matrix_jobs.init_errors): median errors and the cells that started wrong."""
    got = [(r, _get(r, "pvslam", "init_rot_err_deg"), _get(r, "pvslam", "init_t_err_deg")) for r in rows]
    got = [(r, a, b) for r, a, b in got if a is not None and b is not None]
    if not got:
        return []
    bad = [f"{r['scenario']}{'' if r['seed'] is None else '/' + str(r['seed'])} (R {a:.1f}, t {b:.0f})"
           for r, a, b in got if a > INIT_BAD_ROT_DEG or b > INIT_BAD_T_DEG]
    out["init_rot_err_median_deg"] = float(np.median([a for _, a, _ in got]))
    out["init_t_err_median_deg"] = float(np.median([b for _, _, b in got]))
    out["init_wrong"] = bad
    return [f"  map at initialisation ({len(got)} sequences): rotation error median "
            f"{out['init_rot_err_median_deg']:.2f} deg, translation direction median {out['init_t_err_median_deg']:.1f}"
            f" deg; R > {INIT_BAD_ROT_DEG:g} or t > {INIT_BAD_T_DEG:g} deg: {', '.join(bad) or 'none'}"]


def targets(rows: list[dict]) -> list[dict]:
    """The targets, each PASS / MISS with the measured value (or 'not measured')."""
    ok = [r for r in rows if "error" not in r and "error" not in r.get("pvslam", {})]
    name = lambda r: r["scenario"] + ("" if r["seed"] is None else f"/{r['seed']}")  # noqa: E731
    res = []

    def add(title, passed, measured, goal):
        res.append({"name": title, "ok": passed, "measured": measured, "target": goal})

    bad_init = [r for r in ok if r["pvslam"]["init_s"] is None or r["pvslam"]["init_s"] > INIT_TARGET_S
                or r["pvslam"]["posed"] < r["frames"]]
    worst = sorted(bad_init, key=lambda r: -(r["pvslam"]["init_s"] if r["pvslam"]["init_s"] is not None else 1e9))
    examples = ", ".join(f"{name(r)} init {_f(r['pvslam']['init_s'], '{:.1f} s', 'never')} "
                         f"posed {r['pvslam']['posed']}/{r['frames']}" for r in worst[:4])
    add("initialises within 2 s of motion, every frame posed", not bad_init and len(ok) == len(rows),
        f"{len(ok) - len(bad_init)}/{len(rows)} sequences" + (f"; e.g. {examples}" if bad_init else ""),
        "every sequence")
    rats = [(ratio(r), r) for r in ok]
    low = sorted([(x, r) for x, r in rats if x is None or x < 3.0], key=lambda p: p[0] if p[0] is not None else -1)
    add("ATE >= 3x lower than the textbook VO on every sequence", not low and len(ok) == len(rows),
        f"{len(ok) - len(low)}/{len(rows)} sequences" + (
            "; worst " + ", ".join(f"{name(r)} {_f(x, '{:.2f}x')}" for x, r in low[:4]) if low else ""), ">= 3x each")
    pv = [r["pvslam"]["ate_pct"] for r in ok]
    med = float(np.median(pv)) if pv else math.nan
    add("median ATE over the matrix", bool(pv) and med <= 1.0, f"{med:.2f} % of path", "<= 1 %")
    busy = [r for r in ok if r["scenario"] == "busy_street" and _get(r, "colmap", "ate_pct") is not None]
    if busy:
        worst_b = max(r["pvslam"]["ate_pct"] / max(r["colmap"]["ate_pct"], 1e-9) for r in busy)
        add("busy street, no segmenter: within 2x of COLMAP", worst_b <= 2.0, f"worst {worst_b:.1f}x COLMAP's", "<= 2x")
    else:
        add("busy street, no segmenter: within 2x of COLMAP", None, "not measured (run busy_street with --colmap)",
            "<= 2x")
    dl = [r for r in ok if r["scenario"] == "driving_loop"]
    if dl:
        w = max(r["pvslam"]["ate_pct"] for r in dl)
        lab = [_get(r, "labels", "ate_pct") for r in dl if _get(r, "labels", "ate_pct") is not None]
        add("driving loop: no regression", w <= 0.5, f"worst {w:.2f} % (no labels)" + (
            f"; with labels worst {max(lab):.2f} %" if lab else ""), "<= 0.5 %")
    add("3000-frame driving loop <= 0.5 %, no fragment left unmerged", None,
        "not in this matrix: python bench/bench_pipeline.py --only long", "<= 0.5 %")
    return res


# ------------------------------------------------------------------------------------------------ main
def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", choices=[*SEED_SETS, "all"], default="report",
                    help="seed set of bench/seeds.toml (default: report; all = default + tune + report)")
    ap.add_argument("--scenarios", nargs="+", help="synthetic scenario names and/or kitti_06 kitti_01 "
                    "(kitti = both); default: every built-in scenario and both KITTI excerpts")
    ap.add_argument("--seeds", nargs="+", type=int, help="seeds instead of the set's (the output says which set "
                    "each belongs to)")
    ap.add_argument("--frames", type=int, help="first N frames of every sequence (a shorter, cheaper matrix)")
    ap.add_argument("--size", default="320x240", metavar="WxH",
                    help="image size of the synthetic sequences (another camera; default 320x240)")
    ap.add_argument("--hfov", type=float, metavar="DEG", help="horizontal field of view of the synthetic sequences' "
                    "camera in degrees (another lens, same scenes; default: the generator's, about 61)")
    ap.add_argument("--jobs", type=int, default=1, help="parallel processes (default 1)")
    ap.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every pvslam run (repeatable, TOML value syntax, as `pvslam run "
                    "--set`): compare a variant with the default on the same cells")
    ap.add_argument("--labels", action="store_true", help="also run pvslam with the oracle labels (synthetic only)")
    ap.add_argument("--colmap", action="store_true", help="also run COLMAP (pycolmap; slow)")
    ap.add_argument("--exposure", action="store_true", help="every synthetic sequence (for every method) under a "
                    "camera's auto-exposure changes: the synthetic plugin's exposure.auto_exposure_gain, a 1.5x ramp, "
                    "a 0.7x step and back every 140 frames (KITTI as it is)")
    ap.add_argument("--json", help="write the rows, summary and targets to this JSON file, with the commit of the "
                    "measured code (refused without one; not into bench/)")
    ap.add_argument("--out", help="folder for run directories and the KITTI peer folders (default: temporary)")
    ap.add_argument("--reprint", metavar="JSON", help="print the table, summary and targets of a saved --json run")
    ap.add_argument("--markdown", action="store_true", help="with --reprint: the table as Markdown")
    ap.add_argument("--compare", metavar="JSON", help="with --reprint: per scenario, this earlier run (before) "
                    "beside the reprinted one (after), Markdown")
    return ap


def _reprint(args) -> int:
    """``--reprint``: the table, summary and targets of a saved run (``--markdown``, ``--compare``)."""
    saved = json.loads(Path(args.reprint).read_text())
    prov = saved.get("provenance") or {"commit": saved.get("commit")}
    dirty = {True: " (dirty)", False: "", None: ""}[prov.get("dirty")]
    print(f"seed set: {saved['set'].upper()} -- seeds {', '.join(map(str, saved['seeds']))}; commit "
          f"{prov.get('commit') or 'not recorded'}{dirty}; jobs {saved['jobs']}; frames "
          f"{saved['frames'] or 'default lengths'}")
    rows = saved["rows"]
    labels, colmap = any("labels" in r for r in rows), any("colmap" in r for r in rows)
    if args.markdown:
        print("\n".join(table_md(rows, labels, colmap)))
    report(rows, labels, colmap)
    if args.compare:
        print("\n".join(compare_md(json.loads(Path(args.compare).read_text())["rows"], rows)))
    return 0


def _camera(ap: argparse.ArgumentParser, args) -> tuple[int, int]:
    """The synthetic sequences' image size from ``--size`` (and ``--hfov`` checked), said on the console."""
    wh = re.fullmatch(r"(\d+)x(\d+)", args.size.lower())
    if wh is None or min(int(wh[1]), int(wh[2])) < 16:
        ap.error(f"--size must be WIDTHxHEIGHT (each >= 16), got {args.size!r}")
    size = (int(wh[1]), int(wh[2]))
    if size != (320, 240):
        print(f"synthetic image size {size[0]}x{size[1]}")
    if args.hfov is not None:
        from pvslam_plugins.datasets.synthetic.render import check_hfov

        try:
            check_hfov(args.hfov)
        except ValueError as e:
            ap.error(f"--hfov: {e}")
        print(f"synthetic camera: {args.hfov:g} deg horizontal field of view")
    return size


def _run_cells(cells: list, jobs: int, t0: float) -> list[dict]:
    """Every cell's row, in ``jobs`` spawned processes when more than one (progress printed as they finish)."""
    rows = []
    if jobs > 1:
        import multiprocessing as mp

        with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as ex:
            futs = [ex.submit(run_cell, c) for c in cells]
            for f in as_completed(futs):
                rows.append(f.result())
                _progress(rows[-1], len(rows), len(cells), t0)
    else:
        for c in cells:
            rows.append(run_cell(c))
            _progress(rows[-1], len(rows), len(cells), t0)
    return rows


def main(argv=None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.reprint:
        return _reprint(args)
    synth = synthetic_scenarios()
    names = args.scenarios or synth + list(KITTI_SEQS)
    names = [k for n in names for k in (KITTI_SEQS if n == "kitti" else (n,))]
    unknown = [n for n in names if n not in synth and n not in KITTI_SEQS]
    if unknown:
        ap.error(f"unknown scenario(s) {unknown}; known: {', '.join(synth + list(KITTI_SEQS))} (or kitti)")
    if any(n in KITTI_SEQS for n in names) and not (KITTI / "sequences").is_dir():
        print(f"KITTI excerpts not found in {KITTI}: skipped")
        names = [n for n in names if n not in KITTI_SEQS]
    prov = None
    if args.json:
        try:
            prov = provenance.check(args.json)
        except provenance.ProvenanceError as exc:
            return provenance.fail(exc)
    seeds = args.seeds if args.seeds else ([s for k in ("default", "tune", "report") for s in SEED_SETS[k]]
                                           if args.set == "all" else list(SEED_SETS[args.set]))
    label = "custom" if args.seeds else args.set
    sets = sorted({seed_set_of(s) for s in seeds})
    out = Path(args.out or tempfile.mkdtemp(prefix="pvslam-matrix-"))
    out.mkdir(parents=True, exist_ok=True)
    print(f"seed set: {label.upper()} -- seeds {', '.join(map(str, seeds))} ({'/'.join(sets)}; tune = "
          f"{SEED_SETS['tune']}, report = {SEED_SETS['report']}, default = {SEED_SETS['default']}; KITTI is in every "
          f"set)")
    if {"report", "heldout"} & set(sets):
        print("REPORT / HELD-OUT seeds: measure on them, never tune on them.")
    where = f"commit {prov['commit']}{' (dirty)' if prov['dirty'] else ''}" if prov else "no result file"
    print(f"{where}; {platform.node()} {os.cpu_count()} CPUs; jobs {args.jobs}; frames "
          f"{args.frames or 'default lengths'}; run directories in {out}", flush=True)
    if args.override:
        from pvslam_core.config import load_config

        load_config(None, overrides=args.override)  # a typo fails here, not in every cell
        print(f"overrides for every pvslam run: {' '.join(args.override)}")
    size = _camera(ap, args)
    if args.exposure:
        print("auto-exposure changes on every synthetic sequence (exposure.auto_exposure_gain)")
    cells = plan(names, seeds, args.frames, out, args.labels, args.colmap, args.jobs, tuple(args.override), size,
                 args.exposure, args.hfov)
    t0 = time.perf_counter()
    rows = _run_cells(cells, args.jobs, t0)
    order = {n: k for k, n in enumerate(names)}
    rows.sort(key=lambda r: (order[r["scenario"]], -1 if r["seed"] is None else r["seed"]))
    summ, tg = report(rows, args.labels, args.colmap)
    wall = time.perf_counter() - t0
    print(f"\nmatrix wall time {wall:.0f} s")
    if args.json:
        provenance.write_json(args.json, {
            "set": label, "seeds": seeds, "seed_sets": SEED_SETS, "argv": sys.argv[1:] if argv is None else argv,
            "jobs": args.jobs, "frames": args.frames, "size": list(size), "hfov_deg": args.hfov,
            "exposure": args.exposure, "overrides": list(args.override), "wall_s": wall, "rows": rows,
            "summary": summ, "targets": tg}, prov)
        print(f"results written to {args.json}")
    return 0


def report(rows: list[dict], labels: bool, colmap: bool) -> tuple[dict, list[dict]]:
    """Print the table, the per-scenario summary and the targets; returns (summary, targets)."""
    print()
    print("\n".join(table(rows, labels, colmap)))
    if any(_get(r, "vo", "init_frame") == -1 for r in rows):
        print("  * the textbook VO never initialised: its poses are all the identity")
    print("\nper scenario (mean ± std over seeds, ATE % of path):")
    sl, summ = summary(rows)
    print("\n".join(sl))
    print("\ntargets:")
    tg = targets(rows)
    for t in tg:
        status = "n/a " if t["ok"] is None else ("PASS" if t["ok"] else "MISS")
        print(f"  [{status}] {t['name']}: {t['measured']}   (target: {t['target']})")
    return summ, tg


def _progress(row: dict, k: int, n: int, t0: float) -> None:
    pv = row.get("pvslam") or {}
    txt = row.get("error") or pv.get("error") or (f"pvslam {_f(pv.get('ate_pct'))} %, VO "
                                                    f"{_f(_get(row, 'vo', 'ate_pct'))} %")
    seed = "" if row["seed"] is None else f" seed {row['seed']}"
    print(f"[{k}/{n} {time.perf_counter() - t0:6.0f} s] {row['scenario']}{seed}: {txt}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
