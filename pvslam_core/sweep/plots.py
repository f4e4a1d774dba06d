"""Sweep plots (matplotlib, Agg canvas, no pyplot state): ATE per variant per sequence as grouped bars with the
std over seeds as error bars, and per sequence the variants' trajectories overlaid on the ground truth (top view).

Each trajectory is aligned to the ground truth on its own, as in its ATE (Sim(3) for monocular runs), through the
evaluation's :func:`~pvslam_core.evaluation.trajectory.aligned_positions`; the plane is the ground truth's two
axes of largest extent (:func:`~pvslam_core.outputs.plots.top_view_axes`), as in a run's own plot.
"""
from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pandas as pd

from ..outputs._atomic import atomic_write_bytes
from . import cells as C
from .spec import SweepPlan, sanitise


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
    return path


def plot_ate_bars(summary: pd.DataFrame, plan: SweepPlan, path: Path) -> Path:
    seqs, vars_ = plan.sequences, plan.variants
    width = 0.8 / max(1, len(vars_))
    fig = _figure((max(5.0, 1.6 * len(seqs) * max(1, len(vars_)) ** 0.5 + 2), 4.0))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(seqs), dtype=float)
    for k, var in enumerate(vars_):
        sub = summary[summary["variant"] == var].set_index("sequence").reindex(seqs)
        mean = sub["ate_rmse_mean"].to_numpy(dtype=float)
        std = np.nan_to_num(sub["ate_rmse_std"].to_numpy(dtype=float), nan=0.0)
        ax.bar(x + (k - (len(vars_) - 1) / 2) * width, np.nan_to_num(mean, nan=0.0), width, yerr=std, capsize=3,
               label=var)
    for i, seq in enumerate(seqs):  # mark the best variant of each sequence
        best = summary[(summary["sequence"] == seq) & summary["best"]]
        if len(best):
            k = vars_.index(best["variant"].iloc[0])
            m = float(best["ate_rmse_mean"].iloc[0])
            s = float(best["ate_rmse_std"].iloc[0]) if not math.isnan(best["ate_rmse_std"].iloc[0]) else 0.0
            ax.annotate("best", (x[i] + (k - (len(vars_) - 1) / 2) * width, m + s), ha="center", va="bottom",
                        fontsize=7)
    ax.set_xticks(x)
    ax.set_xticklabels(seqs)
    ax.set_ylabel("ATE RMSE (mean ± std over seeds)")
    ax.set_title(f"sweep {plan.name}: ATE per variant")
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    return _save(fig, path)


def plot_trajectories(df: pd.DataFrame, plan: SweepPlan, cells_root: Path, out_dir: Path) -> dict[str, Path]:
    """One PNG per sequence: every finished variant of its first seed with a finished cell, and the GT."""
    from ..evaluation.trajectory import aligned_positions
    from ..outputs.metrics import read_json
    from ..outputs.plots import top_view_axes
    from ..outputs.trajectory_io import read_tum

    out: dict[str, Path] = {}
    done = df[df["status"] == C.DONE]
    for seq in plan.sequences:
        sub = done[done["sequence"] == seq]
        if not len(sub):
            continue
        seed = sorted(sub["seed"].unique())[0]
        curves, gt = [], None
        for _, r in sub[sub["seed"] == seed].iterrows():
            d = cells_root / r["cell"]
            if not ((d / "trajectory.txt").is_file() and (d / "groundtruth.txt").is_file()):
                continue
            try:
                align = read_json(d / "metrics.json").get("ate", {}).get("align", "sim3")
                est_ts, est = read_tum(d / "trajectory.txt")
                gt_ts, gt_poses = read_tum(d / "groundtruth.txt")
                a = aligned_positions(est_ts, est, gt_ts, gt_poses, align=align)
            except (ValueError, OSError):  # too few poses to align: leave this variant out of the figure
                continue
            curves.append((r["variant"], a["est_xyz"]))
            if gt is None:
                gt = a["gt_xyz"]
        if gt is None:
            continue
        i, j = top_view_axes(gt)
        fig = _figure((6.0, 5.0))
        ax = fig.add_subplot(1, 1, 1)
        ax.plot(gt[:, i], gt[:, j], "k--", lw=1.5, label="ground truth")
        for var, xyz in curves:
            ax.plot(xyz[:, i], xyz[:, j], lw=1.2, label=var)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
        ax.set_title(f"{seq} (seed {seed}): aligned trajectories, top view")
        ax.legend(fontsize=8)
        ax.grid(True, alpha=0.3)
        out[seq] = _save(fig, out_dir / f"trajectories_{sanitise(seq)}_seed{seed}.png")
    return out
