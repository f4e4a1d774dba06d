"""Observing edges and the window BA of a new keyframe: a part of :class:`~.mapper.Mapper` (a mixin that uses its
``graph``, ``frontend``, ``optimizer``, ``observed``, ``cfg``, ``cpu``, ``ba_shape``, ``fragment_start`` and
``second_starts`` / ``second_starts_kept``).

Per window BA: ``rounds`` x (the frontend's observations of the active edges, the stored ones of the retired edges
near the window (:func:`.edges.frozen_edges`), the frontend's depth and distance priors, the measured-depth factor
(:mod:`.observed`); one optimizer step); then the pixels the edges measured are marked.  After a stretch without
parallax the window BA of a new keyframe also runs from a second start (:mod:`.motion_start`).
"""
from __future__ import annotations

import logging
from dataclasses import replace
from time import thread_time
from typing import Optional

import torch

from ..geometry.ba import weighted_cost
from ..types import EdgeObservations
from .edges import active_edges, frozen_edges, retirement_mask
from .motion_start import constant_velocity_centre

LOG = logging.getLogger("pvslam")


class WindowBA:
    """Edge observations and the window BA of :class:`~.mapper.Mapper` (see the module docstring)."""

    def _observe(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """The frontend's observations of edges ``ii -> jj`` with the depth prior of their sources."""
        return self._with_prior(self._observe_edges(ii, jj))

    def _observe_edges(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """The frontend's observations (recorded in the graph), without the depth prior: for callers that join
        them with stored ones first and then ask for the prior of the joined sources once."""
        dev = self.graph.device
        obs = self.frontend.observe(self.graph, ii.to(dev), jj.to(dev))
        self.graph.record_observations(obs)
        return obs

    def _with_prior(self, obs: EdgeObservations) -> EdgeObservations:
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

    def _release_pairs(self, ii: torch.Tensor, jj: torch.Tensor) -> None:
        """Tell the frontend that observed pairs which are not active edges (initialisation) are done with."""
        not_edge = ~self.graph.has_edges(ii, jj)
        if bool(not_edge.any()):
            ids = self.graph.ids
            dev = self.graph.device
            self.frontend.on_edges_retired(ids[ii.to(dev)[not_edge]], ids[jj.to(dev)[not_edge]])

    def _optimize_window(self, k: int, rounds: int) -> None:
        self.graph.retire_edges(retirement_mask(self.graph, k, self.cfg))
        self._mark(self._window_rounds(k, rounds)[1])

    def _window_rounds(self, k: int, rounds: int) -> tuple[list[EdgeObservations], Optional[EdgeObservations]]:
        """``rounds`` x (observe the active edges of the window ending at ``k``, one optimizer step; the edges age).
        Returns each round's observations as given to the optimizer and the last round's before the measured-depth
        factor (.observed; None without edges)."""
        given, seen = [], None
        for _ in range(rounds):
            ii, jj = active_edges(self.graph, k, self.cfg.active_window)
            if ii.numel() == 0:
                break
            t0 = thread_time()
            obs = seen = self._with_prior(self._with_frozen(self._observe_edges(ii, jj), k))
            if self.observed.weight < 1.0:
                f = self.observed.factor(self.graph.ids[obs.ii].tolist(), self.ba_shape, obs.weight.device)
                obs = replace(obs, weight=obs.weight * f)
            given.append(obs)
            t1 = thread_time()
            self._step(k, obs)
            self.cpu["edges"] += t1 - t0
            self.graph.age_edges(ii, jj)
        return given, seen

    def _step(self, k: int, obs: EdgeObservations) -> None:
        t0 = thread_time()
        report = self.optimizer.step(self.graph, obs)
        self.cpu["ba"] += thread_time() - t0
        if report.rejected:
            LOG.warning("keyframe %d: optimizer rejected an update: %s", k, report.message)

    def _mark(self, seen: Optional[EdgeObservations]) -> None:
        """After a window BA: the depth pixels its last observations ``seen`` measured (:mod:`.observed`)."""
        if self.observed.active and seen is not None:
            g = self.graph
            self.observed.mark(g.poses, g.disps, g.intrinsics, g.ids.tolist(), seen.ii, seen.jj, seen.weight)

    def _optimize_new(self, k: int, rounds: int) -> None:
        """The window BA of a new keyframe ``k``; after a stretch without parallax also from its constant-velocity
        centre (:mod:`.motion_start`).  The second run reuses the first one's observations round by round (the
        frontend is not asked again: a frontend's observations may depend on how often, and at which estimate, it was
        asked) and the result with the lower flow cost under the first round's observations, those from the common
        start, is kept."""
        c = self.cfg
        centre = None
        if c.second_start and self.observed.active:
            centre = constant_velocity_centre(self.graph, k, self.observed.fraction, c.guess_min_measured,
                                              c.second_start_span, c.second_start_horizon, first=self.fragment_start)
        if centre is None:
            self._optimize_window(k, rounds)
            return
        g = self.graph
        g.retire_edges(retirement_mask(g, k, c))
        start = (g.poses.clone(), g.disps.clone())
        given, seen = self._window_rounds(k, rounds)  # from the pose guess
        if not given:
            return
        cost_guess = weighted_cost(g, given[0])
        guess_result = (g.poses.clone(), g.disps.clone())
        g.poses.copy_(start[0])
        g.disps.copy_(start[1])
        g.poses[k, :3] = centre.to(g.poses)
        for obs in given:
            self._step(k, obs)
        self.second_starts += 1
        if weighted_cost(g, given[0]) < cost_guess:
            self.second_starts_kept += 1
        else:
            g.poses.copy_(guess_result[0])
            g.disps.copy_(guess_result[1])
        self._mark(seen)

    def _with_frozen(self, obs: EdgeObservations, k: int) -> EdgeObservations:
        """``obs`` plus the stored observations of the retired edges :func:`.edges.frozen_edges` selects (no depth
        prior: the caller asks for the joined sources', :meth:`_with_prior`)."""
        ri, rj = frozen_edges(self.graph, k, self.cfg, first=self.fragment_start)
        if ri.numel() == 0:
            return obs
        frozen = self.graph.retired_observations(ri, rj)
        return _concat([obs, frozen], torch.arange(obs.ii.numel() + ri.numel()))

    def observe_any(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """Observations of any edges: retired ones from the graph's store, the others from the frontend."""
        g = self.graph
        ii, jj = ii.to(g.device), jj.to(g.device)
        retired = g.is_retired(ii, jj).to(g.device) & ~g.has_edges(ii, jj)
        if not bool(retired.any()):
            return self._observe(ii, jj)
        live = torch.nonzero(~retired).squeeze(1)
        dead = torch.nonzero(retired).squeeze(1)
        parts = [self._observe_edges(ii[live], jj[live])] if len(live) else []
        parts.append(g.retired_observations(ii[dead], jj[dead]))
        order = torch.argsort(torch.cat([live, dead]))
        return self._with_prior(_concat(parts, order))


def _concat(parts: list[EdgeObservations], order: torch.Tensor) -> EdgeObservations:
    """Concatenate observations and reorder the edges by ``order`` (a permutation of the concatenated rows)."""
    def cat(name):
        vals = [getattr(p, name) for p in parts]
        if any(v is None for v in vals):
            if name != "dynamic":
                return None
            vals = [v if v is not None else torch.zeros(p.target.shape[0], *p.target.shape[-2:], device=p.target.device)
                    for v, p in zip(vals, parts)]
        return torch.cat([v.to(parts[0].target.device) for v in vals])[order.to(parts[0].target.device)]

    damping = next((p.depth_damping for p in parts if p.depth_damping is not None), None)
    # (no depth prior: it is per depth source, and the caller asks for the joined edges' sources, _with_prior)
    return EdgeObservations(cat("ii"), cat("jj"), cat("target"), cat("weight"), dynamic=cat("dynamic"),
                            depth_damping=damping)
