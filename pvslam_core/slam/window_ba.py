"""The window BA of a new keyframe: the online bundle adjustment of the last ``graph.edges.active_window``
keyframes.

Per window BA: edges that left the window retire (:func:`.edges.retirement_mask`), then ``rounds`` x (the
frontend's observations of the active edges with its depth and distance priors, the measured-depth factor
(:mod:`.observed`); one optimizer step; the edges age); then the pixels the edges measured are marked.  After a
stretch without parallax the window BA of a new keyframe also runs from a second start (:mod:`.motion_start`).
"""
from __future__ import annotations

import logging
from dataclasses import replace
from time import thread_time
from typing import Optional

from ..geometry.ba import weighted_cost
from ..types import EdgeObservations
from . import motion_start
from .config import EdgesConfig
from .edges import active_edges, retirement_mask
from .map_state import MapState
from .observe import EdgeObserver

LOG = logging.getLogger("pvslam")

SECOND_START = True  # run a new keyframe's window BA also from its constant-velocity centre after a pan


class WindowBA:
    """Runs the optimizer over the active window (see the module docstring); counts the second starts."""

    def __init__(self, state: MapState, observer: EdgeObserver, optimizer, cfg: EdgesConfig) -> None:
        self.state = state
        self.observer = observer
        self.optimizer = optimizer
        self.cfg = cfg
        self.second_starts = 0  # window BAs also run from the constant-velocity centre (.motion_start) ...
        self.second_starts_kept = 0  # ... and those whose second start won

    def optimize(self, k: int, rounds: int) -> None:
        """The window BA ending at keyframe ``k`` (graph index), ``rounds`` optimizer steps."""
        self.state.graph.retire_edges(retirement_mask(self.state.graph, k, self.cfg))
        self._mark(self._rounds(k, rounds)[1])

    def optimize_new(self, k: int, rounds: int) -> None:
        """The window BA of a new keyframe ``k``; after a stretch without parallax also from its constant-velocity
        centre (:mod:`.motion_start`).  The second run reuses the first one's observations round by round (the
        frontend is not asked again: a frontend's observations may depend on how often, and at which estimate, it was
        asked) and the result with the lower flow cost under the first round's observations, those from the common
        start, is kept."""
        st = self.state
        centre = None
        if SECOND_START and st.observed.active:
            centre = motion_start.constant_velocity_centre(st.graph, k, st.observed.fraction, st.observed.guess_min,
                                                           motion_start.SPAN, motion_start.HORIZON,
                                                           first=st.fragment_start)
        if centre is None:
            self.optimize(k, rounds)
            return
        g = st.graph
        g.retire_edges(retirement_mask(g, k, self.cfg))
        start = (g.poses.clone(), g.disps.clone())
        given, seen = self._rounds(k, rounds)  # from the pose guess
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

    def _rounds(self, k: int, rounds: int) -> tuple[list[EdgeObservations], Optional[EdgeObservations]]:
        """``rounds`` x (observe the active edges of the window ending at ``k``, one optimizer step; the edges age).
        Returns each round's observations as given to the optimizer and the last round's before the measured-depth
        factor (.observed; None without edges)."""
        st, g = self.state, self.state.graph
        given, seen = [], None
        for _ in range(rounds):
            ii, jj = active_edges(g, k, self.cfg.active_window)
            if ii.numel() == 0:
                break
            t0 = thread_time()
            obs = seen = self.observer.observe(ii, jj)
            if st.observed.weight < 1.0:
                f = st.observed.factor(g.ids[obs.ii].tolist(), st.ba_shape, obs.weight.device)
                obs = replace(obs, weight=obs.weight * f)
            given.append(obs)
            t1 = thread_time()
            self._step(k, obs)
            st.cpu["edges"] += t1 - t0
            g.age_edges(ii, jj)
        return given, seen

    def _step(self, k: int, obs: EdgeObservations) -> None:
        t0 = thread_time()
        report = self.optimizer.step(self.state.graph, obs)
        self.state.cpu["ba"] += thread_time() - t0
        if report.rejected:
            LOG.warning("keyframe %d: optimizer rejected an update: %s", k, report.message)

    def _mark(self, seen: Optional[EdgeObservations]) -> None:
        """After a window BA: the depth pixels its last observations ``seen`` measured (:mod:`.observed`)."""
        observed = self.state.observed
        if observed.active and seen is not None:
            g = self.state.graph
            observed.mark(g.poses, g.disps, g.intrinsics, g.ids.tolist(), seen.ii, seen.jj, seen.weight)
