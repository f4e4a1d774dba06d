"""Dense bundle adjustment over keyframe poses and per-pixel inverse depths (DROID-SLAM's BA, anchors 1.4),
in vectorised torch, with the per-pixel linearisation on the CPU in compiled loops (:mod:`.ba_kernels`, numba;
the torch version stays as the reference and for float64, CUDA and the Huber kernel).  A call's settings are one :class:`BAOptions`; the problem's state and the pieces of an
iteration live in :mod:`.ba_problem`, residuals and costs in :mod:`.ba_residuals`, the solvers in :mod:`.ba_linalg`
and the motion-only BA of single frames in :mod:`.ba_motion`.

Problem.  For every edge ``e = (i -> j)`` and pixel ``p`` of keyframe ``i`` the residual is
``r = target - pi(G_ij pi^-1(p, d_i[p]))`` with per-coordinate weights ``w = weight_scale * conf * valid``
(``weight_scale = 1e-3`` as DROID); the cost reported in :class:`~pvslam_core.types.OptimizerReport` is the
plain ``sum conf * valid * |r|^2`` (no ``weight_scale``, no robust re-weighting).

Unknowns.  Poses of the keyframes with ``free = True`` (left retraction of the world-to-camera pose,
``G <- Exp(xi) G``, i.e. ``T_wc <- T_wc Exp(-xi)``; see :mod:`.projective`) and the inverse depths of the
keyframes with ``depth_free = True`` (default: every source keyframe of an edge, as DROID updates the depth of
fixed-pose frames too).

Gauss-Newton step.  ``[B E; E^T C] [dxi; dd] = [v; w]`` with ``C`` diagonal (one entry per pixel,
``C = sum_e w Jd^2 + eta``: ``eta`` is DROID's depth damping).  The depths are eliminated with the Schur
complement ``S = B - E C^-1 E^T``, ``b = v - E C^-1 w``; ``S`` is assembled with vectorised scatters (one
``6 x 6`` block per pair of unknown poses coupled through one source keyframe's depth, no Python loop over
edges), LM-damped ``S_kk += ep + lm S_kk`` and solved in float64: dense Cholesky, or - on the CPU with more than
``SPARSE_MIN_POSES`` free poses (global BA), where ``S`` is block-sparse - a sparse LU.  Depths are then
back-substituted ``dd = C^-1 (w - E^T dxi)`` and clamped to ``>= 1e-3``.  Per-iteration cost is linear in
edges x pixels plus the small dense ``6F x 6F`` pose solve.

Chunking (:mod:`.ba_schur`).  ``C`` is diagonal per source keyframe, so ``E C^-1 E^T`` only couples edges that
share a source and both the Schur complement and the back-substitution split exactly over sources.  Each
iteration linearises the edges in chunks of whole sources - at most ``max_chunk_pixels`` edge-pixels
(:class:`BAOptions`), a source with more edges forms a chunk alone - then in chunks of fixed-depth edges (split by edge): a chunk's
residuals, Jacobians and ``E^T`` rows exist only while it adds its ``6 x 6`` blocks to ``S``, ``b`` and its
sources' ``C^-1``, ``w`` (``[Ns, P]``) to the per-source arrays.  After the pose solve the depths are
back-substituted chunk by chunk: the last (largest) chunk keeps its ``E^T`` for this, the others recompute it at
the same linearisation point.  Peak memory is therefore set by the chunk budget (about 130-250 bytes per
edge-pixel of one chunk at float32), not by the number of edges; a problem that fits one chunk is linearised
once, as without chunking.

Disparity prior. ``obs.disp_prior`` (:class:`~pvslam_core.types.DepthPrior`: ``disp`` and ``weight`` ``[m, h, w]``
for the graph keyframes ``ids``; DROID-SLAM's ``disps_sens`` and ``alpha``) adds ``alpha (d - d_prior)^2 / weight_scale`` per
pixel to the objective: ``C += alpha``, ``w += alpha (d_prior - d)`` (DROID's kernel, which takes ``alpha = 0.05``).
Being diagonal in the depths it changes nothing else of the Schur step; a prior at a constant scale also fixes the
monocular gauge.

Distance prior. ``obs.dist_prior`` (:class:`~pvslam_core.types.DistancePrior`, ``[m]`` pairs ``ii`` / ``jj``) adds ``alpha ((L -
|c_i - c_j|) / L)^2`` per pair of camera centres to the objective (in flow-cost units): its 6x6 blocks join the
reduced pose system directly (:mod:`.ba_distance`, which says why and derives the Jacobian).

Gauge.  Poses with ``free = False`` do not enter the system.  The caller fixes at least one pose (keyframe 0);
for monocular problems the remaining scale direction (all free translations and all depths scaled together) is
*not* fixed explicitly: it is held by the LM damping (``ep``, ``lm``) and by the depth damping ``eta``, so it
only drifts as far as the data push it - exactly DROID-SLAM's behaviour.  Fixing two poses with a baseline
fixes it exactly.

Safety.  Inputs and every update are checked; any NaN/Inf or a failed factorisation (after two retries with
10x / 100x damping) keeps the previous estimate (the graph is written only after the last iteration), sets
``report.rejected`` with a message and logs once per distinct message on the ``pvslam.ba`` logger.  Nothing
non-finite is ever written to the graph.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Union

import torch

from ..types import EdgeObservations, OptimizerReport
from .ba_linalg import all_finite, log_once
from .ba_motion import motion_only_ba
from .ba_problem import BAInputs, DenseBAProblem
from .ba_residuals import DISP_MIN, WEIGHT_SCALE, weighted_cost
from .lie import se3_inv

if TYPE_CHECKING:  # pragma: no cover
    from ..slam.graph import FrameGraph

__all__ = ["BAOptions", "dense_ba", "motion_only_ba", "weighted_cost", "DISP_MIN", "WEIGHT_SCALE"]

# a learned per-keyframe damping (EdgeObservations.depth_damping) enters C as scale * eta + offset (DROID's BA)
LEARNED_DAMPING_SCALE = 0.2
LEARNED_DAMPING_OFFSET = 1e-7


@dataclass(frozen=True)
class BAOptions:
    """Settings of one :func:`dense_ba` call (the defaults are DROID-SLAM's frontend constants)."""

    iters: int = 2  # Gauss-Newton iterations
    lm: float = 1e-4  # multiplicative LM damping of the reduced pose system (S_kk += lm S_kk)
    ep: float = 0.1  # additive LM damping of the reduced pose system (S_kk += ep)
    # DROID's eta added to C: a float or a tensor broadcastable to [n, h, w]; a learned obs.depth_damping replaces it
    depth_damping: Union[float, torch.Tensor] = 1e-3
    min_depth: float = 0.2  # points with relative depth z_j / z_i below this get zero weight
    robust: Optional[str] = None  # IRLS kernel on the 2D residual: None / 'none', 'huber' or 'cauchy'
    robust_scale: float = 2.0  # its scale in BA-resolution pixels
    weight_scale: float = WEIGHT_SCALE  # residual weight per unit of confidence
    # per-pixel arithmetic (None: float32, as the graph stores its disparities; the reduced pose system, the pose
    # updates and the poses are always float64)
    dtype: Optional[torch.dtype] = None
    # edge-pixels linearised at once (one chunk of whole sources; a source with more is a chunk of its own)
    max_chunk_pixels: int = 500_000
    # the per-pixel work through the compiled loops of .ba_kernels where they apply (False: the torch reference)
    compiled: bool = True


def dense_ba(graph: "FrameGraph", obs: EdgeObservations, free: torch.Tensor, options: Optional[BAOptions] = None, *,
             depth_free: Optional[torch.Tensor] = None, **overrides) -> OptimizerReport:
    """Run ``options.iters`` Gauss-Newton/LM iterations of dense BA on ``graph`` in place (module docstring).

    ``free`` / ``depth_free``: bool ``[n]`` (``depth_free`` None: every source keyframe of an edge).  ``overrides``:
    single :class:`BAOptions` fields by keyword (``dense_ba(g, obs, free, iters=3)``), applied on top of
    ``options``."""
    if options is not None and not isinstance(options, BAOptions):
        raise TypeError(f"dense_ba: options must be a BAOptions (keywords for single fields), got {options!r}")
    opt = dataclasses.replace(options or BAOptions(), **overrides) if overrides else (options or BAOptions())
    report = OptimizerReport(num_edges=int(obs.ii.numel()))
    inp = _check_inputs(graph, obs, free, depth_free, opt, report)
    if inp is None:
        return report
    pb = DenseBAProblem(graph, obs, inp, opt)
    report.num_free_poses = pb.F
    cost0 = None
    problems: list[str] = []
    for it in range(max(0, int(opt.iters))):
        sysm = pb.assemble(with_cost=cost0 is None)
        if cost0 is None:
            cost0 = sysm.cost
        dxi = torch.zeros(pb.F, 6, dtype=torch.float64, device=pb.dev)
        if pb.F > 0:
            dxi, boost = pb.solve(sysm)
            if dxi is None:
                return _reject_at(report, it, cost0, f"dense_ba: pose system not positive definite even with 100x "
                                                     f"damping (iteration {it}); previous estimate kept")
            if boost > 1.0:
                problems.append(f"iteration {it}: factorisation needed {boost:g}x damping")
        dd = pb.back_substitute(sysm, dxi)
        if not (all_finite(dxi) and all_finite(dd)):
            return _reject_at(report, it, cost0, "dense_ba: non-finite update; previous estimate kept")
        pb.apply(dxi, dd)
        report.iterations = it + 1
    return _finish(graph, pb, report, cost0, problems)


def _finish(graph, pb: DenseBAProblem, report: OptimizerReport, cost0: Optional[float],
            problems: list[str]) -> OptimizerReport:
    """The final cost, the last safety check, and the estimate into the graph."""
    cost1 = pb.current_cost()
    if cost0 is None:
        cost0 = cost1
    report.cost_before, report.cost_after = cost0, cost1
    newT = se3_inv(pb.G)
    if not (math.isfinite(cost1) and all_finite(newT) and all_finite(pb.d)):
        report.cost_after = cost0
        return _report_reject(report, "dense_ba: non-finite state after update; previous estimate kept")
    pb.write(graph, newT)
    if problems:
        report.message = "; ".join(problems)
        log_once("dense_ba: " + report.message)
    return report


def _report_reject(report: OptimizerReport, msg: str) -> OptimizerReport:
    report.rejected = True
    report.message = msg
    log_once(msg)
    return report


def _reject_at(report: OptimizerReport, it: int, cost0: float, msg: str) -> OptimizerReport:
    """A failed iteration ``it``: the previous estimate is kept (nothing was written to the graph)."""
    report.iterations = it
    report.cost_before = report.cost_after = cost0
    return _report_reject(report, msg)


def _check_inputs(graph, obs: EdgeObservations, free, depth_free, opt: BAOptions,
                  report: OptimizerReport) -> Optional[BAInputs]:
    """Shapes, indices and finiteness of the inputs: a malformed call raises, non-finite data rejects (``report``
    says why) and returns None, as does a problem without edges."""
    N = graph.n
    h, w = graph.ba_shape
    P = h * w
    dev = graph.device
    dtype = opt.dtype or torch.float32
    ii = obs.ii.to(dev, torch.int64).reshape(-1)
    jj = obs.jj.to(dev, torch.int64).reshape(-1)
    E = int(ii.shape[0])
    free = torch.as_tensor(free, dtype=torch.bool, device=dev).reshape(-1)
    if free.shape[0] != N:
        raise ValueError(f"free must have one entry per keyframe ({N}), got {free.shape[0]}")
    if E == 0 or N == 0:
        report.message = "no edges"
        return None
    if int(ii.min()) < 0 or int(jj.min()) < 0 or int(ii.max()) >= N or int(jj.max()) >= N:
        raise IndexError(f"edge index out of range for {N} keyframes")
    if tuple(obs.target.shape) != (E, 2, h, w) or tuple(obs.weight.shape) != (E, 2, h, w):
        raise ValueError(f"obs target/weight must be [{E}, 2, {h}, {w}], got {tuple(obs.target.shape)}")
    if depth_free is None:
        depth_free = torch.zeros(N, dtype=torch.bool, device=dev)
        depth_free[ii] = True
    else:
        depth_free = torch.as_tensor(depth_free, dtype=torch.bool, device=dev).reshape(-1).clone()
    for name, t in (("poses", graph.poses), ("disps", graph.disps), ("target", obs.target), ("weight", obs.weight)):
        if not all_finite(t):
            _report_reject(report, f"dense_ba: non-finite values in {name}; estimate left unchanged")
            return None
    eta = _depth_damping(obs, opt, N, h, w, dtype, dev)
    if eta is None:
        _report_reject(report, "dense_ba: non-finite or negative depth damping; estimate left unchanged")
        return None
    msg = _check_priors(obs, N, h, w)
    if msg:
        _report_reject(report, msg)
        return None
    target, conf = obs.target.reshape(E, 2, P).to(dev), obs.weight.reshape(E, 2, P).to(dev)
    return BAInputs(ii, jj, free, depth_free, target, conf, eta, dtype)


def _depth_damping(obs: EdgeObservations, opt: BAOptions, N: int, h: int, w: int, dtype,
                   dev) -> Optional[torch.Tensor]:
    """The depth damping ``[N, P]`` added to ``C``: the frontend's learned one (DROID: ``0.2 eta + 1e-7``) or
    ``opt.depth_damping``; None when it is non-finite or negative."""
    if obs.depth_damping is not None:
        eta = obs.depth_damping.to(dev, dtype)
        eta_map = (LEARNED_DAMPING_SCALE * eta + LEARNED_DAMPING_OFFSET).reshape(N, h * w)
    else:
        eta_t = torch.as_tensor(opt.depth_damping, dtype=dtype, device=dev)
        eta_map = eta_t.expand(N, h, w).reshape(N, h * w) if eta_t.dim() > 0 else eta_t.expand(N, h * w)
    eta_src = obs.depth_damping if obs.depth_damping is not None else torch.as_tensor(opt.depth_damping)
    if not all_finite(eta_src) or bool((eta_src < 0).any()):
        return None
    return eta_map


def _check_priors(obs: EdgeObservations, N: int, h: int, w: int) -> str:
    """Checks of the disparity and distance priors: raises on a malformed one, returns a rejection message for
    non-finite or negative values ('' when they are fine)."""
    dprior, lprior = obs.disp_prior, obs.dist_prior
    if dprior is not None:
        m = int(dprior.ids.shape[0])
        if tuple(dprior.disp.shape) != (m, h, w):
            raise ValueError(f"obs.disp_prior.disp must be [{m}, {h}, {w}], got {tuple(dprior.disp.shape)}")
        if m and (int(dprior.ids.min()) < 0 or int(dprior.ids.max()) >= N):
            raise IndexError(f"obs.disp_prior.ids out of range for {N} keyframes")
        if not (all_finite(dprior.disp) and all_finite(dprior.weight)) or bool((dprior.weight < 0).any()):
            return "dense_ba: non-finite disparity prior or negative prior weight; estimate left unchanged"
    if lprior is not None:
        dpi, dpj = lprior.ii.reshape(-1), lprior.jj.reshape(-1)
        if dpi.numel() and (int(torch.minimum(dpi, dpj).min()) < 0 or int(torch.maximum(dpi, dpj).max()) >= N):
            raise IndexError(f"obs.dist_prior.ii / jj out of range for {N} keyframes")
        if not (all_finite(lprior.dist) and all_finite(lprior.weight)) \
                or bool((lprior.dist <= 0).any()) or bool((lprior.weight < 0).any()):
            return ("dense_ba: non-finite or non-positive distance prior, or a negative weight; estimate left "
                    "unchanged")
    return ""
