"""Keyframe mapping: initialisation, graph growth, online BA calls, loop closure, pose filling, failures.

The :class:`Mapper` owns the frame graph, the poses of every frame (:class:`~.frame_poses.FramePoses`) and the loop
policy (:class:`~.loops.LoopPolicy`); it calls the frontend, optimizer and loop detector through their interfaces
only.  Per new keyframe ``k``::

    graph.add_keyframe; frontend.add_keyframe(id); loop_detector.add_keyframe(id); neighbour + proximity edges
    retire edges that left the window (graph -> listeners.on_edges_retired)
    rounds x (obs = frontend.observe(active edges); optimizer.step(obs))          # online BA
    candidates = loop_detector.query(id); closure = policy.decide(candidates)     # one loop owner
    if closure: loop edges (i, j-1), (i, j), (i, j+1); optimizer.loop(...) unless gated
    motion-only BA of the frames anchored to the previous keyframe; drop a redundant keyframe

Poses are T_wc ``[t, q_xyzw]``; keyframes are named by stable id outside the graph (see :mod:`.graph`).
"""
from __future__ import annotations

import logging
from typing import Optional

import torch

from ..config import PipelineConfig
from ..geometry.lie import se3_interpolate, se3_mul
from ..geometry.projective import edge_transforms, project_points
from ..interfaces import GraphListener
from ..types import EdgeObservations, Frame, FrameResult, LoopClosure, PanopticSegmentation, SequenceInfo, TrackResult
from .edges import active_edges, loop_edges, neighbour_edges, proximity_edges, retirement_mask
from .frame_poses import FrameEntry, FramePoses
from .graph import EDGE_LOOP, EDGE_ODOMETRY, EDGE_PROXIMITY, FrameGraph, _grid
from .initializer import two_view_init
from .loops import LoopPolicy

LOG = logging.getLogger("pvslam")

IDENTITY = torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)


class Mapper(GraphListener):
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

    # ----------------------------------------------------------------------------------- GraphListener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        self.kf_images.pop(kf_id, None)
        self.kf_segs.pop(kf_id, None)

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

    def _observe(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        dev = self.graph.device
        obs = self.frontend.observe(self.graph, ii.to(dev), jj.to(dev))
        self.graph.record_observations(obs)
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
        for _ in range(rounds):
            ii, jj = active_edges(self.graph, k, self.cfg.active_window)
            if ii.numel() == 0:
                return
            report = self.optimizer.step(self.graph, self._observe(ii, jj))
            self.graph.age_edges(ii, jj)
            if report.rejected:
                LOG.warning("keyframe %d: optimizer rejected an update: %s", k, report.message)

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
        track = self.frontend.track(frame, seg)
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
        pose = self._keyframe_pose_guess(a, track)
        kf_id = self._add_keyframe(frame, seg, pose, disp=None)
        entry = self.frames.entries[-1]
        k = self.graph.n - 1
        if not self.initialized:
            self._try_initialise(k)
            return self._result(frame, entry, ref, track, kf_id=kf_id)
        self._optimize_window(k, self.frontend.rounds)
        self._close_loops(k)
        self._fill_pending(a_id)
        result = self._result(frame, entry, ref, track, kf_id=kf_id)  # before the reference may be removed
        self._remove_redundant(k)
        return result

    def _keyframe_pose_guess(self, a: int, track: TrackResult) -> torch.Tensor:
        t_a = self.graph.poses[a].double()
        if not self.initialized or track.target is None:
            return t_a.cpu().clone()
        init = se3_mul(t_a.cpu(), self.frames.last_rel())
        pose = self.frames.motion_only(init, t_a, self.graph.disps[a], self.graph.intrinsics, track.target,
                                       track.weight)
        return pose if pose is not None else t_a.cpu().clone()

    def _warped_depth(self, a: int, pose_k: torch.Tensor) -> Optional[torch.Tensor]:
        """Inverse depth of a new keyframe at ``pose_k``: keyframe ``a``'s depth map moved into it (z-buffered
        splat at the BA resolution, holes filled with the median). A far better start for the BA than a constant."""
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
        hole = disp <= 0
        disp[hole] = disp[~hole].median()
        return disp.reshape(h, w)

    def _add_keyframe(self, frame: Frame, seg, pose: torch.Tensor, disp: Optional[torch.Tensor]) -> int:
        """Add a keyframe (graph, frontend, loop detector, frame poses, edges); returns its stable id."""
        h, w = self.ba_shape
        g = self.graph
        k_new = g.n
        if disp is None and self.initialized and k_new > self.fragment_start:
            disp = self._warped_depth(k_new - 1, pose)
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
        self.frontend.add_keyframe(kf_id, frame, seg)
        self.frames.add_keyframe(frame.index, frame.timestamp, kf_id)
        self.kf_images[kf_id], self.kf_segs[kf_id] = self._small(frame, seg)
        if k > self.fragment_start:
            ii, jj = neighbour_edges(k, self.cfg, first=self.fragment_start)
            g.add_edges(ii, jj, EDGE_ODOMETRY)
            if self.initialized:
                ii, jj = proximity_edges(g, k, self.cfg, first=self.fragment_start)
                if ii.numel():
                    g.add_edges(ii, jj, EDGE_PROXIMITY)
        if self.loop_detector is not None:  # every keyframe is described; candidates are asked after the BA
            self.loop_detector.add_keyframe(kf_id, frame)
        return kf_id

    # --------------------------------------------------------------------------------- initialisation --
    def _try_initialise(self, k: int) -> None:
        first = self.fragment_start
        if k - first + 1 < self.cfg.warmup:
            return
        # The farthest pair first (most parallax); when its flow fails (fast motion: every frame a keyframe on a
        # highway) nearer partners, down to `init_tries` pairs per keyframe.
        init, m = None, k
        for m in range(k, max(first, k - self.cfg.init_tries), -1):
            pair = torch.tensor([first]), torch.tensor([m])
            obs = self._observe(*pair)
            self._release_pairs(*pair)  # a pair that is not a graph edge is not observed again
            init = two_view_init(obs.target[0], obs.weight[0], self.graph.intrinsics,
                                 min_parallax_deg=self.cfg.init_min_parallax_deg)
            if init is not None:
                break
        if init is None:
            LOG.debug("initialisation deferred at keyframe %d (too little parallax or too few inliers)", k)
            return
        t0 = self.graph.poses[first].double().cpu()
        pose_m = se3_mul(t0, init.pose_wc)
        ts = self.graph.timestamps.double().cpu()
        span = float(ts[m] - ts[first]) or 1.0
        idx = torch.arange(first + 1, k + 1)
        alpha = ((ts[idx] - ts[first]) / span).clamp(min=0)  # > 1 (constant-velocity extrapolation) after m
        poses = se3_interpolate(t0.expand(len(idx), 7), pose_m.expand(len(idx), 7), alpha)
        self.graph.set_poses(idx, poses)
        disp0 = init.disp0.to(self.graph.disps.device)
        self.graph.set_disps(torch.tensor([first]), disp0[None])
        med = float(disp0.median())
        self.graph.set_disps(idx, torch.full((len(idx),) + tuple(self.ba_shape), med, device=self.graph.disps.device))
        self.initialized = True
        LOG.info("map initialised with keyframes %d..%d (pair %d-%d: %d inliers, parallax %.2f deg)",
                 first, k, first, m, init.inliers, init.parallax_deg)
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

    # ------------------------------------------------------------------------------------ pose filling --
    def _fill_pending(self, a_id: int) -> None:
        """Motion-only BA for the non-keyframes anchored at keyframe ``a_id`` (its depth is refined by now)."""
        pend = [e for e in self.frames.pending(a_id) if e.target is not None]
        if not pend:
            return
        g = self.graph
        a = g.index_of(a_id)
        t_a = g.poses[a].double().cpu()
        nxt = g.poses[a + 1].double().cpu() if a + 1 < g.n else t_a
        ts_a = float(g.timestamps[a])
        ts_b = float(g.timestamps[a + 1]) if a + 1 < g.n else ts_a
        for e in pend:
            alpha = 0.0 if ts_b <= ts_a else (e.timestamp - ts_a) / (ts_b - ts_a)
            init = se3_interpolate(t_a, nxt, torch.tensor(alpha, dtype=torch.float64))
            self.frames.refine(e, init)

    # -------------------------------------------------------------------------------------- pruning --
    def _remove_redundant(self, k: int) -> None:
        g = self.graph
        r = k - 1
        if not self.cfg.remove_redundant or r - 1 <= self.fragment_start:
            return
        touches_loop = ((g.edge_kind == EDGE_LOOP) & ((g.ii == r) | (g.jj == r))).any()
        if bool(touches_loop):
            return
        i = torch.tensor([r - 1], device=g.device)
        j = torch.tensor([r], device=g.device)
        d = 0.5 * float(g.frame_distance(i, j)[0] + g.frame_distance(j, i)[0])
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
        pose = self.trajectory()[1][-1]
        self.reinits += 1
        self.fragment_start = self.graph.n
        self.initialized = False
        self._consecutive_failures = 0
        LOG.warning("re-initialising the map at frame %d (new fragment from keyframe %d)", frame.index,
                    self.fragment_start)
        kf_id = self._add_keyframe(frame, seg, pose.double(), disp=None)
        return self._result(frame, self.frames.entries[-1], ref, track, kf_id=kf_id)

    # -------------------------------------------------------------------------------------- the end --
    def observe_any(self, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """Observations of any edges: retired ones from the graph's store, the others from the frontend."""
        g = self.graph
        ii, jj = ii.to(g.device), jj.to(g.device)
        retired = g.is_retired(ii, jj).to(g.device) & ~g.has_edges(ii, jj)
        if not bool(retired.any()):
            return self._observe(ii, jj)
        live = torch.nonzero(~retired).squeeze(1)
        dead = torch.nonzero(retired).squeeze(1)
        parts = [self._observe(ii[live], jj[live])] if len(live) else []
        parts.append(g.retired_observations(ii[dead], jj[dead]))
        order = torch.argsort(torch.cat([live, dead]))
        return _concat(parts, order)

    def finalize(self) -> None:
        if self.graph.n and self.initialized:
            self._fill_pending(self.graph.id_of(-1))
        if self.graph.n > 1 and self.initialized:
            report = self.optimizer.finalize(self.graph, self.observe_any)
            if report.rejected:
                LOG.warning("final optimisation rejected: %s", report.message)
            self.frames.refill()
        elif not self.initialized:
            LOG.warning("the map was never initialised (too little parallax); poses are identity/extrapolated")


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
    return EdgeObservations(cat("ii"), cat("jj"), cat("target"), cat("weight"), dynamic=cat("dynamic"),
                            depth_damping=damping)
