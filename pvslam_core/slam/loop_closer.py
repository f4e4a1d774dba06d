"""Loop closing for a new keyframe: the detector's candidates, the loop policy's decision, the loop edges, the loop
BA, and the merge of two map fragments that a loop joins.

Per new keyframe ``k`` (after its window BA)::

    candidates = detector.query(id, skip=policy.suppressed); decision = policy.decide(candidates)   # .loops
    if the decision joins two fragments: relocalise k in the older one's map and move k's fragment there (.fragments)
    loop edges (k, j-1), (k, j), (k, j+1); optimizer.loop(active + loop edges) unless the policy gates it

Poses are T_wc; keyframes are named by stable id, ``k`` and ``j`` are graph indices.
"""
from __future__ import annotations

import logging

import torch

from ..types import LoopClosure
from .config import LoopClosureSection
from .edges import active_edges, loop_edges
from .fragments import align_fragment, fragment_indices, relocalise, replace_gap_frames
from .graph import EDGE_LOOP
from .loops import LoopPolicy
from .map_state import MapState
from .observe import EdgeObserver

LOG = logging.getLogger("pvslam")


class LoopCloser:
    """Closes loops at new keyframes (see the module docstring); ``detector`` may be None (no loop closure)."""

    def __init__(self, cfg: LoopClosureSection, state: MapState, observer: EdgeObserver, optimizer, detector,
                 active_window: int) -> None:
        self.state = state
        self.observer = observer
        self.optimizer = optimizer
        self.detector = detector
        self.active_window = active_window  # the loop BA also observes the window's active edges
        self.policy = LoopPolicy(cfg, state.graph, state.fragments)

    @property
    def loops(self) -> list[LoopClosure]:
        """Accepted loop closures, in order."""
        return self.policy.closures

    def close(self, k: int) -> None:
        """Query the detector for the new keyframe ``k`` and close the loop the policy accepts, if any."""
        if self.detector is None:
            return
        g = self.state.graph
        kf_id = g.id_of(k)
        cands = self.detector.query(kf_id, skip=lambda j_id: self.policy.suppressed(kf_id, j_id))
        decision = self.policy.decide(cands)
        if decision is None:
            return
        c = decision.closure
        j = g.index_of(c.kf_j)
        if decision.merge and not self._merge_fragments(k, j):
            return
        ii, jj = loop_edges(k, j, g.n)
        added = g.add_edges(ii, jj, EDGE_LOOP)
        if not bool(added.any()):
            return
        LOG.info("loop closure: keyframe %d (frame %d) <-> keyframe %d (frame %d), score %.3f, %d inliers%s",
                 k, c.frame_i, j, c.frame_j, c.score, c.inliers, "" if c.verified else " (not verified)")
        self.policy.accepted(decision)
        if not decision.run_loop_ba:
            # along a revisit nearly every keyframe closes a loop: the first one's loop BA (+ pose graph) corrects
            # the drift; later ones only add their edges, which the next window BAs include (they touch k)
            LOG.debug("loop %d <-> %d: edges added; a loop BA ran recently", k, j)
            return
        a_ii, a_jj = active_edges(g, k, self.active_window)
        pair = torch.unique(torch.stack([torch.cat([a_ii.cpu(), ii]), torch.cat([a_jj.cpu(), jj])]), dim=1)
        report = self.optimizer.loop(g, self.observer.observe(pair[0], pair[1]), [c])
        g.age_edges(pair[0], pair[1])
        if report.rejected:
            LOG.warning("loop BA rejected: %s", report.message)
        else:
            LOG.debug("loop BA %d <-> %d: %s", k, j, report.message)

    def _merge_fragments(self, k: int, j: int) -> bool:
        """A verified loop from keyframe ``k`` (current fragment) to ``j`` (an older fragment not merged with it):
        relocalise ``k`` in ``j``'s map from the flow ``j -> k`` and ``j``'s depth, move the current fragment there
        by the Sim(3) this gives, and merge the two (see :mod:`.fragments`).  False when relocalisation fails (the
        loop is then not closed)."""
        st, g = self.state, self.state.graph
        obs = self.observer.observe_pair(j, k)  # not an edge yet: the loop edges that follow are observed afresh
        reloc = relocalise(g.poses[j], g.disps[j], g.disps[k], g.intrinsics, obs.target[0], obs.weight[0])
        if reloc is None:
            LOG.info("fragment merge %d <-> %d: relocalisation failed", k, j)
            return False
        idx = fragment_indices(g, st.fragments, g.id_of(k))
        align_fragment(g, st.frames, idx, k, reloc)
        st.fragments.merge(g.id_of(k), g.id_of(j))
        first = int(idx[0])
        if first > 0 and st.fragments.same(g.id_of(first - 1), g.id_of(k)):
            replace_gap_frames(g, st.frames, first)  # the frames lost between the two, now both in one frame
        LOG.warning("map fragments merged: keyframe %d relocalised against keyframe %d (median error %.2f BA px, "
                    "%d matches, scale %.3g); %d keyframes moved, %d separate map(s) left", k, j, reloc.error,
                    reloc.matched, reloc.scale, len(idx), st.fragments.unmerged)
        return True
