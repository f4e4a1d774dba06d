"""Trajectory plots (matplotlib, Agg canvas, imported lazily; pyplot's global state is never touched).

Files are written atomically (rendered into memory, then temp file + ``os.replace``).
"""
from __future__ import annotations

import io
import os
from typing import Any, Optional

import numpy as np

from ._atomic import atomic_write_bytes

__all__ = ["top_view_axes", "plot_trajectory_top", "plot_error_over_time"]

_AXIS_NAMES = "xyz"


def _np(x: Any) -> Optional[np.ndarray]:
    if x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | os.PathLike) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def top_view_axes(xyz: np.ndarray) -> tuple[int, int]:
    """The two axes with the largest extent (max - min), in increasing index order."""
    ext = np.nanmax(xyz, axis=0) - np.nanmin(xyz, axis=0) if len(xyz) else np.zeros(3)
    a, b = sorted(np.argsort(-ext, kind="stable")[:2].tolist())
    return a, b


def plot_trajectory_top(
    path: str | os.PathLike,
    est_xyz: Any,
    gt_xyz: Optional[Any] = None,
    errors: Optional[Any] = None,
    title: str = "",
) -> tuple[int, int]:
    """Top view of the (aligned) estimate, coloured by per-pose error when given, with the GT dashed.

    The plane is chosen automatically: the two axes with the largest extent (of the GT when given). Returns the
    two axis indices used.
    """
    from matplotlib.collections import LineCollection

    est = _np(est_xyz).reshape(-1, 3)
    gt = _np(gt_xyz)
    err = _np(errors)
    a, b = top_view_axes(gt.reshape(-1, 3) if gt is not None and len(gt) else est)
    fig = _figure((7, 6))
    ax = fig.add_subplot(1, 1, 1)
    if gt is not None and len(gt):
        ax.plot(gt[:, a], gt[:, b], linestyle="--", color="0.3", linewidth=1.2, label="ground truth")
    if err is not None and len(err) == len(est) and len(est) > 1:
        seg = np.stack([est[:-1][:, [a, b]], est[1:][:, [a, b]]], axis=1)
        lc = LineCollection(seg, cmap="viridis", linewidth=2.0)
        lc.set_array(0.5 * (err[:-1] + err[1:]))
        ax.add_collection(lc)
        cb = fig.colorbar(lc, ax=ax)
        cb.set_label("ATE [m]")
        ax.plot([], [], color="tab:green", label="estimate (colour = error)")
    else:
        ax.plot(est[:, a], est[:, b], color="tab:blue", linewidth=1.5, label="estimate")
    if len(est):
        ax.plot(est[0, a], est[0, b], "o", color="tab:red", markersize=5, label="start")
    ax.set_xlabel(f"{_AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    _save(fig, path)
    return a, b


def plot_error_over_time(path: str | os.PathLike, timestamps: Any, errors: Any, title: str = "") -> None:
    """Per-pose error against time (seconds from the first pose), with the RMSE as a horizontal line."""
    t = _np(timestamps).reshape(-1)
    e = _np(errors).reshape(-1)
    if len(t) != len(e):
        raise ValueError(f"plot_error_over_time: {len(t)} timestamps but {len(e)} errors")
    fig = _figure((8, 3.5))
    ax = fig.add_subplot(1, 1, 1)
    t0 = t[0] if len(t) else 0.0
    ax.plot(t - t0, e, color="tab:blue", linewidth=1.2, label="error")
    if len(e):
        rmse = float(np.sqrt(np.mean(e**2)))
        ax.axhline(rmse, color="tab:red", linestyle="--", linewidth=1.0, label=f"RMSE {rmse:.4g} m")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("ATE [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    _save(fig, path)
