"""Human-readable summaries of runs and ablation comparison tables."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

from .types import RunResult


def _get(d: dict, *path, default=None):
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return default
        d = d[p]
    return d


def _fmt(v: Any, spec: str = ".4f") -> str:
    if v is None:
        return "-"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "n/a" if math.isnan(f) else format(f, spec)


def _value(v: Any, spec: str, why: str) -> str:
    """``v`` formatted, or ``n/a (why)`` where it is undefined (None or NaN: e.g. a precision without detections)."""
    try:
        defined = v is not None and not math.isnan(float(v))
    except (TypeError, ValueError):
        return str(v)
    return format(float(v), spec) if defined else f"n/a ({why})"


def summary_lines(result: RunResult) -> list[str]:
    return [f"run directory: {result.run_dir}"] + metric_lines(result.metrics, result.run_dir,
                                                                 len(result.loops))


def metric_lines(m: dict, run_dir: Optional[str] = None, num_loops: int = 0) -> list[str]:
    """The console lines of a run's metrics (timing, ATE, RPE, loops, PQ); what is undefined says why."""
    lines = []
    t = m.get("timing") or {}
    if t:
        lines.append(f"frames: {t.get('frames')}  keyframes: {t.get('keyframes')}  "
                     f"time: {_fmt(t.get('seconds'), '.1f')} s  ({_fmt(t.get('fps'), '.1f')} frames/s)")
    if "ate" in m and m["ate"].get("error"):
        lines.append(f"ATE: n/a ({m['ate']['error']})")
    elif "ate" in m:
        a = m["ate"]
        lines.append(f"ATE RMSE ({a.get('align', 'sim3')}): {_fmt(a.get('rmse'))}  "
                     f"= {_fmt(a.get('rmse_percent_of_path'), '.3f')} % of the {_fmt(a.get('path_length'), '.1f')} path")
    if "rpe" in m:
        lines.append(f"RPE trans RMSE: {_fmt(_get(m, 'rpe', 'trans_rmse'))}  rot RMSE: {_fmt(_get(m, 'rpe', 'rot_rmse'), '.3f')} deg")
    if "loops" in m:
        lines.append(_loop_line(m["loops"], num_loops))
    if "panoptic" in m:
        lines.append(_panoptic_line(m["panoptic"], run_dir))
    return lines


def _loop_line(lp: dict, num_loops: int) -> str:
    if lp.get("error"):
        return f"loops: n/a ({lp['error']})"
    n = lp.get("num_detected", num_loops)
    precision = _value(lp.get("precision"), ".2f", "no loop detected" if n == 0 else "not computed")
    recall = _value(lp.get("recall"), ".2f", "no true loop among the frames run" if lp.get("num_gt_events") == 0
                    else "not computed")
    return f"loops: {n} detected  precision {precision}  recall {recall}"


def _panoptic_line(p: dict, run_dir: Optional[str]) -> str:
    if p.get("error"):
        return f"PQ: n/a ({p['error']})"
    other = _other_categories(p, run_dir)
    if other is not None:
        return f"PQ: n/a ({other})  VPQ: n/a"
    return (f"PQ: {_value(p.get('pq'), '.3f', 'no labelled category occurs')}  "
            f"VPQ: {_value(p.get('vpq'), '.3f', 'too few frames with labels')}")


def _other_categories(p: dict, run_dir: Optional[str]) -> Optional[str]:
    """Why PQ means nothing here: the panoptic output's categories (``panoptic/segments.json``: the segmenter's)
    are not the labels' it was compared with (the same id names other classes, or no id is shared); else None."""
    per = (p.get("pq_detail") or {}).get("per_category") or {}
    labels = {int(k): str(v.get("name")) for k, v in per.items() if isinstance(v, dict) and "name" in v}
    if run_dir is None or not labels:
        return None
    try:
        from .outputs.panoptic_png import read_segments_json

        ours = {int(c["id"]): str(c.get("name")) for c in read_segments_json(Path(run_dir) / "panoptic")["categories"]}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    shared = sorted(set(ours) & set(labels))
    differ = [i for i in shared if ours[i] != labels[i]]
    if ours and not shared:
        return "the segmenter's categories are not the labels': no category id in common"
    if differ:
        i = differ[0]
        return (f"the segmenter's categories are not the labels': {len(differ)} of {len(shared)} shared ids name "
                f"other classes, e.g. id {i} is {ours[i]!r} vs {labels[i]!r}")
    return None


def comparison_rows(results: list[tuple[str, RunResult]]) -> list[dict[str, Any]]:
    rows = []
    for name, r in results:
        m = r.metrics
        failed = bool(m.get("failed"))
        rows.append({
            "variant": name,
            "status": "failed" if failed else "ok",
            "error": m.get("error") if failed else None,
            "ate_rmse": _get(m, "ate", "rmse"),
            "ate_percent": _get(m, "ate", "rmse_percent_of_path"),
            "rpe_trans": _get(m, "rpe", "trans_rmse"),
            "loops": len(r.loops),
            "loop_precision": _get(m, "loops", "precision"),
            "PQ": _get(m, "panoptic", "pq"),
            "VPQ": _get(m, "panoptic", "vpq"),
            "fps": _get(m, "timing", "fps"),
            "keyframes": _get(m, "timing", "keyframes"),
            "run_dir": r.run_dir,
        })
    return rows


def comparison_table(results: list[tuple[str, RunResult]]) -> str:
    rows = comparison_rows(results)
    for r in rows:
        r["state"] = "FAILED" if r["status"] == "failed" else "ok"
    cols = [("variant", "variant", "s"), ("status", "state", "s"), ("ATE rmse", "ate_rmse", ".4f"),
            ("ATE %path", "ate_percent", ".3f"),
            ("RPE", "rpe_trans", ".4f"), ("loops", "loops", "d"), ("PQ", "PQ", ".3f"), ("VPQ", "VPQ", ".3f"),
            ("fps", "fps", ".1f"), ("KFs", "keyframes", "d")]
    table = [[h for h, _, _ in cols]]
    for r in rows:
        table.append([r[k] if spec == "s" else _fmt(r[k], spec if spec != "d" else ".0f") for _, k, spec in cols])
    widths = [max(len(str(row[i])) for row in table) for i in range(len(cols))]
    out = []
    for n, row in enumerate(table):
        out.append("  ".join(str(c).ljust(widths[i]) for i, c in enumerate(row)))
        if n == 0:
            out.append("  ".join("-" * w for w in widths))
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        out.append("\nFAILED variants (the others ran):")
        out += [f"  {r['variant']}: {r['error']}" for r in failed]
    if rows:
        out.append(f"\nrun directories under: {rows[0]['run_dir'].rsplit('/', 1)[0] if rows[0]['run_dir'] else '-'}")
    return "\n".join(out)
