"""Human-readable summaries of runs and ablation comparison tables."""
from __future__ import annotations

from typing import Any

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
        return format(float(v), spec)
    except (TypeError, ValueError):
        return str(v)


def summary_lines(result: RunResult) -> list[str]:
    m = result.metrics
    lines = [f"run directory: {result.run_dir}"]
    t = m.get("timing", {})
    lines.append(f"frames: {t.get('frames')}  keyframes: {t.get('keyframes')}  "
                 f"time: {_fmt(t.get('seconds'), '.1f')} s  ({_fmt(t.get('fps'), '.1f')} frames/s)")
    if "ate" in m:
        a = m["ate"]
        lines.append(f"ATE RMSE ({a.get('align', 'sim3')}): {_fmt(a.get('rmse'))}  "
                     f"= {_fmt(a.get('rmse_percent_of_path'), '.3f')} % of the {_fmt(a.get('path_length'), '.1f')} path")
    if "rpe" in m:
        lines.append(f"RPE trans RMSE: {_fmt(_get(m, 'rpe', 'trans_rmse'))}  rot RMSE: {_fmt(_get(m, 'rpe', 'rot_rmse'), '.3f')} deg")
    if "loops" in m:
        lp = m["loops"]
        lines.append(f"loops: {lp.get('num_detected', len(result.loops))} detected  precision {_fmt(lp.get('precision'), '.2f')}  "
                     f"recall {_fmt(lp.get('recall'), '.2f')}")
    if "panoptic" in m:
        p = m["panoptic"]
        lines.append(f"PQ: {_fmt(p.get('pq'), '.3f')}  VPQ: {_fmt(p.get('vpq'), '.3f')}")
    return lines


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
