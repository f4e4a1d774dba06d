"""The rows and sections of the current figures (:mod:`bench.figures`), read from one benchmark's result file each:
a row function returns the figure and what it is compared with, as the page and the README's Status table show
them; a section function the lines of a per-benchmark table of the page."""
from __future__ import annotations

import math
import statistics
from typing import Callable, Optional

from bench import speed_table

__all__ = ["matrix_summary", "matrix_scenario", "kitti", "default_run", "ablation", "long_run", "long_speed", "endless",
           "speed", "real_peers", "matrix_cells", "accuracy_section", "real_section", "speed_section"]


def _pct(x: Optional[float], digits: int = 3) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}f}"


def _cells(r: dict, synthetic_only: bool = False) -> list[dict]:
    rows = [c for c in r["rows"] if "error" not in c and "error" not in c.get("pvslam", {})]
    return [c for c in rows if c["seed"] is not None] if synthetic_only else rows


def _ratio(c: dict) -> Optional[float]:
    pv, vo = c["pvslam"].get("ate_pct"), (c.get("vo") or {}).get("ate_pct")
    return vo / pv if pv and vo is not None and pv > 0 else None


def _name(c: dict) -> str:
    return c["scenario"] + ("" if c["seed"] is None else f"/{c['seed']}")


def matrix_summary(r: dict, synthetic_only: bool = False) -> tuple[str, str]:
    """Median / mean ATE, cells >= 3x below the textbook VO, initialisation; compared: the VO, the closest cell."""
    cells, n_all = _cells(r, synthetic_only), len([c for c in r["rows"] if c["seed"] is not None or not synthetic_only])
    pv = [c["pvslam"]["ate_pct"] for c in cells]
    ok3 = [c for c in cells if (_ratio(c) or 0) >= 3.0]
    init = [c for c in cells if c["pvslam"].get("init_s") is not None and c["pvslam"]["init_s"] <= 2.0
            and c["pvslam"]["posed"] >= c["frames"]]
    closest = min(cells, key=lambda c: _ratio(c) or 0.0)
    vo = [c["vo"]["ate_pct"] for c in cells if (c.get("vo") or {}).get("ate_pct") is not None]
    fig = (f"median {_pct(statistics.median(pv))} %, mean {_pct(statistics.fmean(pv))} %; **{len(ok3)} / {n_all}** "
           f"cells >= 3x below the VO; {len(init)} / {n_all} initialised within 2 s, every frame posed")
    return fig, (f"textbook VO median {_pct(statistics.median(vo), 2)} %; closest cell {_name(closest)} "
                 f"({_pct(_ratio(closest), 1)}x)")


def matrix_scenario(scenario: str) -> Callable[[dict], tuple[str, str]]:
    def render(r: dict) -> tuple[str, str]:
        cells = [c for c in _cells(r) if c["scenario"] == scenario]
        pv = " / ".join(_pct(c["pvslam"]["ate_pct"]) for c in cells)
        vo = " / ".join(_pct(c["vo"].get("ate_pct"), 2) for c in cells)
        return f"{pv} %", f"textbook VO {vo} %"
    return render


def kitti(r: dict) -> tuple[str, str]:
    cells = {c["scenario"]: c for c in _cells(r) if c["seed"] is None}
    if not cells:
        raise KeyError("no KITTI cells (excerpts not found when it ran)")
    order = [k for k in ("kitti_06", "kitti_01") if k in cells]
    fig = " / ".join(_pct(cells[k]["pvslam"]["ate_pct"]) for k in order)
    vo = " / ".join(_pct(cells[k]["vo"].get("ate_pct"), 2) for k in order)
    line = " / ".join(_pct(cells[k]["line"].get("ate_pct"), 2) for k in order)
    return f"{fig} %", f"textbook VO {vo} %; constant-velocity line {line} %"


def default_run(r: dict) -> tuple[str, str]:
    m = r["accuracy"]["online_ba+loop"]
    pan, lp = m.get("panoptic") or {}, m.get("loops") or {}
    fig = (f"{_pct(m['ate']['rmse_percent_of_path'])} % of {m['ate']['path_length']:.0f} m; loops P "
           f"{_pct(lp.get('precision'), 2)} R {_pct(lp.get('recall'), 2)}; PQ {_pct(pan.get('pq'), 3)} / VPQ "
           f"{_pct(pan.get('vpq'), 3)} (oracle labels)")
    return fig, f"textbook VO {_pct(r['peers']['textbook_vo']['ate_pct'], 2)} %"


def ablation(r: dict) -> tuple[str, str]:
    a = {k: v["ate"]["rmse_percent_of_path"] for k, v in r["accuracy"].items()}
    fig = (f"loop closure off {_pct(a['online_ba, no loop'])} %; offline BA + loop {_pct(a['offline_ba+loop'])} %; "
           f"offline, no loop {_pct(a['offline_ba, no loop'])} %")
    return fig, f"the default (online BA + loop) {_pct(a['online_ba+loop'])} %, from frame 1 " \
                f"{_pct(a['online_ba+loop (start 1)'])} %"


def long_run(r: dict) -> tuple[str, str]:
    d = r["long"]
    maps = d["unmerged"]
    fig = (f"{_pct(d['ate_pct'], 4)} % of {d['path_m'] / 1000:.1f} km; {maps} map{'s' if maps != 1 else ''}, "
           f"{d['loops']} loops")
    cut = (r.get("forced_loss") or {}).get("cut")
    extra = f"; 30 frames cut from driving_block: {cut['separate_maps']} map after the re-initialisation" if cut else ""
    return fig, f"target <= 0.5 %, one map{extra}"


def long_speed(r: dict) -> tuple[str, str]:
    d = r["long"]
    return (f"CPU per frame last / first 500 frames {d['last_cpu'] / d['first_cpu']:.2f}; peak memory "
            f"{d['peak_mb'] / 1024:.2f} GB", "targets <= 1.2 and < 2 GB")


def endless(r: dict) -> Optional[tuple[str, str]]:
    if "flat" not in r:
        return None  # measured without the endless-input runs (--flat-frames 0)
    base, d = r["flat"]["base"], r["flat"]["long"]
    return (f"peak memory {base['peak_mb'] / 1024:.2f} / {d['peak_mb'] / 1024:.2f} GB at {base['frames']} / "
            f"{d['frames']} frames ({d['peak_mb'] / base['peak_mb']:.2f}x); {base['keyframes']} / {d['keyframes']} "
            f"keyframes; ATE {_pct(base['ate_pct'], 4)} / {_pct(d['ate_pct'], 4)} %", "target: within 1.10x")


def speed(r: dict) -> tuple[str, str]:
    """The speed table in one row (bench/speed_table.py): the default run, each scenario's mean over its
    report seeds, and the real excerpts as a user runs them beside ORB-SLAM3's CPU per frame."""
    rows = r["speed"]
    default = next((x for x in rows if x["group"] == "default"), None)
    means = [x for x in rows if x["run"] == "mean"]
    parts = []
    if default is not None:
        parts.append(f"default run {default['fps']:.1f} ({default['kf_per_frame']:.2f} keyframes a frame)")
    if means:
        fast = [x["group"] for x in means if x["fps"] >= 30]
        parts.append("scenario means " + ", ".join(f"{x['group']} {x['fps']:.1f}" for x in means)
                     + f" ({len(fast)} of {len(means)} at 30 or more)")
    real = speed_table.real_groups(rows)
    if real:
        kitti, mine, orb = zip(*real)
        ratios = " / ".join(f"{m['cpu_ms'] / o['cpu_ms']:.1f}" if o and o["cpu_ms"] > 0 else "-"
                            for m, o in zip(mine, orb))
        missing = "" if all(orb) else " (ORB-SLAM3 not run: no $PVSLAM_ORB_PYTHON / $PVSLAM_ORB_VOCAB)"
        parts.append(f"{' / '.join(g.split()[-1] for g in kitti)} as a user runs them (native size) "
                     + " / ".join(f"{m['fps']:.1f}" for m in mine) + ", CPU "
                     + " / ".join(f"{m['cpu_ms']:.0f}" for m in mine) + f" ms a frame, {ratios}x ORB-SLAM3's"
                     + missing)
    return ("frames/s wall: " + "; ".join(parts),
            "targets 30 frames/s at 320x240 (default run, each scenario), 15 on KITTI-size frames, CPU within 3x "
            "ORB-SLAM3's; 2 cores")


def speed_section(r: dict) -> list[str]:
    """The speed table, one line per run and scenario mean (bench/speed_table.py), with its per-stage CPU."""
    return ["Frames/s wall, mean wall time of a keyframe step and of any other step, CPU per frame of the whole process "
            "and, per stage, of the pipeline thread (`other threads`: the process less the pipeline thread: reading "
            "ahead, writing behind, the flow lanes); evaluation and start-up excluded. The peers have totals only "
            "(ORB-SLAM3: one run, paced, less its vocabulary load).", "", *speed_table.table(r["speed"])]


def _real_rows(r: dict) -> dict[tuple[str, str], list[dict]]:
    return {(row["sequence"], row["method"]): row.get("runs") or [] for row in r["rows"]}


def real_peers(r: dict) -> tuple[str, str]:
    """The real excerpts beside ORB-SLAM3 (bench_real.py): ATE m per excerpt, over all frames and over ORB-SLAM3's."""
    from bench.bench_real import SAME_FRAMES, SEQUENCES as seqs, span

    runs = _real_rows(r)

    def each(method: str, key: str, fmt: str) -> str:
        return " / ".join(span([x.get(key) for x in runs.get((q, method), [])], fmt) for q in seqs)

    sizes = f" (its processing size and {r['size_spread']:g} % per side either way)" if r.get("size_spread") else ""
    first = " / ".join(str((runs.get((q, "pvslam")) or [{}])[0].get("first", 0)) for q in seqs)
    value = (f"scored from frame {first} (the measured ground truth): pvslam {each('pvslam', 'ate_m', '.3f')} m"
             f"{sizes}; on ORB-SLAM3's frames {each(SAME_FRAMES, 'ate_m', '.3f')} m; all frames "
             f"{each('pvslam', 'ate_all_m', '.3f')} m; CPU {each('pvslam', 'cpu_ms_per_frame', '.0f')} ms per frame")
    if not any(runs.get((q, "orbslam3")) for q in seqs):
        orb = "ORB-SLAM3 not run (" + next((row.get("note") or "?" for row in r["rows"]
                                            if row["method"] == "orbslam3"), "?") + ")"
    else:
        orb = (f"ORB-SLAM3, {r['orb_runs']} runs each: {each('orbslam3', 'ate_m', '.3f')} m on "
               f"{each('orbslam3', 'posed', 'd')} frames, {each('orbslam3', 'cpu_ms_per_frame', '.0f')} ms")
    return value, f"{orb}; textbook VO {each('textbook_vo', 'ate_m', '.2f')} m"


# ------------------------------------------------------------------------------ the page's sections
def matrix_cells(r: dict) -> list[str]:
    """The per-cell table of a matrix result."""
    out = ["| cell | set | pvslam ATE % | textbook VO ATE % | VO / pvslam | line % | initialised (s of motion) | "
           "frames posed |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for c in r["rows"]:
        if "error" in c or "error" in c.get("pvslam", {}):
            out.append(f"| {_name(c)} | {c.get('set')} | error: {c.get('error') or c['pvslam']['error']} | | | | | |")
            continue
        pv = c["pvslam"]
        init = "never" if pv.get("init_s") is None else f"{pv['init_s']:.1f}"
        out.append(f"| {_name(c)} | {c.get('set')} | {_pct(pv['ate_pct'])} | {_pct(c['vo'].get('ate_pct'), 2)} | "
                   f"{_pct(_ratio(c), 1)}x | {_pct(c['line'].get('ate_pct'), 2)} | {init} | "
                   f"{pv['posed']} / {c['frames']} |")
    return out


def real_section(real: dict) -> list[str]:
    """The real excerpts' table and per-run lines, with what was run."""
    table = [t for t in real.get("table", []) if t.startswith("|")]
    details = [t for t in real.get("table", []) if not t.startswith("|")]
    sizes = (f", and with the processing area {real['size_spread']:g} % per side smaller and larger "
             "(`--size-spread`)") if real.get("size_spread") else ""
    return [f"pvslam is run as `pvslam run SEQUENCE --calib SEQUENCE/calib.txt`{sizes}; ORB-SLAM3 with a vocabulary "
            "trained on the other excerpts; ATE and RPE after Sim(3) alignment over the frames each posed "
            "(ORB-SLAM3: its largest map) from the first frame with measured ground truth on (KITTI's poses "
            "begin 00 and 06 with a constant-velocity extrapolation; "
            "docs/decisions.md: MEASURED GROUND TRUTH), the ATE over every frame beside; CPU per frame with "
            "start-up.", "", *table, "", *(f"- {t}" for t in details)]


def accuracy_section(acc: dict) -> list[str]:
    """The default run's variants (Table 7), one row each."""
    lines = ["| variant | ATE % | loops detected | loop precision / recall | keyframes |", "|---|---:|---:|---:|---:|"]
    for name, m in acc["accuracy"].items():
        lp = m.get("loops") or {}
        lines.append(f"| {name} | {_pct(m['ate']['rmse_percent_of_path'])} | {lp.get('num_detected', 0)} | "
                     f"{_pct(lp.get('precision'), 2)} / {_pct(lp.get('recall'), 2)} | "
                     f"{m['timing']['keyframes']} |")
    return lines
