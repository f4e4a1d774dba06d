"""The loop policy: which of a detector's candidates close a loop, and whether a closure runs a loop BA.

Detectors only *propose* (retrieval, optionally geometric verification).  Every acceptance rule lives here, in one
place, configured by the ``[loop_closure]`` table and the constants below:

1. verification: ``verified is True`` is accepted; ``verified is None`` (a retrieval-only detector) only with
   ``accept_unverified``; ``verified is False`` never;
2. consecutive hits: the last ``consecutive - 1`` keyframes must also have proposed (not necessarily accepted) a
   candidate within ``CONSECUTIVE_TOLERANCE + m`` keyframes of the same place (DPVO's rule);
3. suppression: a candidate within ``NMS_KEYFRAMES`` (both ends) of a loop accepted from an earlier keyframe is
   dropped - along a revisit every keyframe would close a loop with its neighbour of the last lap.  On repeated
   laps that is not enough: a place seen on laps 1..L would be closed again to *each* earlier lap.  So accepted
   closures also build *places*: connected components (union-find over keyframe ids) of closure endpoints, where a
   closure joins its two keyframes and every earlier endpoint within ``NMS_KEYFRAMES`` of either (the temporal
   neighbourhood).  A candidate ``(i, j)`` is dropped when a closure accepted within ``PLACE_RECENT x
   NMS_KEYFRAMES`` keyframes before ``i`` belongs to a place of more than two keyframes (tied to more than one
   earlier view) that has an endpoint within ``PLACE_RECENT x NMS_KEYFRAMES`` of ``j``: the new keyframe is already
   tied to that place, whichever lap ``j`` is on (docs/decisions.md: PLACE_RECENT).  :meth:`LoopPolicy.suppressed`
   is also handed to the detector as ``skip`` so it need not verify such candidates;
4. orientation: the two keyframes' current orientations must differ by at most ``max_rotation_deg`` (look-alike
   places seen from opposite directions) - except between two map fragments not merged yet (see
   :mod:`.fragments`): their frames are unrelated until the loop merges them, so only a geometrically verified
   candidate (``verified is True``) is accepted there, flagged ``merge`` for the loop closer to relocalise and align;
5. at most one closure per keyframe: the best remaining candidate of the *most recent* visit (within 2 x
   ``NMS_KEYFRAMES`` of the newest ``j``), before any older lap's, whatever their scores.  The loop BA's Sim(3)
   pose graph sees only the new loop and the odometry chain from ``j`` to ``i``: it bends every keyframe in
   between and none before ``j``.  Closing to lap 1 from lap 4 bends laps 1-3 away from the closures that tie them
   together; closing to lap 3 bends laps 3-4 only (docs/decisions.md: MOST RECENT VISIT FIRST);
6. loop BA gating: a closure accepted fewer than ``LOOP_BA_MIN_GAP`` keyframes after the last loop BA only adds its
   edges (the window BA of the following keyframes includes them); a merge of two map fragments always runs its loop
   BA (docs/decisions.md: LOOP_BA_MIN_GAP).

Keyframes are named by stable id; index distances are taken in the current graph.  Poses are T_wc.
"""
from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass
from typing import Optional

import torch

from ..types import LoopCandidate, LoopClosure
from .config import LoopClosureSection
from .fragments import Fragments
from .graph import FrameGraph

LOG = logging.getLogger("pvslam")

CONSECUTIVE_TOLERANCE = 3  # keyframe slack when checking that consecutive candidates point at the same place
NMS_KEYFRAMES = 5  # suppression radius (keyframes, both ends) around accepted loops (0: none)
# a loop accepted fewer than this many keyframes after the last loop BA only adds its edges: on repeated laps nearly
# every keyframe closes a loop, and a loop BA for each slows the run down (docs/decisions.md: LOOP_BA_MIN_GAP)
LOOP_BA_MIN_GAP = 8
# A closure suppresses candidates into its place from keyframes up to PLACE_RECENT x NMS_KEYFRAMES after it: the
# plain rule lets a continuous revisit close every NMS_KEYFRAMES + 1 keyframes, which is what a first revisit needs
# (the drift since the last lap); a place already tied to earlier laps needs half as many.
PLACE_RECENT = 2


class UnionFind:
    """Union-find over keyframe ids (path halving, union by size): the places of accepted closures, the parts of
    the map that edges link (:mod:`.revisits`)."""

    def __init__(self) -> None:
        self.parent: dict[int, int] = {}
        self.size: dict[int, int] = {}

    def find(self, x: int) -> int:
        p = self.parent.setdefault(x, x)
        while p != x:
            gp = self.parent.setdefault(p, p)
            self.parent[x] = gp
            x, p = p, gp
        return x

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return
        if self.size.get(ra, 1) < self.size.get(rb, 1):
            ra, rb = rb, ra
        self.parent[rb] = ra
        self.size[ra] = self.size.get(ra, 1) + self.size.get(rb, 1)


def rotation_deg(q1: torch.Tensor, q2: torch.Tensor) -> float:
    """Angle in degrees between two orientations given as unit quaternions ``[x, y, z, w]``."""
    dot = float((q1.double() * q2.double()).sum().abs().clamp(max=1.0))
    return float(torch.rad2deg(2 * torch.acos(torch.tensor(dot))))


@dataclass
class LoopDecision:
    closure: LoopClosure
    run_loop_ba: bool
    merge: bool = False  # the two keyframes are in map fragments not merged yet (rule 4)


class LoopPolicy:
    """Accepts loop closures (see the module docstring); keeps the accepted closures and the proposal history."""

    def __init__(self, cfg: LoopClosureSection, graph: FrameGraph, fragments: Optional[Fragments] = None) -> None:
        self.cfg = cfg
        self.graph = graph
        self.closures: list[LoopClosure] = []
        self._proposed: dict[int, list[int]] = {}  # new keyframe id -> old keyframe ids it proposed (bounded)
        self._last_loop_ba_n: Optional[int] = None  # graph size at the last loop BA
        self.places = UnionFind()  # rule 3: places of accepted closures
        self._endpoints: list[int] = []  # sorted stable ids of accepted closures' keyframes
        self.fragments = fragments  # the map fragments (rule 4), if any

    # ------------------------------------------------------------------------------------------- rules --
    def _index(self, kf_id: int) -> int:
        """Graph index of ``kf_id``, -1 when it is gone (a bisection of the graph's id list: this runs for every
        candidate against every recent closure, thousands of times per lap on repeated laps)."""
        try:
            return self.graph.index_of(kf_id)
        except KeyError:
            return -1

    def endpoints_near(self, j: int, radius: Optional[int] = None) -> list[int]:
        """Ids of accepted closures' keyframes within ``radius`` (default ``NMS_KEYFRAMES``) of graph index ``j``
        (ids grow with the index, so the id range of ``[j - n, j + n]`` is a bisection of the sorted endpoint ids)."""
        g = self.graph
        n = NMS_KEYFRAMES if radius is None else radius
        if j < 0 or not self._endpoints:
            return []
        lo, hi = g.id_of(max(0, j - n)), g.id_of(min(g.n - 1, j + n))
        a, b = bisect.bisect_left(self._endpoints, lo), bisect.bisect_right(self._endpoints, hi)
        return [e for e in self._endpoints[a:b] if self._index(e) >= 0]

    def suppressed(self, i_id: int, j_id: int) -> bool:
        """Rule 3: within ``NMS_KEYFRAMES`` of a loop accepted from an earlier keyframe, or into the place of a
        closure accepted shortly before (see the module docstring)."""
        n = NMS_KEYFRAMES
        if n <= 0 or not self.closures:
            return False
        i, j = self._index(i_id), self._index(j_id)
        roots: set[int] = set()
        for c in self.closures[-64:]:  # only recent closures can be near the newest keyframe
            if c.kf_i == i_id:
                continue
            ci, cj = self._index(c.kf_i), self._index(c.kf_j)
            if ci >= 0 and cj >= 0 and abs(ci - i) <= n and abs(cj - j) <= n:
                return True
            if ci >= 0 and abs(ci - i) <= PLACE_RECENT * n:
                root = self.places.find(c.kf_i)
                if self.places.size.get(root, 1) > 2:  # tied to more than one earlier view (else the plain rule)
                    roots.add(root)
        # the candidate is as far along the place as the new keyframe is from the closure: up to PLACE_RECENT x n
        return bool(roots) and any(self.places.find(e) in roots for e in self.endpoints_near(j, PLACE_RECENT * n))

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
            if not any(jp >= 0 and abs(j - jp) <= CONSECUTIVE_TOLERANCE + m for jp in idx):
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
        # rule 5: the candidates of the most recent visit (within 2 x NMS_KEYFRAMES of the newest one) first, in the
        # detector's order (best first), then the others in the detector's order
        if len(ok) > 1:
            newest = max(self._index(c.j) for c in ok)
            span = 2 * max(NMS_KEYFRAMES, 1)
            ok = sorted(ok, key=lambda c: self._index(c.j) < newest - span)  # stable: keeps the order within
        for c in ok:
            i, j = self._index(c.i), self._index(c.j)
            if i < 0 or j < 0 or j >= i:
                continue
            if not self._consecutive_ok(c.i, c.j) or self.suppressed(c.i, c.j):
                continue
            merge = self.fragments is not None and not self.fragments.same(c.i, c.j)
            if merge and c.verified is not True:
                continue  # a merge moves a whole fragment: retrieval alone is not enough
            rot = rotation_deg(g.poses[i, 3:], g.poses[j, 3:])
            if not merge and rot > self.cfg.max_rotation_deg:
                LOG.info("loop %d <-> %d rejected: current orientations differ by %.0f deg", i, j, rot)
                continue
            n = g.n
            recent_ba = self._last_loop_ba_n is not None and 0 <= n - self._last_loop_ba_n < LOOP_BA_MIN_GAP
            run_ba = merge or not recent_ba
            closure = LoopClosure(int(g.frame_index[i]), int(g.frame_index[j]), c.i, c.j, c.score, c.verified,
                                  c.inliers, loop_ba=run_ba)
            return LoopDecision(closure, run_ba, merge)
        return None

    def accepted(self, decision: LoopDecision) -> None:
        """Record a closure whose edges were added (and whose loop BA ran, if it was to)."""
        c = decision.closure
        self.closures.append(c)
        near = self.endpoints_near(self._index(c.kf_i)) + self.endpoints_near(self._index(c.kf_j))
        self.places.union(c.kf_i, c.kf_j)
        for e in near:  # the temporal neighbourhood: the same place on the laps already tied to those endpoints
            self.places.union(c.kf_j, e)
        for e in (c.kf_i, c.kf_j):
            at = bisect.bisect_left(self._endpoints, e)
            if at == len(self._endpoints) or self._endpoints[at] != e:
                self._endpoints.insert(at, e)
        if decision.run_loop_ba:
            self._last_loop_ba_n = self.graph.n
