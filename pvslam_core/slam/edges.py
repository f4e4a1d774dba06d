"""Which frame-graph edges a new keyframe gets and which edges retire (DROID-SLAM style; DROID-SLAM reference
notes, shared/reference/anchors.md section 1.5).

* neighbour edges to the previous ``neighbours`` keyframes;
* proximity edges to older keyframes inside ``proximity_window`` whose frame distance (mean induced flow at the
  BA resolution, under the current estimate) is below ``proximity_thresh``, greedily by distance with index NMS;
* loop edges ``(i, j-1), (i, j), (i, j+1)`` for a detected loop ``i <-> j`` (the paper adds the two outer ones).

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
