"""The loop policy: which of a detector's candidates close a loop, and whether a closure runs a loop BA.

Detectors only *propose* (retrieval, optionally geometric verification).  Every acceptance rule lives here, in one
place, configured by the ``[loop_closure]`` table:

1. verification: ``verified is True`` is accepted; ``verified is None`` (a retrieval-only detector) only with
   ``accept_unverified``; ``verified is False`` never;
2. consecutive hits: the last ``consecutive - 1`` keyframes must also have proposed (not necessarily accepted) a
   candidate within ``consecutive_tolerance + m`` keyframes of the same place (DPVO's rule);
3. suppression: a candidate within ``nms_keyframes`` (both ends) of a loop accepted from an earlier keyframe is
   dropped - along a revisit every keyframe would close a loop with its neighbour of the last lap;
   :meth:`LoopPolicy.suppressed` is also handed to the detector as ``skip`` so it need not verify such candidates;
4. orientation: the two keyframes' current orientations must differ by at most ``max_rotation_deg`` (look-alike
   places seen from opposite directions);
5. at most one closure per keyframe (the best remaining candidate);
6. loop BA gating: a closure accepted fewer than ``ba_min_gap`` keyframes after the last loop BA only adds its edges
   (the window BA of the following keyframes includes them).

Keyframes are named by stable id; index distances are taken in the current graph.  Poses are T_wc.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import torch

from ..types import LoopCandidate, LoopClosure

if TYPE_CHECKING:  # pragma: no cover
    from ..config import LoopClosureSection
    from .graph import FrameGraph

LOG = logging.getLogger("pvslam")


def rotation_deg(q1: torch.Tensor, q2: torch.Tensor) -> float:
    """Angle in degrees between two orientations given as unit quaternions ``[x, y, z, w]``."""
    dot = float((q1.double() * q2.double()).sum().abs().clamp(max=1.0))
    return float(torch.rad2deg(2 * torch.acos(torch.tensor(dot))))


@dataclass
class LoopDecision:
    closure: LoopClosure
    run_loop_ba: bool


class LoopPolicy:
    """Accepts loop closures (see the module docstring); keeps the accepted closures and the proposal history."""

    def __init__(self, cfg: "LoopClosureSection", graph: "FrameGraph") -> None:
        self.cfg = cfg
        self.graph = graph
        self.closures: list[LoopClosure] = []
        self._proposed: dict[int, list[int]] = {}  # new keyframe id -> old keyframe ids it proposed (bounded)
        self._last_loop_ba_n: Optional[int] = None  # graph size at the last loop BA

    # ------------------------------------------------------------------------------------------- rules --
    def _index(self, kf_id: int) -> int:
        """Graph index of ``kf_id``, -1 when it is gone (a bisection of the graph's id list: this runs for every
        candidate against every recent closure, thousands of times per lap on repeated laps)."""
        try:
            return self.graph.index_of(kf_id)
        except KeyError:
            return -1

    def suppressed(self, i_id: int, j_id: int) -> bool:
        """Rule 3: within ``nms_keyframes`` of a loop accepted from an earlier keyframe."""
        n = self.cfg.nms_keyframes
        if n <= 0 or not self.closures:
            return False
        i, j = self._index(i_id), self._index(j_id)
        for c in self.closures[-64:]:  # only recent closures can be near the newest keyframe
            if c.kf_i == i_id:
                continue
            ci, cj = self._index(c.kf_i), self._index(c.kf_j)
            if ci >= 0 and cj >= 0 and abs(ci - i) <= n and abs(cj - j) <= n:
                return True
        return False

    def _consecutive_ok(self, i_id: int, j_id: int) -> bool:
        """Rule 2 over the keyframes before ``i_id`` in the current graph."""
        need = self.cfg.consecutive
        if need <= 1:
            return True
        g = self.graph
        i, j = self._index(i_id), self._index(j_id)
        for m in range(1, need):
            if i - m < 0:
                return False
            hits = self._proposed.get(g.id_of(i - m), [])
            idx = [self._index(h) for h in hits]
            if not any(jp >= 0 and abs(j - jp) <= self.cfg.consecutive_tolerance + m for jp in idx):
                return False
        return True

    def _verified_ok(self, c: LoopCandidate) -> bool:
        return c.verified is True or (c.verified is None and self.cfg.accept_unverified)

    # ------------------------------------------------------------------------------------------ decide --
    def decide(self, candidates: list[LoopCandidate]) -> Optional[LoopDecision]:
        """The closure (at most one) accepted among the candidates of the newest keyframe, or None."""
        g = self.graph
        ok = [c for c in candidates if self._verified_ok(c)]
        if candidates:
            i_id = candidates[0].i
            self._proposed[i_id] = [c.j for c in ok]
            if len(self._proposed) > 4 * max(self.cfg.consecutive, 8):  # only the last few keyframes are read
                del self._proposed[next(iter(self._proposed))]
        for c in ok:
            i, j = self._index(c.i), self._index(c.j)
            if i < 0 or j < 0 or j >= i:
                continue
            if not self._consecutive_ok(c.i, c.j) or self.suppressed(c.i, c.j):
                continue
            rot = rotation_deg(g.poses[i, 3:], g.poses[j, 3:])
            if rot > self.cfg.max_rotation_deg:
                LOG.info("loop %d <-> %d rejected: current orientations differ by %.0f deg", i, j, rot)
                continue
            n = g.n
            run_ba = not (self._last_loop_ba_n is not None and 0 <= n - self._last_loop_ba_n < self.cfg.ba_min_gap)
            closure = LoopClosure(int(g.frame_index[i]), int(g.frame_index[j]), c.i, c.j, c.score, c.verified,
                                  c.inliers, loop_ba=run_ba)
            return LoopDecision(closure, run_ba)
        return None

    def accepted(self, decision: LoopDecision) -> None:
        """Record a closure whose edges were added (and whose loop BA ran, if it was to)."""
        self.closures.append(decision.closure)
        if decision.run_loop_ba:
            self._last_loop_ba_n = self.graph.n
