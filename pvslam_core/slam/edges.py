"""Which frame-graph edges a new keyframe gets and which edges retire (DROID-SLAM style; DROID-SLAM reference
notes, shared/reference/anchors.md section 1.5).

* neighbour edges to the previous ``neighbours`` keyframes;
* proximity edges to older keyframes inside ``proximity_window`` whose frame distance (mean induced flow at the
  BA resolution, under the current estimate) is below ``proximity_thresh``, greedily by distance with index NMS;
* loop edges ``(i, j-1), (i, j), (i, j+1)`` for a detected loop ``i <-> j`` (the paper adds the two outer ones).

* frozen: retired edges just behind the active window, whose stored observations join the window BA
  (``retired_margin``, off by default);

* retirement: edges that no longer touch the last ``active_window`` keyframes (the window BAs would never use
  them again), edges older than ``max_edge_age`` optimisation rounds, and beyond ``max_active_edges`` the oldest.

The edge functions return ``(ii, jj)`` int64 tensors; with ``bidirectional`` both directions are included.
"""
from __future__ import annotations

import torch

from ..config import GraphSection
from .graph import FrameGraph


def _both(ii: torch.Tensor, jj: torch.Tensor, bidirectional: bool) -> tuple[torch.Tensor, torch.Tensor]:
    if not bidirectional:
        return ii, jj
    return torch.cat([ii, jj]), torch.cat([jj, ii])


def neighbour_edges(k: int, cfg: GraphSection, first: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Edges from keyframe ``k`` to ``k-1 .. k-neighbours`` (not below ``first``, the fragment start)."""
    jj = torch.arange(max(first, k - cfg.neighbours), k, dtype=torch.int64)
    ii = torch.full_like(jj, k)
    return _both(ii, jj, cfg.bidirectional)


def proximity_edges(graph: FrameGraph, k: int, cfg: GraphSection, first: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to ``max_proximity_edges`` edges from ``k`` to older keyframes that look at the same place."""
    lo = max(first, k - cfg.proximity_window)
    hi = k - cfg.neighbours  # exclusive: neighbours are connected already
    empty = torch.zeros(0, dtype=torch.int64)
    if cfg.max_proximity_edges == 0 or hi <= lo:
        return empty, empty
    cand = torch.arange(lo, hi, dtype=torch.int64)
    src = torch.full_like(cand, k)
    d = 0.5 * (graph.frame_distance(src, cand).cpu() + graph.frame_distance(cand, src).cpu())  # [C]
    order = torch.argsort(d)
    chosen: list[int] = []
    for idx in order.tolist():
        if float(d[idx]) > cfg.proximity_thresh or len(chosen) >= cfg.max_proximity_edges:
            break
        j = int(cand[idx])
        if all(abs(j - c) > cfg.proximity_nms for c in chosen):
            chosen.append(j)
    if not chosen:
        return empty, empty
    jj = torch.tensor(chosen, dtype=torch.int64)
    return _both(torch.full_like(jj, k), jj, cfg.bidirectional)


def loop_edges(i: int, j: int, n: int, bidirectional: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Edges ``(i, j-1), (i, j), (i, j+1)`` clipped to existing keyframes ``[0, n)`` and excluding ``i``."""
    jj = torch.tensor([t for t in (j - 1, j, j + 1) if 0 <= t < n and t != i], dtype=torch.int64)
    ii = torch.full_like(jj, i)
    return _both(ii, jj, bidirectional)


def active_edges(graph: FrameGraph, k: int, window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Graph edges that touch one of the last ``window`` keyframes (ending at ``k``)."""
    if graph.ii.numel() == 0:
        return graph.ii, graph.jj
    lo = k - window + 1
    mask = (graph.ii >= lo) | (graph.jj >= lo)
    return graph.ii[mask], graph.jj[mask]


def frozen_edges(graph: FrameGraph, k: int, cfg: GraphSection, first: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Retired edges (with a stored observation) whose both ends lie at most ``cfg.retired_margin`` keyframes
    before the active window ending at ``k`` (and not before ``first``, the fragment start); empty when
    ``retired_margin`` is None.  The window BA uses their last observations as frozen constraints, as DROID-SLAM's
    frontend keeps its inactive edges with both ends >= t0 - 3.  Why: the keyframes just behind the window have
    fixed poses but free depths, and without these edges nothing ties those depths to the fixed poses, so the
    window's scale and the depths it is anchored to can drift together.  Off by default: on the synthetic highway
    it holds the scale (forward_low_parallax tune seeds 2.0-19.0 -> 2.5-3.9 % of the path with a margin of 8), on
    the moving_vehicles street it pulls the scale down as steadily (0.3 -> 0.6-0.9 %, with oracle masks too);
    bench/RESULTS.md, "DROID-SLAM's inactive edges as frozen constraints"."""
    if cfg.retired_margin is None:
        empty = torch.zeros(0, dtype=torch.int64, device=graph.device)
        return empty, empty.clone()
    return graph.retired_edges(max(first, k - cfg.active_window + 1 - cfg.retired_margin))


def retirement_mask(graph: FrameGraph, k: int, cfg: GraphSection) -> torch.Tensor:
    """bool ``[num_edges]``: active edges to retire before keyframe ``k``'s window BA (see the module docstring).
    Edges touching ``k`` itself never retire here (they were just added or are about to be observed)."""
    if graph.num_edges == 0:
        return torch.zeros(0, dtype=torch.bool, device=graph.device)
    lo = k - cfg.active_window + 1
    touches_new = (graph.ii == k) | (graph.jj == k)
    mask = ~((graph.ii >= lo) | (graph.jj >= lo))
    mask |= (graph.edge_age >= cfg.max_edge_age) & ~touches_new
    excess = int((~mask).sum()) - cfg.max_active_edges
    if excess > 0:  # the oldest of the remaining ones (by the keyframe count when they were added)
        cand = torch.nonzero(~mask & ~touches_new).squeeze(1)
        order = torch.argsort(graph.edge_born[cand], stable=True)
        mask[cand[order[:excess]]] = True
    return mask
