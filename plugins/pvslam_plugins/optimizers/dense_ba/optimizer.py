"""The dense BA optimizer behind ``online_ba`` and ``offline_ba``: windowed BA per keyframe (:meth:`step`), loop
closure (Sim(3) pose graph + relaxed loop BA, :meth:`loop`) and a global BA at the end (:meth:`finalize`), on top of
:mod:`pvslam_core.geometry`.  Keyframe 0 is always fixed (the gauge); poses are T_wc."""
from __future__ import annotations

import logging
import math
from typing import Callable, Optional

import numpy as np
import torch

from pvslam_core.geometry.ba import BAOptions, dense_ba
from pvslam_core.geometry.lie import quat_to_rotmat, sim3_from_se3, sim3_inv, sim3_log, sim3_mul
from pvslam_core.geometry.pose_graph import loop_relative_sim3, odometry_measurements, sim3_pose_graph
from pvslam_core.geometry.two_view import translation_direction
from pvslam_core.interfaces import BuildContext, Optimizer
from pvslam_core.types import EdgeObservations, LoopClosure, OptimizerReport

from .config import BAConfigBase

log = logging.getLogger("pvslam.ba")

# LM damping of the reduced pose system (S_kk += ep + lm S_kk): DROID-SLAM's frontend constants for the window BA,
# its backend constants for the loop and global BAs (larger problems, better constrained)
WINDOW_LM, WINDOW_EP = 1e-4, 0.1
GLOBAL_LM, GLOBAL_EP = 1e-5, 1e-2
# inverse-depth damping added to C where the frontend gives no learned one: DROID's 1e-3 kept the window's depths
# from converging against a classical flow (docs/decisions.md: DEPTH_DAMPING)
DEPTH_DAMPING = 1e-5
MIN_DEPTH = 0.2  # points with relative depth z_j / z_i below this get zero weight (DROID)
PGO_ITERS = 25  # Levenberg-Marquardt iterations of the Sim(3) pose graph
# the pose graph runs only when a loop measurement disagrees with the estimate by more than this (|log scale|,
# rotation in rad, translation / median depth of the old keyframe); smaller drift is left to the loop BA
# (docs/decisions.md: PGO_MIN_DRIFT)
PGO_MIN_DRIFT = 0.02
PGO_LOOP_WEIGHT = 10.0  # information weight of a loop edge relative to an odometry edge in the pose graph
# a loop measurement whose translation is further off the loop edge's epipolar direction (deg) stays out of the pose
# graph: a revisit seen from behind gets a depth-based pose that lands short (docs/decisions.md: PGO_MAX_DIRECTION_DEG)
PGO_MAX_DIRECTION_DEG = 15.0
# ... and so does a loop whose scale measured from both ends disagrees by more than this factor: a loop seen on few
# pixels can put a wrong scale into the whole chain (docs/decisions.md: PGO_MAX_SCALE_DISAGREEMENT)
PGO_MAX_SCALE_DISAGREEMENT = 1.25
PGO_MIN_PIXELS = 30  # confidently matched pixels a loop edge's Sim(3) measurement needs (else the BA alone)


def _merge(reports: list[OptimizerReport], message: str = "") -> OptimizerReport:
    reports = [r for r in reports if r is not None]
    if not reports:
        return OptimizerReport(message=message)
    out = OptimizerReport(
        iterations=sum(r.iterations for r in reports),
        cost_before=reports[0].cost_before,
        cost_after=reports[-1].cost_after,
        num_edges=max(r.num_edges for r in reports),
        num_free_poses=max(r.num_free_poses for r in reports),
        rejected=any(r.rejected for r in reports),
    )
    msgs = [message] + [r.message for r in reports if r.message]
    out.message = "; ".join(m for m in msgs if m)
    return out


class DenseBAOptimizer(Optimizer):
    """Base class: windowed BA in :meth:`step`, loop closure in :meth:`loop`, global BA in :meth:`finalize`."""

    def __init__(self, config: BAConfigBase, device: Optional[torch.device] = None):
        self.config = config
        self.device = device
        self.last_pgo: dict = {}
        self._corrected_id: Optional[int] = None  # stable id of the newest keyframe of the last loop BA

    # ------------------------------------------------------------------------------------------ helpers
    def options(self, kind: str) -> BAOptions:
        """The dense BA's settings for one kind of call: ``"window"`` (:meth:`step`), ``"loop"`` or ``"final"``."""
        c = self.config
        iters, lm, ep = {"window": (c.iters, WINDOW_LM, WINDOW_EP), "loop": (c.loop.iters, GLOBAL_LM, GLOBAL_EP),
                         "final": (c.final.iters, GLOBAL_LM, GLOBAL_EP)}[kind]
        return BAOptions(iters=iters, lm=lm, ep=ep, depth_damping=DEPTH_DAMPING, min_depth=MIN_DEPTH, robust=c.robust,
                         robust_scale=c.robust_scale)

    def window_free(self, graph, window: int) -> torch.Tensor:
        """Poses of the last ``window`` keyframes are free; keyframe 0 is always fixed."""
        n = graph.n
        free = torch.zeros(n, dtype=torch.bool, device=graph.device)
        free[max(1, n - window):] = True
        return free

    def window_ba(self, graph, obs: EdgeObservations, window: int, options: BAOptions) -> OptimizerReport:
        n = graph.n
        free = self.window_free(graph, window)
        # depths: the window's keyframes, plus any older keyframe that is the source of an observed edge
        depth_free = torch.zeros(n, dtype=torch.bool, device=graph.device)
        depth_free[max(0, n - window):] = True
        depth_free[obs.ii.to(graph.device)] = True
        return dense_ba(graph, obs, free, options, depth_free=depth_free)

    # ------------------------------------------------------------------------------------------ interface
    def step(self, graph, obs: EdgeObservations) -> OptimizerReport:
        if graph.n < 2 or obs.ii.numel() == 0:
            return OptimizerReport(message="nothing to optimise")
        return self.window_ba(graph, obs, self.config.window, self.options("window"))

    def loop(self, graph, obs: EdgeObservations, loops: list[LoopClosure]) -> OptimizerReport:
        c = self.config
        n = graph.n
        if n < 2 or obs.ii.numel() == 0:
            return OptimizerReport(message="nothing to optimise")
        pairs = [(int(graph.index_of(l.kf_i)), int(graph.index_of(l.kf_j))) for l in loops]  # graph indices
        # a depth or distance prior observes the scale: a Sim(3) correction would move it against the prior
        pgo = c.loop.sim3_pgo and obs.disp_prior is None and obs.dist_prior is None
        msg = self.sim3_correction(graph, obs, pairs) if pgo and pairs else ""
        if c.loop.sim3_pgo and not pgo and pairs:
            msg = "sim3 pgo skipped (the observations carry a depth or distance prior: the scale is observed)"
        # the loop BA frees the keyframes from the oldest loop keyframe on (the window spans the loop)
        t0 = max(1, min((min(i, j) for i, j in pairs), default=max(0, n - c.window)))
        touched = torch.zeros(n, dtype=torch.bool, device=graph.device)
        touched[obs.ii.to(graph.device)] = True
        touched[obs.jj.to(graph.device)] = True
        free = touched.clone()
        free[:t0] = False
        free[0] = False
        for i, j in pairs:  # the old side of each loop anchors the map (and the monocular scale)
            free[min(i, j)] = False
        rep = dense_ba(graph, obs, free, self.options("loop"))
        if not rep.rejected:  # the keyframes up to this loop's newest one are corrected (see sim3_correction)
            self._corrected_id = int(graph.id_of(max(max(i, j) for i, j in pairs)))
        return _merge([rep], msg)

    def finalize(self, graph, observe: Callable[[torch.Tensor, torch.Tensor], EdgeObservations]) -> OptimizerReport:
        c = self.config
        if graph.n < 2 or (graph.num_edges + graph.num_retired) == 0 or c.final.iters == 0 or c.final.rounds == 0:
            return OptimizerReport(message="no final optimisation")
        free = torch.ones(graph.n, dtype=torch.bool, device=graph.device)
        free[0] = False
        reports = []
        for _ in range(c.final.rounds):
            obs = observe(*graph.all_edges())  # active edges re-observed, retired ones as stored
            reports.append(dense_ba(graph, obs, free, self.options("final")))
        return _merge(reports, "global BA")

    # ------------------------------------------------------------------------------------------ loop closure
    @staticmethod
    def _drift(S: torch.Tensor, a: int, b: int, Zab: torch.Tensor, disp_old: torch.Tensor) -> float:
        """How far the current relative Sim3 ``S_a^-1 S_b`` is from the loop measurement ``Zab``: the largest of
        |log scale|, the rotation angle (rad) and the translation difference over the old keyframe's median depth."""
        r = sim3_log(sim3_mul(sim3_inv(Zab), sim3_mul(sim3_inv(S[a]), S[b])))  # [tau(3), phi(3), sigma]
        d = disp_old[torch.isfinite(disp_old) & (disp_old > 0)]
        depth = 1.0 / float(d.median()) if d.numel() else 1.0
        return max(abs(float(r[6])), float(r[3:6].norm()), float(r[:3].norm()) / depth)

    def sim3_correction(self, graph, obs: EdgeObservations, loops: list[tuple[int, int]]) -> str:
        """Sim(3) pose graph of the drift since the last correction: the odometry chain (k, k+1) from keyframe ``p``
        to the newest, with their current relative poses (scale 1), plus one edge per observed loop edge, measured
        by :func:`loop_relative_sim3` with the old keyframe fixed.  ``p`` is the newest keyframe of the previous
        loop call when it lies between the loop's old keyframe and the new one, else the oldest loop keyframe;
        ``p`` and the loops' old keyframes are fixed.  A loop stays out of the graph when its translation is off the
        loop edge's epipolar direction (``PGO_MAX_DIRECTION_DEG``) or, where both of its edges are observed, when
        the scale measured from either end disagrees (``PGO_MAX_SCALE_DISAGREEMENT``; with one usable direction
        only, that one is taken unchecked).  Applies the corrected poses to the chain and divides each chain
        keyframe's inverse depth by its scale.  Returns a message.

        Why not all keyframes with keyframe 0 fixed: the graph holds the chain and this call's loop edges only, so
        it cannot know what earlier loops corrected.  On repeated laps (closures go to the previous lap, see the loop
        policy) a closure then bent every keyframe from the old keyframe on, i.e. the part of the previous lap that
        earlier closures had tied to the lap before it; and a pose graph over every keyframe grows with the run.
        The keyframes up to the previous correction are as good as the map gets; the chain since then holds this
        loop's drift (ORB-SLAM instead keeps the older loop edges in its graph; fixing the corrected keyframes is
        the simpler stand-in, not an equivalent; docs/decisions.md: DenseBAOptimizer.sim3_correction)."""
        n, dev = graph.n, graph.device
        lo = min(min(i, j) for i, j in loops)  # the oldest loop keyframe
        p = self._chain_start(graph, lo, min(max(i, j) for i, j in loops))
        olds = sorted({min(i, j) for i, j in loops if min(i, j) < p})  # fixed nodes outside the chain
        nodes = torch.cat([torch.tensor(olds, dtype=torch.int64), torch.arange(p, n)]).to(dev)  # graph indices
        local = {g: l for l, g in enumerate(nodes.tolist())}  # graph index -> node; every loop end is a node
        S_all = sim3_from_se3(graph.poses, 1.0)
        ii, jj, Z = odometry_measurements(S_all[p:])
        e_ii, e_jj, e_Z = [ii + len(olds)], [jj + len(olds)], [Z]
        e_w = [torch.ones(len(ii), dtype=torch.float64, device=dev)]
        used_loops, drift, rejected = 0, 0.0, 0
        for li, lj in loops:
            edge = self._loop_edge(graph, obs, max(li, lj), min(li, lj))
            if edge is None:
                rejected += 1
                continue
            if not edge:
                continue
            a, b, Zab = edge
            e_ii.append(torch.tensor([local[a]], device=dev))
            e_jj.append(torch.tensor([local[b]], device=dev))
            e_Z.append(Zab[None])
            e_w.append(torch.full((1,), PGO_LOOP_WEIGHT, dtype=torch.float64, device=dev))
            drift = max(drift, self._drift(S_all, a, b, Zab, graph.disps[min(li, lj)]))
            used_loops += 1
        if used_loops == 0:
            why = f"{rejected} left out by the direction / scale checks" if rejected else "no usable loop measurement"
            return f"sim3 pgo skipped ({why})"
        if drift < PGO_MIN_DRIFT:
            self.last_pgo = {"applied": False, "drift": drift}
            return f"sim3 pgo skipped (drift {drift:.3g} < PGO_MIN_DRIFT {PGO_MIN_DRIFT:g})"
        edges = [torch.cat(e) for e in (e_ii, e_jj, e_Z, e_w)]
        return self._apply_pose_graph(graph, S_all[nodes], edges, len(olds), p, used_loops)

    def _loop_edge(self, graph, obs: EdgeObservations, a_new: int, b_old: int):
        """The pose graph's edge for the loop ``a_new <-> b_old``: ``(a, b, Z_ab)`` of one usable measurement
        direction (the old keyframe as the reference where both are usable); ``()`` when neither direction gives a
        usable measurement; None when the direction or scale check leaves the loop out."""
        meas = self._loop_measurements(graph, obs, a_new, b_old)
        if len(meas) == 2:
            # the same relative scale measured from either end: a consistent pair multiplies to 1
            product = meas[(b_old, a_new)][2] * meas[(a_new, b_old)][2]
            if abs(math.log(product)) > math.log(PGO_MAX_SCALE_DISAGREEMENT):
                log.info("loop %d <-> %d: measurement left out of the pose graph (scale %.3g from keyframe %d, "
                         "%.3g from %d: product %.3g)", a_new, b_old, meas[(b_old, a_new)][2], b_old,
                         meas[(a_new, b_old)][2], a_new, product)
                return None
        for a, b in ((b_old, a_new), (a_new, b_old)):  # prefer the old keyframe as the reference
            if (a, b) not in meas:
                continue
            e, Zab, _ = meas[(a, b)]
            off = self._direction_error(Zab, obs.target[e], obs.weight[e], graph.intrinsics)
            if off is not None and off > PGO_MAX_DIRECTION_DEG:
                log.info("loop %d <-> %d: measurement left out of the pose graph (translation %.1f deg off the "
                         "edge's epipolar direction)", a_new, b_old, off)
                return None
            return a, b, Zab
        return ()

    @staticmethod
    def _loop_measurements(graph, obs: EdgeObservations, a_new: int, b_old: int) -> dict:
        """``{(a, b): (edge, Z_ab, scale ratio)}`` for each observed direction of the loop whose Sim(3) measurement
        (:func:`loop_relative_sim3`) saw enough pixels and gave a finite, plausible scale."""
        dev, poses, disps = graph.device, graph.poses, graph.disps
        oii, ojj = obs.ii.to(dev), obs.jj.to(dev)
        meas = {}
        for a, b in ((b_old, a_new), (a_new, b_old)):
            m = torch.nonzero((oii == a) & (ojj == b)).squeeze(1)
            if len(m) == 0:
                continue
            e = int(m[0])
            Zab, s, used = loop_relative_sim3(poses[a], disps[a], poses[b], disps[b], graph.intrinsics,
                                              obs.target[e].to(dev), obs.weight[e].to(dev))
            if used < PGO_MIN_PIXELS or not bool(torch.isfinite(Zab).all()) or not (0.05 < s < 20.0):
                continue
            meas[(a, b)] = (e, Zab, s)
        return meas

    def _apply_pose_graph(self, graph, S: torch.Tensor, edges: list[torch.Tensor], n_olds: int, p: int,
                          used_loops: int) -> str:
        """Solve the pose graph over nodes ``S [m, 8]`` (the loops' old keyframes, then the chain from ``p``; those
        and ``p`` fixed) with ``edges = [ii, jj, Z, weights]`` and apply it to the chain's poses and depths."""
        n, dev, disps = graph.n, graph.device, graph.disps
        fixed = torch.zeros(S.shape[0], dtype=torch.bool, device=dev)
        fixed[: n_olds + 1] = True  # the loops' old keyframes and the chain's first keyframe p
        res = sim3_pose_graph(S, edges[0], edges[1], edges[2], fixed, edges[3], iters=PGO_ITERS)
        scales = res.poses[:, 7]
        ok = bool(torch.isfinite(res.poses).all()) and bool((scales > 0.02).all()) and bool((scales < 50).all())
        self.last_pgo = {"cost_before": res.cost_before, "cost_after": res.cost_after, "iterations": res.iterations,
                         "loops": used_loops, "applied": ok}
        if not ok:
            log.warning("sim3 pose graph gave a degenerate result; poses left unchanged")
            return "sim3 pgo rejected (degenerate result)"
        chain = res.poses[n_olds:]  # [n - p, 8]
        idx = torch.arange(p, n, device=dev)
        graph.set_poses(idx, chain[:, :7])
        graph.set_disps(idx, (disps[p:] / chain[:, 7].to(disps.dtype).reshape(-1, 1, 1)).clamp(min=1e-3))
        return (f"sim3 pgo: {used_loops} loop edge(s) over keyframes {p}..{n - 1}, cost {res.cost_before:.4g} -> "
                f"{res.cost_after:.4g} in {res.iterations} it")

    @staticmethod
    def _direction_error(Zab: torch.Tensor, target: torch.Tensor, weight: torch.Tensor,
                         intr: torch.Tensor) -> Optional[float]:
        """Angle (deg) between the translation of a loop measurement ``Zab`` (camera b -> camera a, a's depth) and
        the direction of the loop edge's own essential matrix (``target [2, h, w]``: a's pixels in b, ``weight [2, h,
        w]``), sign ignored; None when the flow does not give a direction (too little parallax, no fit).

        Why: the measurement fits b's pose to the flow with a's depth held, so where the flow of the near scene is
        short (a revisit seen from some metres behind: the view is magnified and DIS underestimates it) the pose
        lands short along the viewing direction and the pose graph bends the whole chain to it; the essential
        matrix only needs the flow's directions (docs/decisions.md: PGO_MAX_DIRECTION_DEG)."""
        h, w = target.shape[-2:]
        conf = weight.double().reshape(2, -1).min(0).values
        ok = conf >= 0.5 * float(conf.max().clamp(min=1e-12))
        if int(ok.sum()) < 16:
            return None
        ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                                indexing="ij")
        p0 = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)[ok.cpu()].numpy()
        p1 = target.double().reshape(2, -1).T[ok].cpu().numpy()
        fx, fy, cx, cy = (float(v) for v in intr.reshape(-1)[:4])
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        R_ab = quat_to_rotmat(Zab[3:7].double().cpu()).numpy()
        # inside b's view only (a loop edge's targets outside it are extrapolated), RANSAC at 0.25 BA px
        inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        t_e = translation_direction(p0[inside], p1[inside], K, threshold=0.25, min_parallax=1.0, rotation=R_ab.T)
        if t_e is None:
            return None
        t_ab = -R_ab.T @ Zab[:3].double().cpu().numpy()  # a -> b: X_b = R_ab^T X_a - R_ab^T t_ab
        n = float(np.linalg.norm(t_ab))
        if n == 0.0:
            return 90.0
        return float(np.degrees(np.arccos(min(1.0, abs(float(t_e @ t_ab)) / n))))

    def _chain_start(self, graph, lo: int, newest_new: int) -> int:
        """First keyframe of the pose graph's chain: the newest keyframe of the previous loop call when it is still
        in the graph and lies strictly between ``lo`` and the loops' new keyframes, else ``lo``."""
        if self._corrected_id is None:
            return lo
        try:
            p = int(graph.index_of(self._corrected_id))
        except KeyError:  # removed since
            return lo
        return p if lo < p < newest_new else lo


def make_dense_ba(config: BAConfigBase, context: Optional[BuildContext] = None) -> DenseBAOptimizer:
    """Registry factory for both schedules (``online_ba``, ``offline_ba``)."""
    return DenseBAOptimizer(config, getattr(context, "device", None))
