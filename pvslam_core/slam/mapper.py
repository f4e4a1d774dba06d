"""Keyframe mapping: initialisation, graph growth, online BA calls, loop closure, pose filling, failures.

The :class:`Mapper` owns the frame graph, the poses of every frame (:class:`~.frame_poses.FramePoses`) and the loop
policy (:class:`~.loops.LoopPolicy`); it calls the frontend, optimizer and loop detector through their interfaces
only.  Per new keyframe ``k``::

    settle the provisional keyframe, if any (below)
    graph.add_keyframe; frontend.add_keyframe(id); loop_detector.add_keyframe(id); neighbour + proximity edges
    retire edges that left the window (graph -> listeners.on_edges_retired)
    rounds x (obs = frontend.observe(active edges); optimizer.step(obs))          # online BA (.window_ba)
        (every obs also carries frontend.depth_prior of its depth sources, if the frontend has one; after a
         stretch without parallax the window BA also runs from a second start, .motion_start)
    candidates = loop_detector.query(id); closure = policy.decide(candidates)     # one loop owner
    if closure: loop edges (i, j-1), (i, j), (i, j+1); optimizer.loop(...) unless gated
        (a closure into an older map fragment not merged yet first relocalises k and moves the current fragment
         into that map: see .fragments)
    motion-only BA of the frames anchored to the previous keyframe; drop a redundant keyframe

Provisional keyframes (``graph.provisional_keyframes``).  Tracking needs a recent reference (the frontend's motion
filter asks for a keyframe every second frame on the driving loop), the map does not: half of those keyframes used
to be removed as redundant right after paying for their edges and BA.  A new keyframe whose frame distance to the
last one (under its motion-only pose guess) is below ``redundant_thresh`` is therefore added *provisionally*: graph
entry, frontend features, loop description and frame anchor only.  The next keyframe proposal settles it first:
still redundant under the current estimate -> its frames are placed by motion-only BA against it and it is removed
(never optimised); otherwise it gets its edges and the next window BA optimises it with the new keyframe.

Poses are T_wc ``[t, q_xyzw]``; keyframes are named by stable id outside the graph (see :mod:`.graph`).
"""
from __future__ import annotations

import logging
from collections import defaultdict
from time import thread_time
from typing import Optional

import torch

from ..config import PipelineConfig
from ..geometry.lie import se3_interpolate, se3_mul
from ..geometry.projective import edge_transforms, fill_holes, project_points
from ..interfaces import GraphListener
from ..types import Frame, FrameResult, LoopClosure, PanopticSegmentation, SequenceInfo, TrackResult
from .edges import active_edges, loop_edges, neighbour_edges, proximity_edges, retirement_mask
from .frame_poses import FrameEntry, FramePoses
from .graph import EDGE_LOOP, EDGE_ODOMETRY, EDGE_PROXIMITY, FrameGraph
from .bootstrap import Bootstrap
from .keyframing import keyframe_distance, pair_flow_quantile
from .fragments import Fragments, align_fragment, fragment_indices, relocalise, replace_gap_frames
from .loops import LoopPolicy
from .observed import ObservedMasks
from .scale_gaps import ScaleGap, graph_scale_gaps
from .window_ba import WindowBA

LOG = logging.getLogger("pvslam")

IDENTITY = torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)


class Mapper(GraphListener, WindowBA):
    def __init__(self, pcfg: PipelineConfig, info: SequenceInfo, frontend, optimizer, loop_detector, device):
        self.cfg = pcfg.graph
        self.frontend = frontend
        self.optimizer = optimizer
        self.loop_detector = loop_detector
        ds = self.cfg.ba_downsample
        intr = info.intrinsics.scaled(1.0 / ds)
        self.ba_shape = (info.intrinsics.height // ds, info.intrinsics.width // ds)
        self.graph = FrameGraph(self.ba_shape[0], self.ba_shape[1], intr.vector(torch.float32, device), device=device)
        self.frames = FramePoses(self.graph, self.cfg.motion_robust, self.cfg.motion_robust_scale)
        self.policy = LoopPolicy(pcfg.loop_closure, self.graph)
        self.fragments = Fragments()  # map fragments after re-initialisations, merged by loops (see .fragments)
        self.policy.fragments = self.fragments
        self.bootstrap = Bootstrap(self.cfg)  # map initialisation (sliding pairs, H/E model selection)
        for listener in (frontend, loop_detector, self):
            self.graph.add_listener(listener)
        self.initialized = False
        self.fragment_start = 0  # first keyframe of the current map fragment (after a re-initialisation)
        # per keyframe id, at BA resolution, for the point clouds
        self.kf_images: dict[int, torch.Tensor] = {}  # uint8 [3, h, w]
        self.kf_segs: dict[int, Optional[PanopticSegmentation]] = {}
        self.failures = 0
        self.reinits = 0
        self._consecutive_failures = 0
        self._provisional: Optional[int] = None  # id of the provisional keyframe (the newest), if any
        # CPU seconds of this thread per part of the mapping (track, pose_guess, edges, ba, loops, fill, ...)
        self.cpu: dict[str, float] = defaultdict(float)
        self.provisional_removed = 0  # provisional keyframes removed without ever being optimised
        self.second_starts = 0  # window BAs also run from the constant-velocity centre (.motion_start) ...
        self.second_starts_kept = 0  # ... and those whose second start won
        self.observed = ObservedMasks(self.cfg.unobserved_weight, self.cfg.observed_parallax,
                                      self.cfg.guess_min_measured)  # see .observed
        self.scale_gaps: list[ScaleGap] = []  # where the map's scale was not observed (.scale_gaps; at finalize)

    # ----------------------------------------------------------------------------------- GraphListener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        self.kf_images.pop(kf_id, None)
        self.kf_segs.pop(kf_id, None)
        self.observed.forget(kf_id)

    @property
    def loops(self) -> list[LoopClosure]:
        """Accepted loop closures, in order."""
        return self.policy.closures

    # ------------------------------------------------------------------------------------------ helpers --
    def _small(self, frame: Frame, seg: Optional[PanopticSegmentation]):
        h, w = self.ba_shape
        img = torch.nn.functional.interpolate(frame.image[None].float(), size=(h, w), mode="area")[0]
        small = None
        if seg is not None:
            s = self.cfg.ba_downsample
            small = PanopticSegmentation(seg.ids[s // 2 :: s, s // 2 :: s][:h, :w].clone(), list(seg.segments))
        return img.round().clamp(0, 255).to(torch.uint8), small

    def trajectory(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.frames.poses()

    def _reference(self, track: Optional[TrackResult]) -> dict:
        """The newest keyframe as this frame's tracking reference (captured before this frame changes the map)."""
        g = self.graph
        if g.n == 0:
            return {}
        ok = track is not None and not track.failed and track.target is not None
        return dict(ref_id=g.id_of(-1), ref_pose=g.poses[-1].double().cpu().clone(),
                    ref_target=track.target.float() if ok else None, ref_weight=track.weight if ok else None,
                    ref_disp=g.disps[-1].float().clone())

    def _result(self, frame: Frame, entry: FrameEntry, ref: dict, track: Optional[TrackResult] = None,
                kf_id: Optional[int] = None) -> FrameResult:
        """The per-frame result (poses as estimated now)."""
        return FrameResult(
            frame_index=int(frame.index), timestamp=float(frame.timestamp), pose=self.frames.pose_of(entry),
            initialized=self.initialized, keyframe_id=kf_id, intrinsics=self.graph.intrinsics.clone(),
            failed=entry.failed, message=track.message if track is not None else "", **ref)

    # -------------------------------------------------------------------------------------- per frame --
    def process(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> FrameResult:
        """Track one frame (and, when it becomes a keyframe, grow and optimise the map)."""
        if self.graph.n == 0:
            kf_id = self._add_keyframe(frame, seg, pose=IDENTITY.clone(), disp=None)
            return self._result(frame, self.frames.entries[-1], {}, kf_id=kf_id)
        t0 = thread_time()
        track = self.frontend.track(frame, seg)
        self.cpu["track"] += thread_time() - t0
        ref = self._reference(track)
        if track.failed:
            return self._failed(frame, seg, track, ref)
        self._consecutive_failures = 0
        a_id = self.graph.id_of(-1)
        if not track.is_keyframe:
            entry = self.frames.add_frame(frame.index, frame.timestamp, a_id, self.frames.last_rel(),
                                          track.target, track.weight)
            return self._result(frame, entry, ref, track)
        a = self.graph.n - 1
        t0 = thread_time()
        pose = self._keyframe_pose_guess(a, track)  # against the tracking reference (maybe provisional)
        self.cpu["pose_guess"] += thread_time() - t0
        removed = self._settle_provisional(next_ts=frame.timestamp)
        a_id = self.graph.id_of(-1)  # the previous keyframe that stays
        # after a removal the next keyframe is ordinary: chains of provisional keyframes judged on pose guesses
        # alone thinned the map (90 instead of ~120 keyframes on the driving loop, and a higher ATE)
        provisional = not removed and self._predict_redundant(pose, frame.timestamp)
        kf_id = self._add_keyframe(frame, seg, pose, disp=None, provisional=provisional)
        if removed:  # the removed one's frames, held to a_id alone so far, are held between it and this keyframe
            self.frames.bracket(a_id, kf_id)
        entry = self.frames.entries[-1]
        k = self.graph.n - 1
        if provisional:
            self._fill_pending(a_id)
            return self._result(frame, entry, ref, track, kf_id=kf_id)
        if not self.initialized:
            # the window's retirement rule applies before initialisation too: otherwise a fragment that does not
            # initialise keeps every neighbour edge active and a learned frontend its per-edge state (~5.7 MB per
            # keyframe for raft_gru); the initialisation pairs are observed directly, not as edges
            self.graph.retire_edges(retirement_mask(self.graph, k, self.cfg))
            self._try_initialise(k)
            return self._result(frame, entry, ref, track, kf_id=kf_id)
        self._optimize_new(k, self.frontend.rounds)
        self.observed.settle(self.graph.id_of(k))
        t0 = thread_time()
        self._close_loops(k)
        self.cpu["loops"] += thread_time() - t0
        self._fill_pending(a_id)
        result = self._result(frame, entry, ref, track, kf_id=kf_id)  # before the reference may be removed
        self._remove_redundant(k)
        return result

    # ------------------------------------------------------------------------------ provisional keyframes --
    def _redundancy(self, r: int, next_ts: Optional[float] = None) -> float:
        """Symmetric distance (BA px, :func:`.keyframing.keyframe_distance`: mean and 90th percentile of the
        induced flow) of keyframe ``r`` to keyframe ``r - 1`` under the current estimate; infinite when removing
        ``r`` would leave more than ``max_keyframe_gap_s`` between the keyframes around it (the next one: ``r + 1``,
        else the frame at ``next_ts`` about to become a keyframe, else ``r`` itself)."""
        g = self.graph
        after = float(g.timestamps[r + 1]) if r + 1 < g.n else (next_ts if next_ts is not None else
                                                                 float(g.timestamps[r]))
        if after - float(g.timestamps[r - 1]) > self.cfg.max_keyframe_gap_s:
            return float("inf")  # never redundant: see GraphSection.max_keyframe_gap_s
        return 0.5 * (self._kf_distance(g.poses[r - 1], g.poses[r], g.disps[r - 1])
                      + self._kf_distance(g.poses[r], g.poses[r - 1], g.disps[r]))

    def _kf_distance(self, pose_i: torch.Tensor, pose_j: torch.Tensor, disp_i: torch.Tensor) -> float:
        c = self.cfg
        poses = torch.stack([pose_i.double(), pose_j.to(pose_i.device).double()])
        return keyframe_distance(poses, disp_i, self.graph.intrinsics, c.redundant_thresh, c.redundant_max_flow)

    def _predict_redundant(self, pose: torch.Tensor, timestamp: float) -> bool:
        """Whether a new keyframe at ``pose`` would be removed as redundant (``graph.provisional_keyframes``): its
        frame distance from the last keyframe (that keyframe's depth, the new pose guess) is under
        ``redundant_thresh``.  Such a keyframe becomes *provisional*: the tracking reference of the next frames
        (tracking always needs a recent one), with no edges, BA or loop query until the next keyframe settles it
        (the loop detector describes it like every keyframe: a detector hears of each keyframe it is told to forget)."""
        c = self.cfg
        g = self.graph
        if not (c.provisional_keyframes and c.remove_redundant and self.initialized and g.n - 1 > self.fragment_start):
            return False
        if timestamp - float(g.timestamps[-1]) > c.max_keyframe_gap_s:
            return False
        return self._kf_distance(g.poses[-1], pose, g.disps[-1]) < c.redundant_thresh

    def _settle_provisional(self, keep: bool = False, next_ts: Optional[float] = None) -> bool:
        """Decide the provisional keyframe (the newest one) before anything else changes the map: still redundant
        (and not ``keep``) -> its frames are placed (motion-only BA against it) and it goes; else it becomes an
        ordinary keyframe (its edges now; the next window BA optimises it).  Returns whether it was removed."""
        if self._provisional is None:
            return False
        kf_id, self._provisional = self._provisional, None
        g = self.graph
        r = g.index_of(kf_id)
        if not keep and r - 1 > self.fragment_start and self._redundancy(r, next_ts) < self.cfg.redundant_thresh:
            self._fill_pending(kf_id)
            g.remove_keyframe(r)  # frames anchored to it re-anchor to keyframe r - 1
            self.provisional_removed += 1
            return True
        self._connect(r)
        return False

    def _keyframe_pose_guess(self, a: int, track: TrackResult) -> torch.Tensor:
        t_a = self.graph.poses[a].double()
        if not self.initialized or track.target is None:
            return t_a.cpu().clone()
        init = se3_mul(t_a.cpu(), self.frames.last_rel())
        weight = track.weight
        if self.observed.active:
            weight = self.observed.guess_weight(self.graph.id_of(a), weight)
        pose = self.frames.motion_only(init, t_a, self.graph.disps[a], self.graph.intrinsics, track.target, weight)
        return pose if pose is not None else t_a.cpu().clone()

    def _warped_depth(self, a: int, pose_k: torch.Tensor) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
        """Inverse depth of a new keyframe at ``pose_k``: keyframe ``a``'s depth map moved into it (z-buffered
        splat at the BA resolution, holes filled by :func:`~..geometry.projective.fill_holes`). A far better start
        for the BA than a constant.  With it, the pixels that are measured (:mod:`.observed`): those a measured
        pixel of ``a`` lands on."""
        h, w = self.ba_shape
        g = self.graph
        poses = torch.stack([g.poses[a].double(), pose_k.to(g.device).double()])
        R, t = edge_transforms(poses, torch.tensor([0]), torch.tensor([1]))  # camera a -> camera k
        d_a = g.disps[a].float().reshape(1, -1)  # [1, P]
        # homogeneous projection: Z = z_k * d_a, so the inverse depth in camera k is d_a / Z
        out = project_points(R.float(), t.float(), d_a, g.intrinsics, h, w, min_depth=1e-6)
        u, v = torch.round(out["u"][0]), torch.round(out["v"][0])
        ok = out["valid"][0] & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        if int(ok.sum()) < 0.2 * h * w:
            return None
        idx = (v[ok] * w + u[ok]).long()
        disp_k = d_a[0, ok] / out["z"][0, ok]
        disp = torch.zeros(h * w, device=g.device).scatter_reduce(0, idx, disp_k, reduce="amax")
        disp = disp.reshape(h, w)
        known_a = self.observed.masks.get(g.id_of(a))
        src = known_a.to(g.device).reshape(-1)[ok].float() if known_a is not None else torch.ones_like(disp_k)
        known = torch.zeros(h * w, device=g.device).scatter_reduce(0, idx, src, reduce="amax")
        return fill_holes(disp, disp <= 0, self.cfg.fill_row_min_frac), known.reshape(h, w) > 0

    def _add_keyframe(self, frame: Frame, seg, pose: torch.Tensor, disp: Optional[torch.Tensor],
                      provisional: bool = False) -> int:
        """Add a keyframe (graph, frontend, loop detector, frame poses, edges); returns its stable id.  A
        provisional one gets no edges yet (see :meth:`_settle_provisional`)."""
        h, w = self.ba_shape
        g = self.graph
        k_new = g.n
        known = None
        if disp is None and self.initialized and k_new > self.fragment_start:
            warped = self._warped_depth(k_new - 1, pose)
            if warped is not None:
                disp, known = warped
        if disp is None:
            guess = self.frontend.initial_depth(g, g.next_id) if k_new > 0 else None
            if guess is not None:
                disp = guess
            elif k_new > 0:
                disp = torch.full((h, w), float(g.disps[k_new - 1].median()))
            else:
                disp = torch.ones(h, w)
        k = g.add_keyframe(frame.index, frame.timestamp, pose.to(g.device), disp.to(g.device))
        kf_id = g.id_of(k)
        self.observed.set(kf_id, known if known is not None else torch.zeros(h, w, dtype=torch.bool, device=g.device))
        self.frontend.add_keyframe(kf_id, frame, seg)
        self.frames.add_keyframe(frame.index, frame.timestamp, kf_id)
        self.kf_images[kf_id], self.kf_segs[kf_id] = self._small(frame, seg)
        if self.loop_detector is not None:  # every keyframe is described; candidates are asked after the BA
            self.loop_detector.add_keyframe(kf_id, frame)
        if provisional:
            self._provisional = kf_id
        else:
            self._connect(k)
        return kf_id

    def _connect(self, k: int) -> None:
        """Neighbour and proximity edges of keyframe ``k`` (the newest)."""
        g = self.graph
        if k > self.fragment_start:
            ii, jj = neighbour_edges(k, self.cfg, first=self.fragment_start)
            g.add_edges(ii, jj, EDGE_ODOMETRY)
            if self.initialized:
                ii, jj = self._reliable(*proximity_edges(g, k, self.cfg, first=self.fragment_start))
                if ii.numel():
                    g.add_edges(ii, jj, EDGE_PROXIMITY)

    def _reliable(self, ii: torch.Tensor, jj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The proximity edges ``(ii, jj)`` whose pair's 90th-percentile parallax (translation-only induced flow,
        both directions, current estimate: :func:`.keyframing.pair_flow_quantile`) is at most
        ``graph.proximity_max_flow`` (0: all).  Why: see :mod:`.keyframing`; a proximity edge is a long baseline
        chosen on the *mean* flow, and the near field of a forward-moving camera moves farther than the frontend's
        flow can follow."""
        limit = self.cfg.proximity_max_flow
        # a young map keeps them all: its depths come from the two-view initialisation and a few window BAs, so
        # the parallax read from them is a guess, and the long edges are what holds its scale (with the filter from
        # the first keyframe, driving_block seed 0 lost them all over its first 30 frames: 0.17 -> 1.03 % ATE)
        if limit <= 0 or ii.numel() == 0 or int(ii.max()) - self.fragment_start < self.cfg.active_window:
            return ii, jj
        g = self.graph
        keep = {}
        for a, b in zip(ii.tolist(), jj.tolist()):
            pair = (min(a, b), max(a, b))
            if pair not in keep:  # both directions share the decision
                poses = torch.stack([g.poses[pair[0]].double(), g.poses[pair[1]].double()])
                keep[pair] = pair_flow_quantile(poses, g.disps[pair[0]], g.disps[pair[1]], g.intrinsics) <= limit
        mask = torch.tensor([keep[(min(a, b), max(a, b))] for a, b in zip(ii.tolist(), jj.tolist())], dtype=torch.bool)
        return ii[mask], jj[mask]

    # --------------------------------------------------------------------------------- initialisation --
    def _try_initialise(self, k: int) -> None:
        """Two-view initialisation of the current fragment on a sliding window of keyframe pairs (see
        :mod:`.bootstrap`), then a window BA and the poses of the frames so far."""
        first = self.fragment_start
        if not self.bootstrap.try_initialise(self, k):
            return
        self.initialized = True
        everywhere = torch.ones(self.ba_shape, dtype=torch.bool, device=self.graph.device)
        for a in range(first, k + 1):  # the triangulation measured them (.observed)
            self.observed.set(self.graph.id_of(a), everywhere)
        self._optimize_window(k, max(3, 2 * self.frontend.rounds))
        for a in range(first, k):
            self._fill_pending(self.graph.id_of(a))

    # ------------------------------------------------------------------------------------------ loops --
    def _close_loops(self, k: int) -> None:
        if self.loop_detector is None:
            return
        g = self.graph
        kf_id = g.id_of(k)
        cands = self.loop_detector.query(kf_id, skip=lambda j_id: self.policy.suppressed(kf_id, j_id))
        decision = self.policy.decide(cands)
        if decision is None:
            return
        c = decision.closure
        j = g.index_of(c.kf_j)
        if decision.merge and not self._merge_fragments(k, j):
            return
        ii, jj = loop_edges(k, j, g.n, self.cfg.bidirectional)
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
        a_ii, a_jj = active_edges(g, k, self.cfg.active_window)
        pair = torch.unique(torch.stack([torch.cat([a_ii.cpu(), ii]), torch.cat([a_jj.cpu(), jj])]), dim=1)
        report = self.optimizer.loop(g, self._observe(pair[0], pair[1]), [c])
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
        g = self.graph
        jt, kt = torch.tensor([j]), torch.tensor([k])
        obs = self._observe(jt, kt)
        self._release_pairs(jt, kt)  # not an edge yet: the loop edges that follow are observed afresh
        reloc = relocalise(g.poses[j], g.disps[j], g.disps[k], g.intrinsics, obs.target[0], obs.weight[0])
        if reloc is None:
            LOG.info("fragment merge %d <-> %d: relocalisation failed", k, j)
            return False
        idx = fragment_indices(g, self.fragments, g.id_of(k))
        align_fragment(self, idx, k, reloc)
        self.fragments.merge(g.id_of(k), g.id_of(j))
        first = int(idx[0])
        if first > 0 and self.fragments.same(g.id_of(first - 1), g.id_of(k)):
            replace_gap_frames(self, first)  # the frames lost between the two, now both in one frame
        LOG.warning("map fragments merged: keyframe %d relocalised against keyframe %d (median error %.2f BA px, "
                    "%d matches, scale %.3g); %d keyframes moved, %d separate map(s) left", k, j, reloc.error,
                    reloc.matched, reloc.scale, len(idx), self.fragments.unmerged)
        return True

    # ------------------------------------------------------------------------------------ pose filling --
    def _fill_pending(self, a_id: int) -> None:
        """Motion-only BA for the non-keyframes anchored at keyframe ``a_id`` (its depth is refined by now)."""
        pend = [e for e in self.frames.pending(a_id) if e.target is not None]
        if not pend:
            return
        t0 = thread_time()
        g = self.graph
        a = g.index_of(a_id)
        t_a = g.poses[a].double().cpu()
        nxt = g.poses[a + 1].double().cpu() if a + 1 < g.n else t_a
        ts_a = float(g.timestamps[a])
        ts_b = float(g.timestamps[a + 1]) if a + 1 < g.n else ts_a
        alpha = torch.tensor([0.0 if ts_b <= ts_a else (e.timestamp - ts_a) / (ts_b - ts_a) for e in pend],
                             dtype=torch.float64)
        inits = se3_interpolate(t_a.expand(len(pend), 7), nxt.expand(len(pend), 7), alpha)
        self.frames.refine_many_later(pend, inits)  # one batched motion-only BA for all of them, on a worker
        self.cpu["fill"] += thread_time() - t0

    # -------------------------------------------------------------------------------------- pruning --
    def _remove_redundant(self, k: int) -> None:
        g = self.graph
        r = k - 1
        if not self.cfg.remove_redundant or r - 1 <= self.fragment_start:
            return
        touches_loop = ((g.edge_kind == EDGE_LOOP) & ((g.ii == r) | (g.jj == r))).any()
        if bool(touches_loop):
            return
        d = self._redundancy(r)
        if d >= self.cfg.redundant_thresh:
            return
        self._fill_pending(g.id_of(r))
        g.remove_keyframe(r)  # listeners (frame poses, frontend, loop detector, this mapper) hear of it
        LOG.debug("removed redundant keyframe %d (frame distance %.2f)", r, d)

    # ------------------------------------------------------------------------------------- failures --
    def _failed(self, frame: Frame, seg, track: TrackResult, ref: dict) -> FrameResult:
        self.failures += 1
        self._consecutive_failures += 1
        LOG.warning("frame %d (%s): tracking failed: %s", frame.index, frame.name or frame.timestamp, track.message)
        blank = float(frame.image.float().std()) < 2.0  # a dark/blank stretch: nothing to re-initialise on
        if self._consecutive_failures < self.cfg.reinit_after or blank:
            entry = self.frames.add_frame(frame.index, frame.timestamp, self.graph.id_of(-1), self.frames.last_rel(),
                                          failed=True)
            return self._result(frame, entry, ref, track)
        # Re-initialise: start a new map fragment at this frame, placed at the last known pose.
        self._settle_provisional(keep=True)  # the newest reference ends the old fragment as an ordinary keyframe
        pose = self.trajectory()[1][-1]
        self.reinits += 1
        self.fragment_start = self.graph.n
        self.initialized = False
        self._consecutive_failures = 0
        LOG.warning("re-initialising the map at frame %d (new fragment from keyframe %d)", frame.index,
                    self.fragment_start)
        kf_id = self._add_keyframe(frame, seg, pose.double(), disp=None)
        self.fragments.start(kf_id)
        return self._result(frame, self.frames.entries[-1], ref, track, kf_id=kf_id)

    # -------------------------------------------------------------------------------------- the end --
    def finalize(self) -> None:
        self._settle_provisional(keep=True)  # it holds the last frames' reference; the final BA optimises it
        if self.fragments.unmerged > 1:
            LOG.warning("%d map fragments were never joined by a loop (%d merged): the trajectory is in %d unrelated "
                        "frames", len(self.fragments.starts), self.fragments.merges, self.fragments.unmerged)
        if self.graph.n and self.initialized:
            self._fill_pending(self.graph.id_of(-1))
        if self.graph.n > 1 and self.initialized:
            report = self.optimizer.finalize(self.graph, self.observe_any)
            if report.rejected:
                LOG.warning("final optimisation rejected: %s", report.message)
            self.frames.refill()
            self._report_scale_gaps()
        elif not self.initialized:
            LOG.warning("the map was never initialised (too little parallax); poses are identity/extrapolated")
        self.frames.close()  # the queued frame refinements are done; their worker thread stops

    def _report_scale_gaps(self) -> None:
        """Where the map's scale was not observed (:mod:`.scale_gaps`; warns of the gaps wider than the view)."""
        if self.observed.active:
            self.scale_gaps = graph_scale_gaps(self.graph, self.observed.settled_fraction, self.fragments.starts)
