"""Keyframes on a revisit: culled when they leave the window if the map already holds their view
(``graph.keyframes.revisit_thresh``).

Driving the same place again makes new keyframes where the map has keyframes already, so without culling the map,
the final BA and the memory grow with the time driven, not with the places seen.  Along a revisit nearly every new
keyframe closes a loop (:mod:`.loop_closer`), and the window BAs that follow optimise it against the older
keyframes its loop edges join (:attr:`.map_state.MapState.loop_partners`).  When such a keyframe ``r`` leaves the
optimisation window (it is ``active_window`` keyframes behind the newest) and its frame distance to the nearest of
those partners ``j`` is under ``revisit_thresh`` under the current estimate, ``r`` is culled: its own pose and its
frames are held rigidly to ``j`` at their poses now (:meth:`.frame_poses.FramePoses.rehome`, so they follow ``j``
through later loop BAs and the final BA), then ``r`` and its edges go (every GraphListener hears of it).  This is
ORB-SLAM3's keyframe culling in this map's terms: a keyframe whose view other keyframes hold is not kept.

Only the window's tail is culled, so the window BAs, the tracking reference and the loop queries of the newest
keyframes are what they are without culling; a keyframe that closed no loop, or whose partners see another view,
stays.  The first two keyframes of a fragment always stay.  Keyframes are named by stable id; ``k``, ``r``, ``j``
are graph indices.  Poses are T_wc.
"""
from __future__ import annotations

import bisect
import logging
from collections import deque

import torch

from ..types import LoopClosure
from .fragments import apply_sim3, median_error, relocalise, sim3_between
from .map_state import MapState
from .observe import EdgeObserver

LOG = logging.getLogger("pvslam")


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


class RevisitCulling:
    """Culls the keyframe leaving the window when an older keyframe near a loop it is near holds its view (see the
    module docstring).  ``thresh``: frame distance (BA px); 0 keeps every keyframe.  ``loops``: the accepted loop
    closures, in order (the list grows as loops are closed)."""

    def __init__(self, thresh: float, state: MapState, observer: EdgeObserver, active_window: int,
                 loops: list[LoopClosure]) -> None:
        self.thresh = float(thresh) * state.px_scale  # in this camera's BA px (an angle of view: adapt.ba_px_scale)
        self.state = state
        self.observer = observer
        self.active_window = int(active_window)
        self.loops = loops
        self.culled = 0  # keyframes culled so far
        self._pending: deque[int] = deque()  # ids of keyframes that left the window, waiting for the map to settle
        self._kept: dict[int, None] = {}  # ids of revisit keyframes that stayed (in order), watched for isolation

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
        window; once the map has settled after the newest loop BA, each keyframe that left it since is culled when
        an older keyframe holds its view.  Returns how many were culled."""
        st, g = self.state, self.state.graph
        if self.thresh <= 0 or not self.loops:
            return 0
        if k - self.active_window - 1 > st.fragment_start:
            self._pending.append(g.id_of(k - self.active_window))
        last_ba = next((c.kf_i for c in reversed(self.loops) if c.loop_ba), None)
        if last_ba is not None and g.id_of(k) - last_ba < SETTLE_KEYFRAMES:
            return 0
        culled = 0
        while self._pending:
            r_id = self._pending.popleft()
            if g.has_id(r_id) and g.index_of(r_id) - 1 > st.fragment_start:
                culled += self._cull_one(g.index_of(r_id))
        if culled and self._kept:
            culled += self._cull_isolated()
        return culled

    def _cull_isolated(self) -> int:
        """Cull the revisit keyframes that stayed (:meth:`_cull_one` said no) and have since lost every edge, their
        neighbours being culled: nothing ties such a keyframe to the map any more, so a later loop edge or BA would
        move it (and its frames) freely.  Its frames are held, at their poses now, to the nearest of its candidates
        (or the keyframe before it).  Returns how many."""
        st, g = self.state, self.state.graph
        linked = g.linked_ids()
        done = 0
        for r_id in list(self._kept):
            if not g.has_id(r_id) or r_id in linked:
                if not g.has_id(r_id):
                    del self._kept[r_id]
                continue
            r = g.index_of(r_id)
            cands = self.candidates(r) or [r - 1]
            jj = torch.tensor(cands, dtype=torch.int64)
            src = torch.full_like(jj, r)
            d = g.frame_distance(src, jj).cpu() + g.frame_distance(jj, src).cpu()  # [C]
            st.frames.rehome(r_id, g.id_of(cands[int(torch.argmin(d))]))
            g.remove_keyframe(r)
            del self._kept[r_id]
            done += 1
        self.culled += done
        return done

    def _cull_one(self, r: int) -> bool:
        """Cull keyframe ``r`` when the nearest of its candidates (:meth:`candidates`) is under the threshold."""
        st, g = self.state, self.state.graph
        cands = self.candidates(r)
        if not cands:
            return False
        jj = torch.tensor(cands, dtype=torch.int64)
        src = torch.full_like(jj, r)
        d = 0.5 * (g.frame_distance(src, jj).cpu() + g.frame_distance(jj, src).cpu())  # [C] BA px
        best = int(torch.argmin(d))
        if float(d[best]) >= self.thresh:
            return False
        if not self._relocalise_and_cull(r, cands[best], float(d[best])):
            self._kept[g.id_of(r)] = None
            return False
        return True

    def _relocalise_and_cull(self, r: int, j: int, dist: float) -> bool:
        """Relocalise keyframe ``r`` against ``j`` (which holds its view at frame distance ``dist``) and cull it
        there, unless the two disagree (the gates of the module docstring)."""
        st, g = self.state, self.state.graph
        obs = self.observer.observe_pair(j, r)  # j's pixels in r, measured now
        reloc = relocalise(g.poses[j], g.disps[j], g.disps[r], g.intrinsics, obs.target[0], obs.weight[0])
        if reloc is None or not 1 / MAX_SCALE_CHANGE <= reloc.scale <= MAX_SCALE_CHANGE:
            return False
        r_id, j_id = g.id_of(r), g.id_of(j)
        pose_r = g.poses[r].double().cpu()
        err_now = median_error(g.poses[j], pose_r, g.disps[j], g.intrinsics, obs.target[0], obs.weight[0])
        if err_now > MAX_DISAGREEMENT:
            return False
        LOG.debug("culling keyframe %d (frame %d) for keyframe %d (frame %d): frame distance %.2f, relocalised by "
                  "%.3f (median error %.2f BA px, scale %.3f) now %.3f", r_id, int(g.frame_index[r]), j_id,
                  int(g.frame_index[j]), dist, float((reloc.pose[:3] - pose_r[:3]).norm()), reloc.error,
                  reloc.scale, err_now)
        q, t = sim3_between(pose_r, reloc.pose, reloc.scale)
        st.frames.rehome(r_id, j_id, lambda poses: apply_sim3(poses, q, t, reloc.scale))
        g.remove_keyframe(r)  # listeners (frame poses, frontend, loop detector, map state) hear of it
        self.culled += 1
        return True
