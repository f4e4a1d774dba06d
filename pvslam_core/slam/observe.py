"""Asking the frontend for edge observations: what the window BA, the loop closer and the bootstrap share.

:class:`EdgeObserver` turns graph edges ``ii -> jj`` into the frontend's :class:`~pvslam_core.types.EdgeObservations`
(recorded in the graph, so a retired edge keeps its last one), joined with the frontend's depth and distance priors
of the keyframes they touch; it also tells the frontend when pairs observed outside the graph's edges are done with.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Optional

import torch

from ..types import EdgeObservations
from .graph import FrameGraph


class EdgeObserver:
    """The frontend's observations of frame-graph edges (see the module docstring)."""

    def __init__(self, graph: FrameGraph, frontend) -> None:
        self.graph = graph
        self.frontend = frontend

    def observe(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """The frontend's observations of edges ``ii -> jj`` with the priors of their keyframes."""
        return self.with_prior(self.observe_edges(ii, jj))

    def observe_edges(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """The frontend's observations (recorded in the graph), without the priors: for callers that join them with
        stored ones first and then ask for the priors of the joined keyframes once."""
        dev = self.graph.device
        obs = self.frontend.observe(self.graph, ii.to(dev), jj.to(dev))
        self.graph.record_observations(obs)
        return obs

    def with_prior(self, obs: EdgeObservations) -> EdgeObservations:
        """``obs`` with the frontend's inverse-depth prior (:meth:`Frontend.depth_prior`) for its depth sources and
        its distance prior (:meth:`Frontend.distance_prior`) for the keyframes of its edges."""
        if obs.ii.numel() == 0:
            return obs
        src = torch.unique(obs.ii)
        prior = self.frontend.depth_prior(self.graph, src)
        if prior is not None:
            obs = replace(obs, disp_prior=prior)
        dist = self.frontend.distance_prior(self.graph, torch.unique(torch.cat([obs.ii, obs.jj])))
        if dist is not None:
            obs = replace(obs, dist_prior=dist)
        return obs

    def release(self, ii: torch.Tensor, jj: torch.Tensor) -> None:
        """Tell the frontend that observed pairs which are not active edges (initialisation, relocalisation) are
        done with."""
        not_edge = ~self.graph.has_edges(ii, jj)
        if bool(not_edge.any()):
            ids = self.graph.ids
            dev = self.graph.device
            self.frontend.on_edges_retired(ids[ii.to(dev)[not_edge]], ids[jj.to(dev)[not_edge]])

    def observe_pair(self, a: int, b: int) -> EdgeObservations:
        """One pair ``a -> b`` that is not an edge: observed, then released (never observed again as such)."""
        ii, jj = torch.tensor([a]), torch.tensor([b])
        obs = self.observe(ii, jj)
        self.release(ii, jj)
        return obs

    def observe_any(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """Observations of any edges: retired ones from the graph's store, the others from the frontend."""
        g = self.graph
        ii, jj = ii.to(g.device), jj.to(g.device)
        retired = g.is_retired(ii, jj).to(g.device) & ~g.has_edges(ii, jj)
        if not bool(retired.any()):
            return self.observe(ii, jj)
        live = torch.nonzero(~retired).squeeze(1)
        dead = torch.nonzero(retired).squeeze(1)
        parts = [self.observe_edges(ii[live], jj[live])] if len(live) else []
        # the retired observations go straight into their rows of the joined target and weight (no copy of them all
        # in between: at the final BA they are most of the edges); the part stands in for them with a view
        h, w = g.ba_shape
        first = parts[0] if parts else None
        dev = first.target.device if first is not None else g.device
        joined = {}
        for name in ("target", "weight"):
            dtype = torch.promote_types(getattr(first, name).dtype, torch.float32) if first is not None else \
                torch.float32
            joined[name] = torch.empty(len(ii), 2, h, w, dtype=dtype, device=dev)
            if first is not None:
                joined[name][live.to(dev)] = getattr(first, name).to(dev)
        g.retired_observations_into(ii[dead], jj[dead], joined["target"], joined["weight"], dead)
        view = torch.zeros((), dtype=torch.float32, device=g.device).expand(len(dead), 2, h, w)
        parts.append(EdgeObservations(ii[dead], jj[dead], view, view))
        order = torch.argsort(torch.cat([live, dead]))
        return self.with_prior(concat(parts, order, **joined))


def concat(parts: list[EdgeObservations], order: torch.Tensor, target: Optional[torch.Tensor] = None,
           weight: Optional[torch.Tensor] = None) -> EdgeObservations:
    """Concatenate observations and reorder the edges by ``order`` (a permutation of the concatenated rows).
    ``target`` / ``weight``: the joined ones, already in order (the parts' are then not read)."""
    def cat(name):
        vals = [getattr(p, name) for p in parts]
        if any(v is None for v in vals):
            if name != "dynamic":
                return None
            vals = [v if v is not None else torch.zeros(p.target.shape[0], *p.target.shape[-2:], device=p.target.device)
                    for v, p in zip(vals, parts)]
        return torch.cat([v.to(parts[0].target.device) for v in vals])[order.to(parts[0].target.device)]

    damping = next((p.depth_damping for p in parts if p.depth_damping is not None), None)
    # (no depth prior: it is per depth source, and the caller asks for the joined edges' sources, with_prior)
    return EdgeObservations(cat("ii"), cat("jj"), cat("target") if target is None else target,
                            cat("weight") if weight is None else weight, dynamic=cat("dynamic"),
                            depth_damping=damping)
