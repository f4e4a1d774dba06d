"""The sweep's results: one pandas table of every cell's metrics, mean ± std over seeds per (sequence, variant)
with the best variant of each sequence marked, written as CSV and Markdown; then the plots.

Metrics come from each finished cell's ``metrics.json`` (written by the run itself, see
:mod:`pvslam_core.run_outputs`), never from the executor, so the table is the same however the cells ran and can
be rebuilt at any time (``pvslam sweep --report``).  The spread is the sample standard deviation (ddof = 1) over the
seeds that finished; with one seed it is empty.  "Best" = lowest mean ATE RMSE of the sequence.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

import pandas as pd

from ..outputs.metrics import read_json
from . import cells as C
from .spec import SweepPlan

# column -> (path in metrics.json, Markdown header, format)
METRICS: dict[str, tuple[tuple[str, ...], str, str]] = {
    "ate_rmse": (("ate", "rmse"), "ATE RMSE", ".4f"),
    "ate_pct": (("ate", "rmse_percent_of_path"), "ATE % of path", ".3f"),
    "rpe_trans": (("rpe", "trans_rmse"), "RPE trans", ".4f"),
    "rpe_rot_deg": (("rpe", "rot_rmse"), "RPE rot (deg)", ".3f"),
    "loop_precision": (("loops", "precision"), "loop P", ".2f"),
    "loop_recall": (("loops", "recall"), "loop R", ".2f"),
    "loops": (("loops", "num_detected"), "loops", ".1f"),
    "pq": (("panoptic", "pq"), "PQ", ".3f"),
    "vpq": (("panoptic", "vpq"), "VPQ", ".3f"),
    "fps": (("timing", "fps"), "frames/s", ".1f"),
    "keyframes": (("timing", "keyframes"), "KFs", ".0f"),
}
SUMMARY_COLUMNS = ("ate_rmse", "ate_pct", "rpe_trans", "rpe_rot_deg", "loop_precision", "loop_recall", "pq", "vpq",
                   "fps")


def _get(d: Any, path: tuple[str, ...]) -> Optional[float]:
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return None
        d = d[p]
    try:
        return float(d) if d is not None else None
    except (TypeError, ValueError):
        return None


def cell_table(plan: SweepPlan, cells_root: Path) -> pd.DataFrame:
    """One row per cell of the plan (finished or not), in plan order."""
    rows = []
    for c in plan.cells:
        d = cells_root / c.name
        status = C.cell_status(d, c.key)
        row: dict[str, Any] = {"sequence": c.sequence, "seed": c.seed, "variant": c.variant, "status": status}
        metrics: dict = {}
        if status == C.DONE and (d / "metrics.json").is_file():
            metrics = read_json(d / "metrics.json")
        for col, (path, _, _) in METRICS.items():
            row[col] = _get(metrics, path)
        marker = d / ("done.json" if status == C.DONE else "failed.json")
        info = C.read_marker(marker) if marker.is_file() else {}
        row["seconds"] = info.get("seconds")
        row["error"] = info.get("error", "") if status == C.FAILED else ""
        row["cell"] = c.name
        rows.append(row)
    df = pd.DataFrame(rows)
    for col in list(METRICS) + ["seconds"]:
        df[col] = pd.to_numeric(df[col], errors="coerce")
    return df


def summary_table(df: pd.DataFrame, plan: SweepPlan) -> pd.DataFrame:
    """Mean and std over seeds per (sequence, variant) of the finished cells; ``best`` marks the lowest mean ATE."""
    done = df[df["status"] == C.DONE]
    rows = []
    for seq in plan.sequences:
        for var in plan.variants:
            sel = done[(done["sequence"] == seq) & (done["variant"] == var)]
            allc = df[(df["sequence"] == seq) & (df["variant"] == var)]
            row: dict[str, Any] = {"sequence": seq, "variant": var, "seeds_done": len(sel),
                                   "seeds_failed": int((allc["status"] == C.FAILED).sum()), "seeds": len(allc)}
            for col in SUMMARY_COLUMNS:
                vals = sel[col].dropna()
                row[f"{col}_mean"] = float(vals.mean()) if len(vals) else math.nan
                row[f"{col}_std"] = float(vals.std(ddof=1)) if len(vals) > 1 else math.nan
            rows.append(row)
    out = pd.DataFrame(rows)
    out["best"] = False
    for seq in plan.sequences:
        sub = out[(out["sequence"] == seq) & out["ate_rmse_mean"].notna()]
        if len(sub):
            out.loc[sub["ate_rmse_mean"].idxmin(), "best"] = True
    return out


# ------------------------------------------------------------------------------------------------ Markdown --
def _f(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return format(float(v), spec)


def _md(header: list[str], rows: list[list[str]], align_right_from: int) -> str:
    sep = ["---" if i < align_right_from else "---:" for i in range(len(header))]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def summary_markdown(summary: pd.DataFrame) -> str:
    header = ["sequence", "variant", "seeds"] + [METRICS[c][1] for c in SUMMARY_COLUMNS]
    rows = []
    for _, r in summary.iterrows():
        var = f"**{r['variant']}** (best)" if r["best"] else str(r["variant"])
        seeds = f"{r['seeds_done']}/{r['seeds']}" + (f" ({r['seeds_failed']} failed)" if r["seeds_failed"] else "")
        vals = []
        for c in SUMMARY_COLUMNS:
            spec = METRICS[c][2]
            m, s = r[f"{c}_mean"], r[f"{c}_std"]
            txt = _f(m, spec) if math.isnan(s) else f"{_f(m, spec)} ± {_f(s, spec)}"
            vals.append(f"**{txt}**" if r["best"] and c == "ate_rmse" else txt)
        rows.append([str(r["sequence"]), var, seeds] + vals)
    return _md(header, rows, 2)


def cells_markdown(df: pd.DataFrame) -> str:
    cols = ["ate_rmse", "ate_pct", "rpe_trans", "rpe_rot_deg", "loop_precision", "loop_recall", "loops", "pq", "vpq",
            "fps"]
    header = ["sequence", "seed", "variant", "status"] + [METRICS[c][1] for c in cols] + ["seconds"]
    rows = []
    for _, r in df.iterrows():
        status = r["status"] if r["status"] != C.FAILED else f"failed: {str(r['error'])[:80]}".replace("|", "/")
        rows.append([str(r["sequence"]), str(r["seed"]), str(r["variant"]), status]
                    + [_f(r[c], METRICS[c][2]) for c in cols] + [_f(r["seconds"], ".1f")])
    return _md(header, rows, 4)


def write_results(plan: SweepPlan, cells_root: Path, out_dir: Path) -> dict[str, Path]:
    """cells.csv, summary.csv, results.md and (with ``[sweep] plots``) the plots; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    df = cell_table(plan, cells_root)
    summary = summary_table(df, plan)
    paths = {"cells_csv": out_dir / "cells.csv", "summary_csv": out_dir / "summary.csv",
             "markdown": out_dir / "results.md", "summary_md": out_dir / "summary.md"}
    df.to_csv(paths["cells_csv"], index=False)
    summary.to_csv(paths["summary_csv"], index=False)
    n_done = int((df["status"] == C.DONE).sum())
    text = [f"# Sweep {plan.name}", "", f"{n_done} of {len(df)} cells finished; source `{plan.source}`. "
            "Mean ± sample std over seeds; **best** = lowest mean ATE RMSE of the sequence.", "",
            "## Per sequence and variant", "", summary_markdown(summary), "", "## Per cell", "", cells_markdown(df), ""]
    paths["markdown"].write_text("\n".join(text))
    paths["summary_md"].write_text(summary_markdown(summary) + "\n")
    if plan.section.plots and n_done:
        from .plots import plot_ate_bars, plot_trajectories

        paths["ate_plot"] = plot_ate_bars(summary, plan, out_dir / "ate_per_variant.png")
        for seq, p in plot_trajectories(df, plan, cells_root, out_dir).items():
            paths[f"trajectories_{seq}"] = p
    return paths
