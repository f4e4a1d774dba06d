"""The mapper: the per-frame driver of Algorithm 1 over the SLAM parts.

The :class:`Mapper` calls the frontend, optimizer and loop detector through their interfaces only, and delegates
every decision to a part that owns its state: the keyframe policy (:mod:`.keyframes`), the edge policy
(:mod:`.edges`), the window BA (:mod:`.window_ba`), the loop closer (:mod:`.loop_closer`) and the bootstrap
(:mod:`.bootstrap`), all over one shared :class:`~.map_state.MapState`.  Per input frame::

    track = frontend.track(frame)                       # the motion filter proposes keyframes
    not a keyframe: frontend.prefetch(next frame); anchor the frame to the newest keyframe; done
    pose = motion-only guess; keyframes.propose(pose)   # settles the provisional keyframe; provisional or ordinary?
    graph.add_keyframe; frontend.add_keyframe(id); loop_detector.add_keyframe(id); its edges (unless provisional)
    frontend.prefetch(next frame)                       # when at hand: its tracking may begin beside the BA
    provisional: place the frames of the keyframe before; done
    not initialised: bootstrap.try_initialise; done
    retire edges that left the window (graph -> listeners.on_edges_retired)
    rounds x (obs = frontend.observe(active edges); optimizer.step(obs))          # window BA
        (every obs also carries the frontend's depth and distance priors; after a stretch without parallax the
         window BA also runs from a second start, .motion_start)
    loop_closer.close: candidates = loop_detector.query(id); policy.decide; loop edges (i, j-1), (i, j), (i, j+1);
        optimizer.loop(...) unless gated (a loop into an older map fragment first merges the two, .fragments)
    motion-only BA of the frames anchored to the previous keyframe; keyframes.remove_redundant

A tracking failure repeated ``graph.reinit_after`` times starts a new map fragment at the last known pose.  Poses
are T_wc ``[t, q_xyzw]``; keyframes are named by stable id outside the graph (see :mod:`.graph`).
"""
from __future__ import annotations

import logging
from time import thread_time
from typing import Optional

import torch

from ..config import PipelineConfig
from ..types import Frame, FrameResult, LoopClosure, PanopticSegmentation, SequenceInfo, TrackResult
from . import new_keyframe
from .bootstrap import Bootstrap
from .edges import connect_keyframe, retirement_mask
from .frame_poses import FrameEntry
from .graph import FrameGraph
from .keyframes import KeyframePolicy
from .revisits import RevisitCulling, revisit_thresh
from .loop_closer import LoopCloser
from .map_state import KeyframeSnapshot, MapSnapshot, MapState
from .observe import EdgeObserver
from .scale_gaps import ScaleGap, graph_scale_gaps
from .window_ba import WindowBA

LOG = logging.getLogger("pvslam")

IDENTITY = torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)
BLANK_STD = 2.0  # grey-level standard deviation under which a failed frame is blank (nothing to re-initialise on)


class Mapper:
    """Algorithm 1's per-frame driver (see the module docstring)."""

    def __init__(self, pcfg: PipelineConfig, info: SequenceInfo, frontend, optimizer, loop_detector, device,
                 spill_dir=None):
        self.cfg = pcfg.graph
        self.frontend = frontend
        self.loop_detector = loop_detector
        # spill_dir: where the map keeps what only the end of the run reads (.spill; None: in memory)
        self.state = st = MapState(info, self.cfg.ba_downsample, device, spill_dir)
        for listener in (frontend, loop_detector, st):
            st.graph.add_listener(listener)
        observer = EdgeObserver(st.graph, frontend)
        self.window_ba = WindowBA(st, observer, optimizer, self.cfg.edges)
        self.bootstrap = Bootstrap(self.cfg.init, st, observer, frontend)
        self.keyframe_policy = KeyframePolicy(self.cfg.keyframes, st, self._connect)
        self.loop_closer = LoopCloser(pcfg.loop_closure, st, observer, optimizer, loop_detector,
                                      self.cfg.edges.active_window)
        self.revisits = RevisitCulling(revisit_thresh(self.cfg.keyframes.revisit_thresh, info), st, observer,
                                       self.cfg.edges.active_window, self.loop_closer.loops, self.cfg.edges.neighbours)
        self.optimizer = optimizer
        self.observer = observer
        self.failures = 0
        self.reinits = 0
        self._consecutive_failures = 0
        self.scale_gaps: list[ScaleGap] = []  # where the map's scale was not observed (.scale_gaps; at finalize)

    # ------------------------------------------------------------------------------ read-only views --
    @property
    def graph(self) -> FrameGraph:
        return self.state.graph

    @property
    def initialized(self) -> bool:
        """Whether the current map fragment is initialised."""
        return self.state.initialized

    @property
    def cpu(self) -> dict[str, float]:
        """CPU seconds of the mapping thread per part (track, pose_guess, keyframe, edges, ba, loops, fill)."""
        return self.state.cpu

    @property
    def fragments(self):
        return self.state.fragments

    @property
    def loops(self) -> list[LoopClosure]:
        """Accepted loop closures, in order."""
        return self.loop_closer.loops

    def trajectory(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(timestamps float64 [T], poses float64 [T, 7])`` of every frame so far, as estimated now."""
        return self.state.frames.poses()

    def keyframes_snapshot(self) -> KeyframeSnapshot:
        return self.state.keyframes()

    def snapshot(self, trajectory: bool = True) -> MapSnapshot:
        """What the outputs write of the map now; ``trajectory=False`` leaves out every frame's pose (which waits for
        the queued frame refinements)."""
        ts, poses = self.trajectory() if trajectory else (None, None)
        return MapSnapshot(self.state.keyframes(), list(self.loops), len(self.state.frames), ts, poses)

    def stats(self) -> dict:
        """The map's counts for ``metrics.json`` (``tracking``)."""
        g, fr = self.state.graph, self.state.fragments
        return {"active_edges": g.num_edges, "retired_edges": g.num_retired, "keyframes_added": g.next_id,
                "keyframes_removed": g.next_id - g.n,
                "keyframes_provisional_removed": self.keyframe_policy.provisional_removed,
                "keyframes_culled_on_revisits": self.revisits.culled,
                "second_starts": self.window_ba.second_starts, "second_starts_kept": self.window_ba.second_starts_kept,
                # stretches of keyframes whose depth was never measured (pvslam_core/slam/scale_gaps.py)
                "scale_gaps": [gap.as_dict() for gap in self.scale_gaps],
                # map fragments (a re-initialisation starts one; a verified loop merges it back): "maps" is how many
                # separate frames the trajectory ends in (1 = one trajectory in one frame)
                "fragments": len(fr.starts), "fragment_merges": fr.merges, "maps": fr.unmerged}

    # -------------------------------------------------------------------------------------- per frame --
    def process(self, frame: Frame, seg: Optional[PanopticSegmentation],
                next_frame: Optional[Frame] = None) -> FrameResult:
        """Track one frame (and, when it becomes a keyframe, grow and optimise the map).  ``next_frame``: the next
        input frame when it is at hand (:meth:`.Frontend.prefetch`; the results do not depend on it)."""
        st, g = self.state, self.state.graph
        if g.n == 0:
            kf_id = self._add_keyframe(frame, seg, IDENTITY.clone())
            self._prefetch(next_frame)
            return self._result(frame, st.frames.entries[-1], {}, kf_id=kf_id)
        t0 = thread_time()
        track = self.frontend.track(frame, seg)
        st.cpu["track"] += thread_time() - t0
        ref = self._reference(track)
        if track.failed:
            return self._failed(frame, seg, track, ref)
        self._consecutive_failures = 0
        if not track.is_keyframe:
            self._prefetch(next_frame)
            entry = st.frames.add_frame(frame.index, frame.timestamp, g.id_of(-1), st.frames.last_rel(),
                                        track.target, track.weight)
            return self._result(frame, entry, ref, track)
        t0 = thread_time()
        pose = new_keyframe.pose_guess(st, g.n - 1, track)  # against the tracking reference (maybe provisional)
        st.cpu["pose_guess"] += thread_time() - t0
        provisional = self.keyframe_policy.propose(pose, frame.timestamp)
        a_id = g.id_of(-1)  # the previous keyframe that stays
        kf_id = self._add_keyframe(frame, seg, pose, provisional)
        self._prefetch(next_frame)  # beside this keyframe's edges and BA
        entry = st.frames.entries[-1]
        k = g.n - 1
        if provisional:
            st.place_frames(a_id)
            return self._result(frame, entry, ref, track, kf_id=kf_id)
        if not st.initialized:
            # the window's retirement rule applies before initialisation too: otherwise a fragment that does not
            # initialise keeps every neighbour edge active and a learned frontend its per-edge state; the
            # initialisation pairs are observed directly, not as edges
            g.retire_edges(retirement_mask(g, k, self.cfg.edges))
            self._try_initialise(k)
            return self._result(frame, entry, ref, track, kf_id=kf_id)
        self.window_ba.optimize_new(k, self.frontend.rounds)
        st.observed.settle(g.id_of(k))
        t0 = thread_time()
        self.loop_closer.close(k)
        st.cpu["loops"] += thread_time() - t0
        st.place_frames(a_id)
        result = self._result(frame, entry, ref, track, kf_id=kf_id)  # before the reference may be removed
        self.keyframe_policy.remove_redundant(k)
        self.revisits.cull(g.n - 1)
        return result

    def _prefetch(self, next_frame: Optional[Frame]) -> None:
        if next_frame is not None:
            self.frontend.prefetch(next_frame)

    def _add_keyframe(self, frame: Frame, seg: Optional[PanopticSegmentation], pose: torch.Tensor,
                      provisional: bool = False) -> int:
        """Add a keyframe (graph, frontend, frame poses, thumbnails, loop detector; the keyframe policy connects it
        or holds it provisional); returns its stable id."""
        t0 = thread_time()
        try:
            return self._add_keyframe_now(frame, seg, pose, provisional)
        finally:
            self.state.cpu["keyframe"] += thread_time() - t0

    def _add_keyframe_now(self, frame: Frame, seg: Optional[PanopticSegmentation], pose: torch.Tensor,
                          provisional: bool) -> int:
        st, g = self.state, self.state.graph
        disp, known = new_keyframe.initial_depth(st, self.frontend, pose)
        k = g.add_keyframe(frame.index, frame.timestamp, pose.to(g.device), disp.to(g.device))
        kf_id = g.id_of(k)
        st.observed.set(kf_id, known if known is not None else torch.zeros(st.ba_shape, dtype=torch.bool,
                                                                             device=g.device))
        self.frontend.add_keyframe(kf_id, frame, seg)
        st.frames.add_keyframe(frame.index, frame.timestamp, kf_id)
        st.add_thumbnail(kf_id, frame, seg)
        if self.loop_detector is not None:  # every keyframe is described; candidates are asked after the BA
            self.loop_detector.add_keyframe(kf_id, frame)
        self.keyframe_policy.added(kf_id, provisional)
        return kf_id

    def _connect(self, k: int) -> None:
        """Keyframe ``k``'s edges (the edge policy, :func:`.edges.connect_keyframe`)."""
        st = self.state
        connect_keyframe(st.graph, k, self.cfg.edges, st.fragment_start, st.initialized, st.px_scale)

    def _try_initialise(self, k: int) -> None:
        """Two-view initialisation of the current fragment (:mod:`.bootstrap`), then a window BA and the poses of
        the frames so far."""
        st = self.state
        first = st.fragment_start
        if not self.bootstrap.try_initialise(k):
            return
        st.initialized = True
        everywhere = torch.ones(st.ba_shape, dtype=torch.bool, device=st.graph.device)
        for a in range(first, k + 1):  # the triangulation measured them (.observed)
            st.observed.set(st.graph.id_of(a), everywhere)
        self.window_ba.optimize(k, max(3, 2 * self.frontend.rounds))
        for a in range(first, k):
            st.place_frames(st.graph.id_of(a))

    def _reference(self, track: Optional[TrackResult]) -> dict:
        """The newest keyframe as this frame's tracking reference (captured before this frame changes the map)."""
        g = self.state.graph
        if g.n == 0:
            return {}
        ok = track is not None and not track.failed and track.target is not None
        return dict(ref_id=g.id_of(-1), ref_pose=g.poses[-1].double().cpu().clone(),
                    ref_target=track.target.float() if ok else None, ref_weight=track.weight if ok else None,
                    ref_disp=g.disps[-1].float().clone())

    def _result(self, frame: Frame, entry: FrameEntry, ref: dict, track: Optional[TrackResult] = None,
                kf_id: Optional[int] = None) -> FrameResult:
        """The per-frame result (poses as estimated now)."""
        st = self.state
        return FrameResult(
            frame_index=int(frame.index), timestamp=float(frame.timestamp), pose=st.frames.pose_of(entry),
            initialized=st.initialized, keyframe_id=kf_id, intrinsics=st.graph.intrinsics.clone(),
            failed=entry.failed, message=track.message if track is not None else "", **ref)

    # ------------------------------------------------------------------------------------- failures --
    def _failed(self, frame: Frame, seg, track: TrackResult, ref: dict) -> FrameResult:
        st = self.state
        self.failures += 1
        self._consecutive_failures += 1
        LOG.warning("frame %d (%s): tracking failed: %s", frame.index, frame.name or frame.timestamp, track.message)
        blank = float(frame.image.float().std()) < BLANK_STD  # a dark/blank stretch: nothing to re-initialise on
        if self._consecutive_failures < self.cfg.reinit_after or blank:
            entry = st.frames.add_frame(frame.index, frame.timestamp, st.graph.id_of(-1), st.frames.last_rel(),
                                        failed=True)
            return self._result(frame, entry, ref, track)
        # Re-initialise: start a new map fragment at this frame, placed at the last known pose.
        self.keyframe_policy.settle(keep=True)  # the newest reference ends the old fragment as an ordinary keyframe
        pose = self.trajectory()[1][-1]
        self.reinits += 1
        st.fragment_start = st.graph.n
        st.initialized = False
        self._consecutive_failures = 0
        LOG.warning("re-initialising the map at frame %d (new fragment from keyframe %d)", frame.index,
                    st.fragment_start)
        kf_id = self._add_keyframe(frame, seg, pose.double())
        st.fragments.start(kf_id)
        return self._result(frame, st.frames.entries[-1], ref, track, kf_id=kf_id)

    # -------------------------------------------------------------------------------------- the end --
    def finalize(self) -> None:
        """The final global BA over every edge (active and retired) and the last frames' poses."""
        st, g = self.state, self.state.graph
        self.keyframe_policy.settle(keep=True)  # it holds the last frames' reference; the final BA optimises it
        if st.fragments.unmerged > 1:
            LOG.warning("%d map fragments were never joined by a loop (%d merged): the trajectory is in %d unrelated "
                        "frames", len(st.fragments.starts), st.fragments.merges, st.fragments.unmerged)
        if g.n and st.initialized:
            st.place_frames(g.id_of(-1))
        if g.n > 1 and st.initialized:
            report = self.optimizer.finalize(g, self.observer.observe_any)
            if report.rejected:
                LOG.warning("final optimisation rejected: %s", report.message)
            st.frames.refill()
            if st.observed.active:  # where the map's scale was not observed (.scale_gaps)
                self.scale_gaps = graph_scale_gaps(g, st.observed.settled_fraction, st.fragments.starts)
        elif not st.initialized:
            LOG.warning("the map was never initialised (too little parallax); poses are identity/extrapolated")
        st.frames.close()  # the queued frame refinements are done; their worker thread stops
