"""The edge policy: which frame-graph edges a new keyframe gets and which edges retire (DROID-SLAM's policy;
``[graph.edges]``).

* neighbour edges to the previous ``neighbours`` keyframes;
* proximity edges to older keyframes inside ``proximity_window`` whose frame distance (mean induced flow at the
  BA resolution, under the current estimate) is below ``proximity_thresh``, greedily by distance with index NMS,
  kept only where their parallax stays within what the frontend's flow can follow (:func:`reliable_proximity`);
* loop edges ``(i, j-1), (i, j), (i, j+1)`` for a detected loop ``i <-> j`` (the paper adds the two outer ones);
* retirement: edges that no longer touch the last ``active_window`` keyframes (the window BAs would never use
  them again), edges older than ``max_age`` optimisation rounds, and beyond ``max_active`` the oldest.

Every edge is added in both directions.  The edge functions return ``(ii, jj)`` int64 tensors of graph indices.
"""
from __future__ import annotations

import torch

from .config import EdgesConfig
from .flow_distance import pair_flow_quantile
from .graph import EDGE_ODOMETRY, EDGE_PROXIMITY, FrameGraph

PROXIMITY_NMS = 1  # a proximity edge is not added within this many keyframes (index distance) of a chosen one
# a proximity edge is kept only when the 90th percentile of its translation-only flow (reference BA px,
# adapt.ba_px_scale) is at most this: the frontend's flow does not follow a near field that moves farther
# (docs/decisions.md: PROXIMITY_MAX_FLOW)
PROXIMITY_MAX_FLOW = 8.0


def _both(ii: torch.Tensor, jj: torch.Tensor, bidirectional: bool) -> tuple[torch.Tensor, torch.Tensor]:
    if not bidirectional:
        return ii, jj
    return torch.cat([ii, jj]), torch.cat([jj, ii])


def neighbour_edges(k: int, cfg: EdgesConfig, first: int = 0,
                    bidirectional: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Edges from keyframe ``k`` to ``k-1 .. k-neighbours`` (not below ``first``, the fragment start)."""
    jj = torch.arange(max(first, k - cfg.neighbours), k, dtype=torch.int64)
    ii = torch.full_like(jj, k)
    return _both(ii, jj, bidirectional)


def proximity_edges(graph: FrameGraph, k: int, cfg: EdgesConfig, first: int = 0, nms: int = PROXIMITY_NMS,
                    bidirectional: bool = True, px_scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to ``max_proximity`` edges from ``k`` to older keyframes that look at the same place, none within ``nms``
    keyframes of another (``px_scale``: this camera's BA px per reference BA px, :func:`~pvslam_core.adapt.
    ba_px_scale`)."""
    lo = max(first, k - cfg.proximity_window)
    hi = k - cfg.neighbours  # exclusive: neighbours are connected already
    empty = torch.zeros(0, dtype=torch.int64)
    if cfg.max_proximity == 0 or hi <= lo:
        return empty, empty
    cand = torch.arange(lo, hi, dtype=torch.int64)
    d = graph.mutual_distance(k, cand)  # [C]
    order = torch.argsort(d)
    chosen: list[int] = []
    for idx in order.tolist():
        if float(d[idx]) > cfg.proximity_thresh * px_scale or len(chosen) >= cfg.max_proximity:
            break
        j = int(cand[idx])
        if all(abs(j - c) > nms for c in chosen):
            chosen.append(j)
    if not chosen:
        return empty, empty
    jj = torch.tensor(chosen, dtype=torch.int64)
    return _both(torch.full_like(jj, k), jj, bidirectional)


def reliable_proximity(graph: FrameGraph, ii: torch.Tensor, jj: torch.Tensor, first: int, active_window: int,
                       max_flow: float = PROXIMITY_MAX_FLOW) -> tuple[torch.Tensor, torch.Tensor]:
    """The proximity edges ``(ii, jj)`` whose pair's 90th-percentile parallax (:func:`.flow_distance.
    pair_flow_quantile`, both directions, current estimate) is at most ``max_flow`` BA px (0: all).

    A proximity edge is a long baseline chosen on the *mean* flow, and the near field of a forward-moving camera
    moves farther than the frontend's flow can follow.  A fragment younger than ``active_window`` keyframes keeps
    them all: its depths are still the initialisation's guess, and the long edges are what holds its scale."""
    if max_flow <= 0 or ii.numel() == 0 or int(ii.max()) - first < active_window:
        return ii, jj
    keep = {}
    for a, b in zip(ii.tolist(), jj.tolist()):
        pair = (min(a, b), max(a, b))
        if pair not in keep:  # both directions share the decision
            poses = torch.stack([graph.poses[pair[0]].double(), graph.poses[pair[1]].double()])
            keep[pair] = pair_flow_quantile(poses, graph.disps[pair[0]], graph.disps[pair[1]],
                                            graph.intrinsics) <= max_flow
    mask = torch.tensor([keep[(min(a, b), max(a, b))] for a, b in zip(ii.tolist(), jj.tolist())], dtype=torch.bool)
    return ii[mask], jj[mask]


def connect_keyframe(graph: FrameGraph, k: int, cfg: EdgesConfig, first: int, initialized: bool,
                     px_scale: float = 1.0) -> None:
    """Neighbour edges of keyframe ``k`` (the newest) and, once the map is initialised, its reliable proximity
    edges; none for the first keyframe of a fragment (``first``).  ``px_scale``: this camera's BA px per reference
    BA px (the distance thresholds are angles of view: :func:`~pvslam_core.adapt.ba_px_scale`)."""
    if k <= first:
        return
    ii, jj = neighbour_edges(k, cfg, first=first)
    graph.add_edges(ii, jj, EDGE_ODOMETRY)
    if initialized:
        ii, jj = proximity_edges(graph, k, cfg, first=first, px_scale=px_scale)
        ii, jj = reliable_proximity(graph, ii, jj, first, cfg.active_window, PROXIMITY_MAX_FLOW * px_scale)
        if ii.numel():
            graph.add_edges(ii, jj, EDGE_PROXIMITY)


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


def retirement_mask(graph: FrameGraph, k: int, cfg: EdgesConfig) -> torch.Tensor:
    """bool ``[num_edges]``: active edges to retire before keyframe ``k``'s window BA (see the module docstring).
    Edges touching ``k`` itself never retire here (they were just added or are about to be observed)."""
    if graph.num_edges == 0:
        return torch.zeros(0, dtype=torch.bool, device=graph.device)
    lo = k - cfg.active_window + 1
    touches_new = (graph.ii == k) | (graph.jj == k)
    mask = ~((graph.ii >= lo) | (graph.jj >= lo))
    mask |= (graph.edge_age >= cfg.max_age) & ~touches_new
    excess = int((~mask).sum()) - cfg.max_active
    if excess > 0:  # the oldest of the remaining ones (by the keyframe count when they were added)
        cand = torch.nonzero(~mask & ~touches_new).squeeze(1)
        order = torch.argsort(graph.edge_born[cand], stable=True)
        mask[cand[order[:excess]]] = True
    return mask
