"""The keyframe policy: which of the keyframes the frontend proposes the map keeps (``[graph.keyframes]``).

The frontend's motion filter proposes a keyframe (``TrackResult.is_keyframe``) whenever tracking needs a recent
reference; the map does not need all of them, and a keyframe that is removed right after paying for its edges and
its window BA was wasted work (docs/decisions.md: PROVISIONAL KEYFRAMES).  The life of a proposal
(:class:`KeyframePolicy`):

1. **proposal** (:meth:`~KeyframePolicy.propose`): first the provisional keyframe, if any, is settled (3.); then the
   new keyframe is *provisional* when its frame distance to the newest keyframe (that keyframe's depth, the new
   motion-only pose guess) is already under ``redundant_thresh``, else *ordinary*.  Right after a removal the next
   keyframe is ordinary: chains of provisional keyframes judged on pose guesses alone thin the map.
2. **provisional**: the tracking reference of the next frames (graph entry, frontend features, loop description,
   frame anchor) with no edges, BA or loop query yet.  **Ordinary**: its edges, the window BA and the loop query;
   after them the keyframe before it is removed when it is redundant (4.).
3. **settling** (at the next proposal, a re-initialisation and the end of the run): a provisional keyframe that is
   still redundant under the current estimate goes (its frames are placed by motion-only BA against it first, so it
   is never optimised); otherwise it gets its edges now and the next window BA optimises it.
4. **redundancy**: the symmetric frame distance to the keyframe before (:func:`.flow_distance.keyframe_distance`:
   the mean and the 90th percentile of the induced flow) is under ``redundant_thresh`` -- unless removing it would
   leave more than ``max_gap_s`` seconds between the keyframes around it, or a loop edge touches it.  The first two
   keyframes of a fragment always stay.

A removal tells every GraphListener (frame poses, frontend, loop detector, map state).  Keyframes are named by
stable id; ``k`` and ``r`` are graph indices.  Poses are T_wc.
"""
from __future__ import annotations

import logging
from typing import Callable, Optional

import torch

from .config import KeyframesConfig
from .flow_distance import keyframe_distance
from .graph import EDGE_LOOP
from .map_state import MapState

LOG = logging.getLogger("pvslam")

# a keyframe is redundant only when the 90th percentile of its per-pixel distance is also under this (reference BA
# px, adapt.ba_px_scale): where most of the view is far the mean stays small while the near field moves
# (docs/decisions.md: REDUNDANT_MAX_FLOW)
REDUNDANT_MAX_FLOW = 4.0


class KeyframePolicy:
    """Provisional and ordinary keyframes, settling, the redundancy test and removal (see the module docstring).

    ``connect(k)`` gives keyframe ``k`` its edges (the edge policy)."""

    def __init__(self, cfg: KeyframesConfig, state: MapState, connect: Callable[[int], None]) -> None:
        self.cfg = cfg
        self.state = state
        # the thresholds in this camera's BA px (they are angles of view: adapt.ba_px_scale)
        self.thresh = cfg.redundant_thresh * state.px_scale
        self.max_flow = REDUNDANT_MAX_FLOW * state.px_scale
        self.connect = connect
        self.provisional: Optional[int] = None  # id of the provisional keyframe (the newest), if any
        self.provisional_removed = 0  # provisional keyframes removed without ever being optimised
        self._bracket_from: Optional[int] = None  # id of the keyframe a settled removal left newest

    # --------------------------------------------------------------------------------------- proposals --
    def propose(self, pose: torch.Tensor, timestamp: float) -> bool:
        """A keyframe is proposed at ``pose`` (its motion-only guess) and ``timestamp``: settle the provisional one
        first, then say whether the new one is provisional (1. in the module docstring)."""
        removed = self.settle(next_ts=timestamp)
        self._bracket_from = self.state.graph.id_of(-1) if removed else None
        return not removed and self._would_be_redundant(pose, timestamp)

    def added(self, kf_id: int, provisional: bool = False) -> None:
        """Keyframe ``kf_id`` (the newest) is in the graph, the frontend and the frame poses: provisional, or
        connected now.  After a removal the removed one's frames, held to the keyframe before it so far, are held
        between that one and this keyframe."""
        if provisional:
            self.provisional = kf_id
        else:
            self.connect(self.state.graph.n - 1)
        if self._bracket_from is not None:
            self.state.frames.bracket(self._bracket_from, kf_id)
            self._bracket_from = None

    def settle(self, keep: bool = False, next_ts: Optional[float] = None) -> bool:
        """Decide the provisional keyframe (the newest one) before anything else changes the map: still redundant
        (and not ``keep``) -> its frames are placed and it goes; else it becomes an ordinary keyframe.  ``next_ts``:
        the timestamp of the keyframe about to follow it.  Returns whether it was removed."""
        if self.provisional is None:
            return False
        kf_id, self.provisional = self.provisional, None
        g = self.state.graph
        r = g.index_of(kf_id)
        if not keep and r - 1 > self.state.fragment_start and self.redundancy(r, next_ts) < self.thresh:
            self.state.place_frames(kf_id)
            g.remove_keyframe(r)  # frames anchored to it re-anchor to keyframe r - 1
            self.provisional_removed += 1
            return True
        self.connect(r)
        return False

    # --------------------------------------------------------------------------------------- redundancy --
    def remove_redundant(self, k: int) -> None:
        """After the window BA of the new keyframe ``k``: remove keyframe ``k - 1`` when it is redundant."""
        g = self.state.graph
        r = k - 1
        if r - 1 <= self.state.fragment_start:
            return
        touches_loop = ((g.edge_kind == EDGE_LOOP) & ((g.ii == r) | (g.jj == r))).any()
        if bool(touches_loop):
            return
        d = self.redundancy(r)
        if d >= self.thresh:
            return
        self.state.place_frames(g.id_of(r))
        g.remove_keyframe(r)  # listeners (frame poses, frontend, loop detector, map state) hear of it
        LOG.debug("removed redundant keyframe %d (frame distance %.2f)", r, d)

    def redundancy(self, r: int, next_ts: Optional[float] = None) -> float:
        """Symmetric distance (BA px) of keyframe ``r`` to keyframe ``r - 1`` under the current estimate; infinite
        when removing ``r`` would leave more than ``max_gap_s`` between the keyframes around it (the next one:
        ``r + 1``, else the frame at ``next_ts`` about to become a keyframe, else ``r`` itself)."""
        g = self.state.graph
        after = float(g.timestamps[r + 1]) if r + 1 < g.n else (next_ts if next_ts is not None else
                                                                 float(g.timestamps[r]))
        if after - float(g.timestamps[r - 1]) > self.cfg.max_gap_s:
            return float("inf")  # never redundant (docs/decisions.md: graph.keyframes.max_gap_s)
        return 0.5 * (self._distance(g.poses[r - 1], g.poses[r], g.disps[r - 1])
                      + self._distance(g.poses[r], g.poses[r - 1], g.disps[r]))

    def _would_be_redundant(self, pose: torch.Tensor, timestamp: float) -> bool:
        """Whether a new keyframe at ``pose`` would be removed as redundant: its frame distance from the newest
        keyframe (that keyframe's depth, the new pose guess) is under ``redundant_thresh``."""
        st, g = self.state, self.state.graph
        if not (st.initialized and g.n - 1 > st.fragment_start):
            return False
        if timestamp - float(g.timestamps[-1]) > self.cfg.max_gap_s:
            return False
        return self._distance(g.poses[-1], pose, g.disps[-1]) < self.thresh

    def _distance(self, pose_i: torch.Tensor, pose_j: torch.Tensor, disp_i: torch.Tensor) -> float:
        poses = torch.stack([pose_i.double(), pose_j.to(pose_i.device).double()])
        return keyframe_distance(poses, disp_i, self.state.graph.intrinsics, self.thresh, self.max_flow)
