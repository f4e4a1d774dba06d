"""Keyframes on a revisit: culled when they leave the window if the map already holds their view
(``graph.keyframes.revisit_thresh``).

Driving the same place again makes new keyframes where the map has keyframes already, so without culling the map,
the final BA and the memory grow with the time driven, not with the places seen.  Along a revisit the loop policy
closes a loop every few keyframes (:mod:`.loop_closer`).  A keyframe ``r`` that left the optimisation window (it is
``active_window`` keyframes behind the newest) is examined once the map has settled after the newest loop BA:

1. **candidates**: the older keyframes near the partner of a loop closed near ``r`` (:data:`LOOP_REACH`);
2. **view**: the candidates under ``revisit_thresh`` of frame distance from ``r`` under the current estimate, the
   nearest first (at most :data:`MAX_TRIES`);
3. **agreement**: ``r`` is relocalised against each view ``j`` in turn from their flow, measured now, and ``j``'s
   depth (:func:`.fragments.relocalise`) until one agrees: the two must agree on the local scale
   (:data:`MAX_SCALE_CHANGE`) and the current estimate must explain that flow (:data:`MAX_DISAGREEMENT`).  Where no
   view agrees the map has not settled there (a lap's junction, before the final BA reconciles it) and ``r`` stays;
   but where one of the views is a keyframe that stayed so on an earlier revisit and agrees on the scale, the final
   BA has that place's disagreement to work on already: ``r`` goes, where its relocalisation puts it (a lap's
   junction keeps one revisit's stretch, not one per lap);
4. **cull**, once the ``neighbours`` keyframes on either side of ``r`` were examined too and none of them stays (a
   keyframe that stays keeps its odometry neighbours, so what stays is a connected stretch, not a perforated one
   whose single keyframes a later BA would move on their loop edges alone).  A keyframe whose gates failed stays,
   unless the failure is *isolated* (the keyframes just before and after it passed): one bad relocalisation amid
   agreeing ones says nothing about the map there, so it goes where the current estimate has it (scale 1) and keeps
   no stretch (a lap's junction fails on a run of keyframes, which stays).  ``r``'s own pose and its frames are
   moved as the relocalisation moves ``r`` and held rigidly to ``j``
   (:meth:`.frame_poses.FramePoses.rehome`: they follow ``j`` through later loop BAs and the final BA); ``r`` and
   its edges go (every GraphListener hears of it).
5. **islands**: keyframes that stayed but whose every edge led to culled ones are no longer tied to the map (a later
   loop edge or BA would move them freely); they are held where they are to their nearest candidate and culled.

This is ORB-SLAM3's keyframe culling in this map's terms: a keyframe whose view other keyframes hold is not kept.
Only keyframes past the window are culled, so the window BAs, the tracking reference and the loop queries of the
newest keyframes are what they are without culling.  The first two keyframes of a fragment always stay.  Keyframes
are named by stable id; ``k``, ``r``, ``j`` are graph indices.  Poses are T_wc.
"""
from __future__ import annotations

import bisect
import logging
from collections import deque
from typing import Optional

import torch

from ..geometry.lie import se3_inv, se3_mul
from ..types import LoopClosure
from .fragments import apply_sim3, median_error, relocalise, sim3_between
from .loops import UnionFind
from .map_state import MapState
from .observe import EdgeObserver

LOG = logging.getLogger("pvslam")


# frame distance (reference BA px) under which a live source's revisit keyframes are culled: a keyframe is culled
# where the map holds its view from a few pixels away
LIVE_THRESH = 4.0
# a keyframe is a revisit candidate when a loop was closed within this many keyframe ids of it, and its candidate
# views are the older keyframes within this many graph indices of that loop's partner: along a revisit the loop
# policy closes a loop every few keyframes, and the stretch between two loops is the same stretch of the old map
LOOP_REACH = 10
# keyframes that left the window wait until this many keyframes followed the newest loop BA: a loop BA moves the
# revisited stretch, and a keyframe culled before the map settles would hold its frames where they were
SETTLE_KEYFRAMES = 10
# a relocalisation whose scale (the older keyframe's depth against this one's) differs by more than this factor
# says the two disagree on the local map: the keyframe stays, for the final BA to reconcile them
MAX_SCALE_CHANGE = 1.1
# nor when the current estimate explains the measured flow between the two worse than this median reprojection error
# (BA px): the map around them has not settled (it does after a revisit's first loops, at the final BA at the latest)
MAX_DISAGREEMENT = 0.1
# the nearest views a keyframe is relocalised against, in order, until one agrees: where earlier revisits left a
# stretch that had not settled, its keyframes are often the nearest views, and an older one holds the same view
MAX_TRIES = 3


def revisit_thresh(configured: Optional[float], info) -> float:
    """The culling threshold of a run: as configured, or where it is not set, :data:`LIVE_THRESH` for a live source
    (``info.num_frames`` None: it may run for hours over the same places) and 0 (no culling) otherwise."""
    if configured is not None:
        return float(configured)
    if info.num_frames is None:
        LOG.info("live source: keyframes are culled on revisits (graph.keyframes.revisit_thresh=%g)", LIVE_THRESH)
        return LIVE_THRESH
    return 0.0


def _passed(verdict) -> bool:
    return verdict is not None and verdict[3]


def _stays(before: bool, verdict, after: bool) -> bool:
    """Whether a keyframe stays (and keeps its neighbours): it failed a gate, unless the failure is isolated (the
    keyframes just before and after passed: one bad relocalisation amid agreeing ones), when it goes where the
    current estimate has it."""
    return not _passed(verdict) and not (verdict is not None and before and after)


class RevisitCulling:
    """Culls the keyframe leaving the window when an older keyframe near a loop it is near holds its view (see the
    module docstring).  ``thresh``: frame distance (BA px); 0 keeps every keyframe.  ``loops``: the accepted loop
    closures, in order (the list grows as loops are closed)."""

    def __init__(self, thresh: float, state: MapState, observer: EdgeObserver, active_window: int,
                 loops: list[LoopClosure], neighbours: int = 3) -> None:
        self.thresh = float(thresh) * state.px_scale  # in this camera's BA px (an angle of view: adapt.ba_px_scale)
        self.state = state
        self.observer = observer
        self.active_window = int(active_window)
        self.neighbours = int(neighbours)  # a keyframe that stays keeps this many on either side (its odometry edges)
        self.loops = loops
        self.culled = 0  # keyframes culled so far
        self._pending: deque[int] = deque()  # ids of keyframes that left the window, waiting for the map to settle
        # examined keyframes waiting for their later neighbours' verdicts: (id, verdict of _examine)
        self._examined: deque[tuple[int, Optional[tuple]]] = deque()
        self._recent_stays: deque[bool] = deque(maxlen=self.neighbours)  # whether each last decided keyframe stayed
        self._last_passed = False  # whether the last decided keyframe passed every gate
        self._stayed: set[int] = set()  # ids of the revisit keyframes that stayed (a revisit's stretch)

    def candidates(self, r: int) -> list[int]:
        """Graph indices of the older keyframes that may hold keyframe ``r``'s view: those near the partner of a loop
        closed near ``r`` (see :data:`LOOP_REACH`), older than the window before ``r``."""
        g = self.state.graph
        r_id = g.id_of(r)
        lo = bisect.bisect_left(self.loops, r_id - LOOP_REACH, key=lambda c: c.kf_i)
        hi = bisect.bisect_right(self.loops, r_id + LOOP_REACH, key=lambda c: c.kf_i)
        newest_old = r - self.active_window  # exclusive
        out: set[int] = set()
        for c in self.loops[lo:hi]:
            if g.has_id(c.kf_j):
                j = g.index_of(c.kf_j)
                out.update(range(max(0, j - LOOP_REACH), min(newest_old, j + LOOP_REACH + 1)))
        return sorted(out)

    def cull(self, k: int) -> int:
        """After the newest keyframe ``k``'s window BA and loop closure: keyframe ``k - active_window`` leaves the
        window; once the map has settled after the newest loop BA, each keyframe that left it since is examined, and
        each examined keyframe whose neighbours (``neighbours`` on either side) were examined too is culled when it
        and they all may go.  Returns how many were culled."""
        st, g = self.state, self.state.graph
        if self.thresh <= 0 or not self.loops:
            return 0
        if k - self.active_window - 1 > st.fragment_start:
            self._pending.append(g.id_of(k - self.active_window))
        last_ba = next((c.kf_i for c in reversed(self.loops) if c.loop_ba), None)
        if last_ba is not None and g.id_of(k) - last_ba < SETTLE_KEYFRAMES:
            return 0
        while self._pending:
            r_id = self._pending.popleft()
            ok = g.has_id(r_id) and g.index_of(r_id) - 1 > st.fragment_start
            self._examined.append((r_id, self._examine(g.index_of(r_id)) if ok else None))
        culled = 0
        while len(self._examined) > self.neighbours + 1:  # the last neighbour's own next one decides its isolation
            r_id, verdict = self._examined.popleft()
            # r and the keyframes after it: whether each stays needs whether the ones around it passed
            seq = [verdict, *(v for _, v in list(self._examined)[: self.neighbours + 1])]
            passed = [_passed(v) for v in seq]
            before = [self._last_passed, *passed]
            stay, *stays = (_stays(before[i], seq[i], passed[i + 1]) for i in range(self.neighbours + 1))
            if not stay and not any(self._recent_stays) and not any(stays):
                culled += self._cull(r_id, *verdict[:3])
            elif verdict is not None:  # a revisit's keyframe the map keeps (its own gates or a neighbour's)
                self._stayed.add(r_id)
            self._recent_stays.append(stay)
            self._last_passed = passed[0]
        if culled:
            culled += self._cull_islands()
        return culled

    def _cull_islands(self) -> int:
        """Cull the keyframes that culling cut off from the map: once their neighbours are culled, keyframes that
        stayed (:meth:`_examine` said no, or a neighbour of theirs did) may keep edges only among themselves or none,
        and nothing then ties them to the map: a later loop edge or BA would move them, and their frames, freely.  Each such keyframe (not
        linked by edges to the first keyframe or to the window) has its frames held, at their poses now, to the
        nearest of its candidates, else to the keyframe before it.  Returns how many."""
        st, g = self.state, self.state.graph
        if st.fragments.unmerged > 1:
            return 0  # separate map fragments are unlinked by design
        parts = UnionFind()  # the parts of the map that edges link
        for a, b in g.edge_id_pairs():
            parts.union(a, b)
        find = parts.find
        roots = {find(g.id_of(k)) for k in [0, *range(max(0, g.n - self.active_window), g.n)]}
        island = [g.id_of(r) for r in range(st.fragment_start + 2, g.n - self.active_window)
                  if find(g.id_of(r)) not in roots]
        for r_id in island:
            r = g.index_of(r_id)
            cands = [j for j in self.candidates(r) if find(g.id_of(j)) in roots] or [r - 1]
            st.frames.rehome(r_id, g.id_of(cands[int(torch.argmin(g.mutual_distance(r, cands)))]))
            g.remove_keyframe(r)
        self.culled += len(island)
        return len(island)

    def _examine(self, r: int) -> Optional[tuple[int, torch.Tensor, float, bool]]:
        """Whether keyframe ``r`` may go (steps 1-3 of the module docstring): ``(j's id, r's pose relative to j [7],
        scale, passed)``: relocalised when the gates passed, else the current estimate with scale 1 and ``passed``
        False (step 4 decides); None when no candidate holds its view."""
        g = self.state.graph
        cands = self.candidates(r)
        if not cands:
            return None
        d = g.mutual_distance(r, cands)  # [C] BA px
        order = [int(c) for c in torch.argsort(d)[:MAX_TRIES] if float(d[c]) < self.thresh]
        if not order:
            return None
        pose_r = g.poses[r].double().cpu()
        agreed = scaled = None  # (c, j, relocalisation, j's pose) of the view that agrees / of a stayed one
        for c in order:  # the nearest views first; the first one that agrees decides
            j = cands[c]
            obs = self.observer.observe_pair(j, r)  # j's pixels in r, measured now
            reloc = relocalise(g.poses[j], g.disps[j], g.disps[r], g.intrinsics, obs.target[0], obs.weight[0])
            pose_j = g.poses[j].double().cpu()
            scale_ok = reloc is not None and 1 / MAX_SCALE_CHANGE <= reloc.scale <= MAX_SCALE_CHANGE
            if scale_ok and median_error(pose_j, pose_r, g.disps[j], g.intrinsics, obs.target[0],
                                         obs.weight[0]) <= MAX_DISAGREEMENT:
                agreed = (c, j, reloc, pose_j)
                break
            if scale_ok and scaled is None and g.id_of(j) in self._stayed:
                scaled = (c, j, reloc, pose_j)
        # where no view agrees but the place holds a revisit's stretch already, r goes where its flow puts it
        chosen = agreed or scaled
        if chosen is None:  # every gate failed: the current estimate against the nearest view, for step 4 to decide
            j = cands[order[0]]
            return g.id_of(j), se3_mul(se3_inv(g.poses[j].double().cpu()), pose_r), 1.0, False
        c, j, reloc, pose_j = chosen
        if LOG.isEnabledFor(logging.DEBUG):
            LOG.debug("keyframe %d (frame %d) may go for keyframe %d (frame %d): frame distance %.2f, relocalised by "
                      "%.3f (median error %.2f BA px, scale %.3f)", g.id_of(r), int(g.frame_index[r]), g.id_of(j),
                      int(g.frame_index[j]), float(d[c]), float((reloc.pose[:3] - pose_r[:3]).norm()),
                      reloc.error, reloc.scale)
        return g.id_of(j), se3_mul(se3_inv(pose_j), reloc.pose.double().cpu()), float(reloc.scale), True

    def _cull(self, r_id: int, j_id: int, rel_jr: torch.Tensor, scale: float) -> bool:
        """Cull keyframe ``r_id`` in favour of ``j_id`` (step 4): its frames are moved as its relocalisation moves it
        (``rel_jr``: its pose relative to ``j``, scale ``scale``) and held to ``j``."""
        st, g = self.state, self.state.graph
        if not (g.has_id(r_id) and g.has_id(j_id)):
            return False
        r = g.index_of(r_id)
        pose_r = g.poses[r].double().cpu()
        target = se3_mul(g.poses[g.index_of(j_id)].double().cpu(), rel_jr)
        q, t = sim3_between(pose_r, target, scale)
        st.frames.rehome(r_id, j_id, lambda poses: apply_sim3(poses, q, t, scale))
        g.remove_keyframe(r)  # listeners (frame poses, frontend, loop detector, map state) hear of it
        self.culled += 1
        return True
