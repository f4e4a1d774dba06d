"""Keyframe mapping: initialisation, graph growth, online BA calls, loop closure, pose filling, failures.

The :class:`Mapper` owns the frame graph and the per-frame anchors; it calls the frontend, optimizer and loop
detector through their interfaces only.  Poses are T_wc ``[t, q_xyzw]``.
"""
from __future__ import annotations

import logging
from typing import Optional

import torch

from .anchors import FrameAnchors
from ..config import PipelineConfig
from .edges import active_edges, loop_edges, neighbour_edges, proximity_edges
from ..geometry.lie import se3_interpolate, se3_mul
from ..geometry.projective import edge_transforms, project_points
from .graph import EDGE_LOOP, EDGE_ODOMETRY, EDGE_PROXIMITY, FrameGraph
from .initializer import two_view_init
from ..types import Frame, LoopCandidate, PanopticSegmentation, SequenceInfo, TrackResult

LOG = logging.getLogger("pvslam")


class Mapper:
    def __init__(self, pcfg: PipelineConfig, info: SequenceInfo, frontend, optimizer, loop_detector, device):
        self.cfg = pcfg.graph
        self.frontend = frontend
        self.optimizer = optimizer
        self.loop_detector = loop_detector
        ds = self.cfg.ba_downsample
        intr = info.intrinsics.scaled(1.0 / ds)
        self.ba_shape = (info.intrinsics.height // ds, info.intrinsics.width // ds)
        self.graph = FrameGraph(self.ba_shape[0], self.ba_shape[1], intr.vector(torch.float32, device), device=device)
        self.anchors = FrameAnchors(self.cfg.motion_robust, self.cfg.motion_robust_scale)
        self.initialized = False
        self.fragment_start = 0  # first keyframe of the current map fragment (after a re-initialisation)
        self.loops: list[LoopCandidate] = []  # accepted loops, as input-frame indices in (i, j)
        self.kf_images: list[torch.Tensor] = []  # uint8 [3, h, w] per keyframe at BA resolution (point cloud)
        self.kf_segs: list[Optional[PanopticSegmentation]] = []  # per keyframe at BA resolution (point cloud)
        self.failures = 0
        self.reinits = 0
        self._consecutive_failures = 0
        self._loop_cands: list[LoopCandidate] = []
        self._last_loop_ba: Optional[int] = None  # graph size at the last loop BA

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
        return self.anchors.poses(self.graph.poses)

    def _observe(self, ii: torch.Tensor, jj: torch.Tensor):
        return self.frontend.observe(self.graph, ii.to(self.graph.ii.device), jj.to(self.graph.ii.device))

    def _optimize_window(self, k: int, rounds: int) -> None:
        for _ in range(rounds):
            ii, jj = active_edges(self.graph, k, self.cfg.active_window)
            if ii.numel() == 0:
                return
            report = self.optimizer.step(self.graph, self._observe(ii, jj))
            if report.rejected:
                LOG.warning("keyframe %d: optimizer rejected an update: %s", k, report.message)

    # -------------------------------------------------------------------------------------- per frame --
    def process(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> bool:
        """Track one frame; returns True when it became a keyframe."""
        if self.graph.n == 0:
            self._add_keyframe(frame, seg, pose=torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64),
                               disp=None)
            return True
        track = self.frontend.track(frame, seg)
        if track.failed:
            return self._failed(frame, seg, track)
        self._consecutive_failures = 0
        if not track.is_keyframe:
            self.anchors.add_frame(frame.index, frame.timestamp, self.graph.n - 1, self._predict_rel(),
                                   track.target, track.weight)
            return False
        a = self.graph.n - 1
        pose = self._keyframe_pose_guess(a, track)
        self._add_keyframe(frame, seg, pose, disp=None)
        k = self.graph.n - 1
        if not self.initialized:
            self._try_initialise(k)
            return True
        self._optimize_window(k, self.frontend.iterations)
        self._close_loops(k)
        self._fill_pending(a)
        self._remove_redundant(k)
        return True

    def _predict_rel(self) -> torch.Tensor:
        """Relative pose guess for a non-keyframe: the previous frame's (its anchor is the same keyframe)."""
        return self.anchors.last_rel()

    def _keyframe_pose_guess(self, a: int, track: TrackResult) -> torch.Tensor:
        t_a = self.graph.poses[a].double()
        if not self.initialized or track.target is None:
            return t_a.cpu().clone()
        init = se3_mul(t_a.cpu(), self.anchors.last_rel())
        pose = self.anchors.motion_only(init, t_a, self.graph.disps[a], self.graph.intrinsics, track.target,
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
        h, w = self.ba_shape
        k_new = self.graph.n
        if disp is None and self.initialized and k_new > self.fragment_start:
            disp = self._warped_depth(k_new - 1, pose)
        if disp is None:
            guess = self.frontend.initial_depth(k_new) if k_new > 0 else None
            if guess is not None:
                disp = guess
            elif k_new > 0:
                disp = torch.full((h, w), float(self.graph.disps[k_new - 1].median()))
            else:
                disp = torch.ones(h, w)
        k = self.graph.add_keyframe(frame.index, frame.timestamp, pose.to(self.graph.device), disp.to(self.graph.device))
        self.frontend.add_keyframe(k, frame, seg)
        self.anchors.add_keyframe(frame.index, frame.timestamp, k)
        img, small = self._small(frame, seg)
        self.kf_images.append(img)
        self.kf_segs.append(small)
        if k > self.fragment_start:
            ii, jj = neighbour_edges(k, self.cfg, first=self.fragment_start)
            self.graph.add_edges(ii, jj, EDGE_ODOMETRY)
            if self.initialized:
                ii, jj = proximity_edges(self.graph, k, self.cfg, first=self.fragment_start)
                if ii.numel():
                    self.graph.add_edges(ii, jj, EDGE_PROXIMITY)
        # every keyframe is described in order (indices must match); candidates are used after the local BA
        self._loop_cands = self.loop_detector.add_keyframe(k, frame) if self.loop_detector is not None else []
        return k

    # --------------------------------------------------------------------------------- initialisation --
    def _try_initialise(self, k: int) -> None:
        first = self.fragment_start
        if k - first + 1 < self.cfg.warmup:
            return
        # The farthest pair first (most parallax); when its flow fails (fast motion: every frame a keyframe on a
        # highway) nearer partners, down to `init_tries` pairs per keyframe.
        init, m = None, k
        for m in range(k, max(first, k - self.cfg.init_tries), -1):
            obs = self._observe(torch.tensor([first]), torch.tensor([m]))
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
        self._optimize_window(k, max(3, 2 * self.frontend.iterations))
        for a in range(first, k):
            self._fill_pending(a)

    # ------------------------------------------------------------------------------------------ loops --
    def _rotation_deg(self, i: int, j: int) -> float:
        qi, qj = self.graph.poses[i, 3:].double(), self.graph.poses[j, 3:].double()
        dot = float((qi * qj).sum().abs().clamp(max=1.0))
        return float(torch.rad2deg(2 * torch.acos(torch.tensor(dot))))

    def _close_loops(self, k: int) -> None:
        accepted = []
        for c in self._loop_cands:
            if not (c.verified and 0 <= c.j < k):
                continue
            rot = self._rotation_deg(k, c.j)
            if rot > self.cfg.loop_max_rotation_deg:
                LOG.info("loop %d <-> %d rejected: current orientations differ by %.0f deg", k, c.j, rot)
                continue
            accepted.append(c)
        if not accepted:
            return
        best = accepted[0]
        ii, jj = loop_edges(k, best.j, self.graph.n, self.cfg.bidirectional)
        added = self.graph.add_edges(ii, jj, EDGE_LOOP)
        if not bool(added.any()):
            return
        fi, fj = int(self.graph.frame_index[k]), int(self.graph.frame_index[best.j])
        LOG.info("loop closure: keyframe %d (frame %d) <-> keyframe %d (frame %d), score %.3f, %d inliers",
                 k, fi, best.j, fj, best.score, best.inliers)
        self.loops.append(LoopCandidate(fi, fj, best.score, best.verified, best.inliers))
        n = self.graph.n
        if self._last_loop_ba is not None and 0 <= n - self._last_loop_ba < self.cfg.loop_ba_min_gap:
            # along a revisit nearly every keyframe closes a loop: the first one's loop BA (+ pose graph) corrects
            # the drift; later ones only add their edges, which the next window BAs include (they touch k)
            LOG.debug("loop %d <-> %d: edges added; loop BA ran %d keyframes ago", k, best.j, n - self._last_loop_ba)
            return
        self._last_loop_ba = n
        a_ii, a_jj = active_edges(self.graph, k, self.cfg.active_window)
        ii_all = torch.cat([a_ii.cpu(), ii]).to(self.graph.ii.device)
        jj_all = torch.cat([a_jj.cpu(), jj]).to(self.graph.ii.device)
        pair = torch.unique(torch.stack([ii_all, jj_all]), dim=1)
        report = self.optimizer.loop(self.graph, self._observe(pair[0], pair[1]), [best])
        if report.rejected:
            LOG.warning("loop BA rejected: %s", report.message)

    # ------------------------------------------------------------------------------------ pose filling --
    def _fill_pending(self, a: int) -> None:
        """Motion-only BA for the non-keyframes anchored at keyframe ``a`` (its depth is refined by now)."""
        pend = [e for e in self.anchors.pending(a) if e.target is not None]
        if not pend:
            return
        t_a = self.graph.poses[a].double()
        nxt = self.graph.poses[a + 1].double().cpu() if a + 1 < self.graph.n else t_a.cpu()
        ts_a = float(self.graph.timestamps[a])
        ts_b = float(self.graph.timestamps[a + 1]) if a + 1 < self.graph.n else ts_a
        for e in pend:
            alpha = 0.0 if ts_b <= ts_a else (e.timestamp - ts_a) / (ts_b - ts_a)
            init = se3_interpolate(t_a.cpu(), nxt, torch.tensor(alpha, dtype=torch.float64))
            self.anchors.refine(e, init, t_a, self.graph.disps[a], self.graph.intrinsics)

    # -------------------------------------------------------------------------------------- pruning --
    def _remove_redundant(self, k: int) -> None:
        r = k - 1
        if not self.cfg.remove_redundant or r - 1 <= self.fragment_start:
            return
        touches_loop = ((self.graph.edge_kind == EDGE_LOOP) & ((self.graph.ii == r) | (self.graph.jj == r))).any()
        if bool(touches_loop):
            return
        i = torch.tensor([r - 1], device=self.graph.ii.device)
        j = torch.tensor([r], device=self.graph.ii.device)
        d = 0.5 * float(self.graph.frame_distance(i, j)[0] + self.graph.frame_distance(j, i)[0])
        if d >= self.cfg.redundant_thresh:
            return
        self._fill_pending(r)
        self.anchors.remove_keyframe(r, self.graph.poses)
        mask = (self.graph.ii == r) | (self.graph.jj == r)
        if bool(mask.any()):
            self.frontend.forget_edges(self.graph.ii[mask], self.graph.jj[mask])
        self.frontend.remove_keyframe(r)
        if self.loop_detector is not None:
            self.loop_detector.remove_keyframe(r)
        self.graph.remove_keyframe(r)
        del self.kf_images[r]
        del self.kf_segs[r]
        LOG.debug("removed redundant keyframe %d (frame distance %.2f)", r, d)

    # ------------------------------------------------------------------------------------- failures --
    def _failed(self, frame: Frame, seg, track: TrackResult) -> bool:
        self.failures += 1
        self._consecutive_failures += 1
        LOG.warning("frame %d (%s): tracking failed: %s", frame.index, frame.name or frame.timestamp, track.message)
        blank = float(frame.image.float().std()) < 2.0  # a dark/blank stretch: nothing to re-initialise on
        if self._consecutive_failures < self.cfg.reinit_after or blank:
            self.anchors.add_frame(frame.index, frame.timestamp, self.graph.n - 1, self._predict_rel(), failed=True)
            return False
        # Re-initialise: start a new map fragment at this frame, placed at the last known pose.
        pose = self.trajectory()[1][-1]
        self.reinits += 1
        self.fragment_start = self.graph.n
        self.initialized = False
        self._consecutive_failures = 0
        LOG.warning("re-initialising the map at frame %d (new fragment from keyframe %d)", frame.index,
                    self.fragment_start)
        self._add_keyframe(frame, seg, pose.double(), disp=None)
        return True

    # -------------------------------------------------------------------------------------- the end --
    def finalize(self) -> None:
        if self.graph.n and self.initialized:
            self._fill_pending(self.graph.n - 1)
        if self.graph.n > 1 and self.initialized:
            report = self.optimizer.finalize(self.graph, self._observe)
            if report.rejected:
                LOG.warning("final optimisation rejected: %s", report.message)
            self.anchors.refill(self.graph.poses, self.graph.disps, self.graph.intrinsics)
        elif not self.initialized:
            LOG.warning("the map was never initialised (too little parallax); poses are identity/extrapolated")
