"""Dense bundle adjustment over keyframe poses and per-pixel inverse depths (DROID-SLAM's BA, anchors 1.4),
in plain vectorised torch.

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
iteration linearises the edges in chunks of whole sources - at most ``max_chunk_pixels`` edge-pixels (default
2M), a source with more edges forms a chunk alone - then in chunks of fixed-depth edges (split by edge): a chunk's
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

import logging
import math
import re
from typing import TYPE_CHECKING, Optional

import torch

from ..types import EdgeObservations, OptimizerReport
from .ba_distance import distance_prior_terms
from .ba_schur import rowvec, assemble_chunk, backsub_chunk, depth_rows, plan_chunks
from .lie import quat_to_rotmat, se3_exp, se3_inv, se3_mul
from .projective import project_points

if TYPE_CHECKING:  # pragma: no cover
    from ..slam.graph import FrameGraph

__all__ = ["dense_ba", "motion_only_ba", "weighted_cost", "DISP_MIN", "WEIGHT_SCALE"]

log = logging.getLogger("pvslam.ba")
_LOGGED: set[str] = set()

DISP_MIN = 1e-3  # disps.clamp_(min=0.001) as DROID
WEIGHT_SCALE = 1e-3  # w = 0.001 * confidence (DROID's ba kernel)


def _log_once(msg: str) -> None:
    """Log a warning once per distinct message (numbers ignored, so per-iteration variants count once)."""
    key = re.sub(r"[0-9.e+-]+", "#", msg)
    if key not in _LOGGED:
        _LOGGED.add(key)
        log.warning(msg)


def _all_finite(t: torch.Tensor) -> bool:
    """True when every element is finite.  Fast path: one reduction (NaN/Inf propagate into the sum); only an
    overflowing sum of finite values falls back to the element-wise test."""
    if t.numel() == 0:
        return True
    if bool(torch.isfinite(t.sum())):
        return True
    return bool(torch.isfinite(t).all())


def solve_spd(A: torch.Tensor, b: torch.Tensor) -> Optional[torch.Tensor]:
    """Solve the symmetric positive-definite system ``A x = b`` by Cholesky; None if A is not PD or x not finite.

    (A sparse LU was tried for the large block-sparse systems of a global BA / long pose graph: converting from
    the dense assembly made it slower than dense Cholesky up to n = 3000, about 0.3 s single-threaded.)"""
    L, info = torch.linalg.cholesky_ex(A)
    if int(info) != 0:
        return None
    x = torch.cholesky_solve(b.unsqueeze(-1), L).squeeze(-1)
    return x if _all_finite(x) else None


SPARSE_MIN_POSES = 300  # CPU pose systems with more free poses are solved sparsely (dense is faster below:
# 198 free poses dense 0.26 s vs sparse 0.39 s per global-BA iteration; 498: dense 1.19 s vs sparse 0.53 s)


def sparse_block_matrix(br: torch.Tensor, bc: torch.Tensor, bv: torch.Tensor, F: int):
    """Symmetrised scipy CSC matrix ``[kF, kF]`` from ``k x k`` blocks ``bv [n, k, k]`` at block positions
    ``(br, bc)`` (duplicates summed)."""
    import scipy.sparse as sp

    k = bv.shape[-1]
    ar = torch.arange(k)
    rows = (br.cpu().view(-1, 1, 1) * k + ar.view(1, k, 1)).expand(-1, k, k)
    cols = (bc.cpu().view(-1, 1, 1) * k + ar.view(1, 1, k)).expand(-1, k, k)
    M = sp.coo_matrix((bv.detach().cpu().double().numpy().reshape(-1),
                       (rows.reshape(-1).numpy(), cols.reshape(-1).numpy())), shape=(k * F, k * F)).tocsc()
    return (0.5 * (M + M.T)).tocsc()


def sparse_solve(Hs, diag_add, b: torch.Tensor) -> Optional[torch.Tensor]:
    """Solve ``(Hs + diag(diag_add)) x = b`` with SuperLU; None on failure or a non-finite result."""
    import numpy as np
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    try:
        A = (Hs + sp.diags(np.asarray(diag_add, dtype=np.float64))).tocsc()
        x = splu(A).solve(b.detach().cpu().double().numpy())
    except (RuntimeError, ValueError):
        return None
    xt = torch.from_numpy(np.ascontiguousarray(x)).to(b.device, torch.float64)
    if not _all_finite(xt):
        return None
    # the LU does not test definiteness: a positive-definite system gives b.x = x^T A x > 0
    bn = b.detach().cpu().double()
    if float(bn @ xt.cpu()) <= 0 and float(bn.abs().max()) > 0:
        return None
    return xt


def _robust_weights(ru: torch.Tensor, rv: torch.Tensor, kind: Optional[str], scale: float) -> Optional[torch.Tensor]:
    """Per-pixel IRLS factor from the 2D residual (None: no re-weighting)."""
    if kind is None or kind == "none":
        return None
    n = torch.sqrt(ru * ru + rv * rv)
    if kind == "huber":
        return torch.where(n <= scale, torch.ones_like(n), scale / n.clamp(min=1e-12))
    if kind == "cauchy":
        return 1.0 / (1.0 + (n / scale) ** 2)
    raise ValueError(f"unknown robust kernel {kind!r} (use None, 'huber' or 'cauchy')")


def _edge_rt(G: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor, dtype: torch.dtype):
    """``R_ij, t_ij`` of ``G_ij = G_j G_i^-1`` (world-to-camera poses ``G [N, 7]``), via rotation matrices."""
    R = quat_to_rotmat(G[:, 3:])
    Rij = torch.bmm(R[jj], R[ii].transpose(1, 2))
    tij = G[jj, :3] - torch.bmm(Rij, G[ii, :3].unsqueeze(-1)).squeeze(-1)
    return Rij.to(dtype), tij.to(dtype)


def _residuals(G, d, ii, jj, target, intr, h, w, min_depth, jacobians):
    """``target [E, 2, P]`` -> residuals ``ru, rv [E, P]`` and :func:`project_points`' output."""
    R, t = _edge_rt(G, ii, jj, d.dtype)
    out = project_points(R, t, d[ii], intr, h, w, min_depth, jacobians)
    return target[:, 0] - out["u"], target[:, 1] - out["v"], out


def _cost(conf, valid, ru, rv) -> float:
    return float((valid * (conf[:, 0] * ru * ru + conf[:, 1] * rv * rv)).sum())


def _robust_cost(conf, valid, ru, rv, kind: Optional[str], scale: float) -> float:
    """The objective the IRLS weights of :func:`_robust_weights` minimise: each pixel's ``conf``-weighted squared
    residual times ``2 rho(n) / n^2`` (``n`` the 2D residual; exact where ``conf`` is the same for u and v)."""
    if kind is None or kind == "none":
        return _cost(conf, valid, ru, rv)
    n2 = (ru * ru + rv * rv).clamp(min=1e-12)
    s2 = scale * scale
    if kind == "huber":
        n = n2.sqrt()
        f = torch.where(n <= scale, torch.ones_like(n), (2.0 * scale * n - s2) / n2)
    else:  # cauchy: rho = s^2 / 2 log(1 + n^2 / s^2)
        f = torch.log1p(n2 / s2) * (s2 / n2)
    return _cost(conf, valid * f, ru, rv)


def weighted_cost(graph: "FrameGraph", obs: EdgeObservations, min_depth: float = 0.2) -> float:
    """``sum conf * valid * |target - reprojection|^2`` for the graph's current state."""
    h, w = graph.ba_shape
    dtype = torch.float64 if graph.device.type == "cpu" else torch.float32
    target, conf = _flat_obs(obs, dtype)
    G = se3_inv(graph.poses)
    ru, rv, out = _residuals(G, graph.disps.reshape(graph.n, -1).to(dtype), obs.ii.to(graph.device),
                             obs.jj.to(graph.device), target, graph.intrinsics, h, w, min_depth, False)
    return _cost(conf, out["valid"], ru, rv)


def _flat_obs(obs: EdgeObservations, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``target, conf [E, 2, P]``."""
    E = obs.target.shape[0]
    return obs.target.reshape(E, 2, -1).to(dtype), obs.weight.reshape(E, 2, -1).to(dtype)


def _chunk_obs(target: torch.Tensor, conf: torch.Tensor, idx, dtype: torch.dtype):
    """``target, conf [Ec, 2, P]`` of one chunk of edges (``conf`` clamped to >= 0)."""
    return target[idx].to(dtype), conf[idx].to(dtype).clamp(min=0.0)


def _report_reject(report: OptimizerReport, msg: str) -> OptimizerReport:
    report.rejected = True
    report.message = msg
    _log_once(msg)
    return report


def dense_ba(
    graph: "FrameGraph",
    obs: EdgeObservations,
    free: torch.Tensor,
    iters: int = 2,
    lm: float = 1e-4,
    ep: float = 0.1,
    depth_damping: float | torch.Tensor = 1e-3,
    depth_free: Optional[torch.Tensor] = None,
    min_depth: float = 0.2,
    robust: Optional[str] = None,
    robust_scale: float = 2.0,
    weight_scale: float = WEIGHT_SCALE,
    dtype: Optional[torch.dtype] = None,
    max_chunk_pixels: int = 500_000,
    max_iters: Optional[int] = None,
    rel_tol: float = 0.0,
) -> OptimizerReport:
    """Run ``iters`` Gauss-Newton/LM iterations of dense BA on ``graph`` in place (see the module docstring).

    ``max_iters`` (> ``iters``): after ``iters`` iterations go on, up to ``max_iters``, while the last iteration
    lowered the objective (the robust one: :func:`_robust_cost`; the reported costs stay plain) by more than
    ``rel_tol`` of it (the check is the cost evaluation that ends every call, so a call that stops costs nothing
    extra).  Why: with the damping (``ep``, ``eta``) a step covers only part of the way
    along the weakly observed directions - the monocular scale first - and where the data keep pulling (straight
    drives) an unconverged window leaves its remainder to drift, while where the cost has settled (most windows of
    fast hand-held motion) more iterations only follow noise (bench/RESULTS.md, issue 13, session 2026-12-03).

    ``free`` / ``depth_free``: bool ``[n]``.  ``depth_damping``: DROID's ``eta``, a float or a tensor broadcastable
    to ``[n, h, w]``; when ``obs.depth_damping`` (learned, per keyframe) is given it is used instead, as DROID:
    ``0.2 * obs.depth_damping + 1e-7``.  ``robust``: None, ``'huber'`` or ``'cauchy'`` IRLS on the 2D residual with
    ``robust_scale`` pixels.  ``dtype``: per-pixel arithmetic (default float32 - the graph stores float32
    disparities anyway, and noise-free problems still converge to ~1e-7; the reduced pose system, the pose
    updates and the poses are always float64).  ``max_chunk_pixels``: edge-pixels linearised at once (the
    per-pixel temporaries of one chunk of whole sources; a source with more edge-pixels is a chunk of its own).
    """
    N = graph.n
    h, w = graph.ba_shape
    P = h * w
    dev = graph.device
    dtype = dtype or torch.float32
    ii = obs.ii.to(dev, torch.int64).reshape(-1)
    jj = obs.jj.to(dev, torch.int64).reshape(-1)
    E = int(ii.shape[0])
    free = torch.as_tensor(free, dtype=torch.bool, device=dev).reshape(-1)
    report = OptimizerReport(num_edges=E)
    if free.shape[0] != N:
        raise ValueError(f"free must have one entry per keyframe ({N}), got {free.shape[0]}")
    if E == 0 or N == 0:
        report.message = "no edges"
        return report
    if int(ii.min()) < 0 or int(jj.min()) < 0 or int(ii.max()) >= N or int(jj.max()) >= N:
        raise IndexError(f"edge index out of range for {N} keyframes")
    if tuple(obs.target.shape) != (E, 2, h, w) or tuple(obs.weight.shape) != (E, 2, h, w):
        raise ValueError(f"obs target/weight must be [{E}, 2, {h}, {w}], got {tuple(obs.target.shape)}")
    if depth_free is None:
        depth_free = torch.zeros(N, dtype=torch.bool, device=dev)
        depth_free[ii] = True
    else:
        depth_free = torch.as_tensor(depth_free, dtype=torch.bool, device=dev).reshape(-1).clone()
    # ---- input checks
    for name, t in (("poses", graph.poses), ("disps", graph.disps), ("target", obs.target), ("weight", obs.weight)):
        if not _all_finite(t):
            return _report_reject(report, f"dense_ba: non-finite values in {name}; estimate left unchanged")
    intr = graph.intrinsics
    target_all = obs.target.reshape(E, 2, P).to(dev)  # views: chunks are cast / clamped when used
    conf_all = obs.weight.reshape(E, 2, P).to(dev)
    if obs.depth_damping is not None:
        eta_map = (0.2 * obs.depth_damping.to(dev, dtype) + 1e-7).reshape(N, P)
    else:
        eta_t = torch.as_tensor(depth_damping, dtype=dtype, device=dev)
        eta_map = eta_t.expand(N, h, w).reshape(N, P) if eta_t.dim() > 0 else eta_t.expand(N, P)
    eta_src = obs.depth_damping if obs.depth_damping is not None else torch.as_tensor(depth_damping)
    if not _all_finite(eta_src) or bool((eta_src < 0).any()):
        return _report_reject(report, "dense_ba: non-finite or negative depth damping; estimate left unchanged")
    dprior, lprior = obs.disp_prior, obs.dist_prior
    if dprior is not None:
        m = int(dprior.ids.shape[0])
        if tuple(dprior.disp.shape) != (m, h, w):
            raise ValueError(f"obs.disp_prior.disp must be [{m}, {h}, {w}], got {tuple(dprior.disp.shape)}")
        if m and (int(dprior.ids.min()) < 0 or int(dprior.ids.max()) >= N):
            raise IndexError(f"obs.disp_prior.ids out of range for {N} keyframes")
        if not (_all_finite(dprior.disp) and _all_finite(dprior.weight)) or bool((dprior.weight < 0).any()):
            return _report_reject(report, "dense_ba: non-finite disparity prior or negative prior weight; "
                                          "estimate left unchanged")

    if lprior is not None:
        dpi, dpj = lprior.ii.reshape(-1), lprior.jj.reshape(-1)
        if dpi.numel() and (int(torch.minimum(dpi, dpj).min()) < 0 or int(torch.maximum(dpi, dpj).max()) >= N):
            raise IndexError(f"obs.dist_prior.ii / jj out of range for {N} keyframes")
        if not (_all_finite(lprior.dist) and _all_finite(lprior.weight)) \
                or bool((lprior.dist <= 0).any()) or bool((lprior.weight < 0).any()):
            return _report_reject(report, "dense_ba: non-finite or non-positive distance prior, or a negative "
                                          "weight; estimate left unchanged")

    free_idx = torch.nonzero(free).squeeze(1)
    F = int(free_idx.shape[0])
    pose_map = torch.full((N,), -1, dtype=torch.int64, device=dev)
    pose_map[free_idx] = torch.arange(F, device=dev)
    src = torch.nonzero(depth_free).squeeze(1)
    # only sources that actually have edges get depth unknowns
    has_edge = torch.zeros(N, dtype=torch.bool, device=dev)
    has_edge[ii] = True
    src = src[has_edge[src]]
    Ns = int(src.shape[0])
    src_map = torch.full((N,), -1, dtype=torch.int64, device=dev)
    src_map[src] = torch.arange(Ns, device=dev)
    report.num_free_poses = F
    # the disparity prior per depth source (target, alpha) [Ns, P]: DROID's disps_sens term, C += alpha,
    # w += alpha (d_sens - d); sources without one get alpha 0
    prior = None
    if dprior is not None and Ns > 0:
        at = torch.full((N,), -1, dtype=torch.int64, device=dev)
        at[dprior.ids.to(dev, torch.int64)] = torch.arange(int(dprior.ids.shape[0]), device=dev)
        row = at[src]
        has = torch.nonzero(row >= 0).squeeze(1)
        if has.numel():
            tgt_s = torch.zeros(Ns, P, dtype=dtype, device=dev)
            alpha_s = torch.zeros(Ns, P, dtype=dtype, device=dev)
            tgt_s[has] = dprior.disp.to(dev, dtype).reshape(-1, P)[row[has]]
            alpha_s[has] = dprior.weight.to(dev, dtype).reshape(-1, P)[row[has]]
            prior = (tgt_s, alpha_s)

    G = se3_inv(graph.poses)  # world-to-camera, updated by left retraction
    d = graph.disps.reshape(N, P).to(dtype, copy=True)  # the graph itself is written only at the end
    # chunks of whole sources (then of fixed-depth edges) with their static scatter plans (module docstring)
    chunks = plan_chunks(ii, jj, pose_map, src_map[ii], Ns, F, P, max_chunk_pixels)
    cached = _chunk_obs(target_all, conf_all, chunks[0].idx, dtype) if len(chunks) == 1 else None
    sparse = dev.type == "cpu" and F > SPARSE_MIN_POSES

    def linearise(ch, jac):
        """Residuals, projection output, per-pixel weights ``wu, wv`` and ``conf`` of one chunk."""
        tgt, cf = cached if cached is not None else _chunk_obs(target_all, conf_all, ch.idx, dtype)
        ru, rv, out = _residuals(G, d, ch.ii, ch.jj, tgt, intr, h, w, min_depth, jac)
        if not jac:
            return ru, rv, out, None, None, cf
        del out["u"], out["v"], out["z"]
        valid = out["valid"].to(dtype)
        rw = _robust_weights(ru, rv, robust, robust_scale)
        vw = valid * weight_scale if rw is None else valid * rw * weight_scale
        return ru, rv, out, cf[:, 0] * vw, cf[:, 1] * vw, cf

    n_iters = max(0, int(iters))
    n_max = max(n_iters, int(max_iters)) if max_iters is not None else n_iters
    adaptive = n_max > n_iters

    def dist_terms():
        """The distance prior's Gauss-Newton terms at the current poses (:mod:`.ba_distance`), or None."""
        if lprior is None or lprior.dist.numel() == 0:
            return None
        return distance_prior_terms(G, pose_map, lprior.ii, lprior.jj, lprior.dist, lprior.weight, weight_scale, F)

    def prior_cost() -> float:
        """The priors' part of the objective, in the units of the flow cost (the disparity prior's alpha /
        weight_scale; the distance prior's alpha)."""
        dist = dist_terms()
        total = 0.0 if dist is None else dist[4]
        if prior is None:
            return total
        return total + float((prior[1] * (d[src] - prior[0]) ** 2).sum()) / weight_scale

    def current_cost(with_robust: bool) -> tuple[float, float]:
        """(the reported plain cost, the robust objective if ``with_robust`` else 0) at the current state; the
        objective includes the disparity prior, the reported cost does not (it stays the flow residual's)"""
        total, rtotal = 0.0, prior_cost() if with_robust else 0.0
        for ch in chunks:
            ru, rv, out, _, _, cf = linearise(ch, False)
            total += _cost(cf, out["valid"], ru, rv)
            if with_robust:
                rtotal += _robust_cost(cf, out["valid"], ru, rv, robust, robust_scale)
            del ru, rv, out, cf
        return total, rtotal

    cost0 = cost1 = None
    problems: list[str] = []
    for it in range(n_max):
        # ---- assemble the reduced pose system chunk by chunk; per-pixel temporaries live for one chunk only
        v = torch.zeros(F, 6, dtype=torch.float64, device=dev)
        H = torch.zeros(F * F, 36, dtype=torch.float64, device=dev) if F > 0 and not sparse else None
        sp_dest, sp_vals = [], []
        Cinv = torch.zeros(Ns, P, dtype=dtype, device=dev)
        wd = torch.zeros(Ns, P, dtype=dtype, device=dev)
        kept = None  # (chunk, B, Ad) of the last chunk, reused by the back-substitution
        cost_it = 0.0
        rcost_it = prior_cost() if adaptive and it + 1 >= n_iters else 0.0
        for ci, ch in enumerate(chunks):
            ru, rv, out, wu, wv, cf = linearise(ch, "parts")
            if cost0 is None:
                cost_it += _cost(cf, out["valid"], ru, rv)
            if adaptive and it + 1 >= n_iters:  # only the iterations whose gain is tested need it
                rcost_it += _robust_cost(cf, out["valid"], ru, rv, robust, robust_scale)
            s_ch = src[ch.s0:ch.s1]
            eta_c, wd0 = eta_map[s_ch], None
            if prior is not None:  # the prior's curvature joins the depth diagonal, its pull the depth gradient
                a_ch = prior[1][ch.s0:ch.s1]
                eta_c, wd0 = eta_c + a_ch, a_ch * (prior[0][ch.s0:ch.s1] - d[s_ch])
            blocks, q, Ad, Ci, wdc, B = assemble_chunk(ch, ru, rv, wu, wv, out, eta_c, F,
                                                       want_B=ci == len(chunks) - 1, wd0=wd0)
            del ru, rv, out, wu, wv, cf
            if ch.ns > 0:
                Cinv[ch.s0:ch.s1], wd[ch.s0:ch.s1] = Ci, wdc
            if B is not None:
                kept = (ch, B, Ad)
            if F > 0:
                qi = -torch.bmm(Ad.transpose(1, 2), q.unsqueeze(-1)).squeeze(-1)
                v.index_add_(0, ch.v_dest, torch.cat([q[ch.v_sel[0]], qi[ch.v_sel[1]]]))
                vals = torch.cat([blk[sel] for blk, sel in zip(blocks, ch.H_sel)])  # [nblocks, 6, 6]
                if sparse:
                    sp_dest.append(ch.H_dest)
                    sp_vals.append(vals)
                else:
                    H.index_add_(0, ch.H_dest, vals.reshape(-1, 36))
            del blocks, q, Ad, B
        if cost0 is None:
            cost0 = cost_it
        dist = dist_terms() if F > 0 else None
        if dist is not None:  # the distance prior's blocks join the reduced pose system (ba_distance.py)
            v.index_add_(0, dist[2], dist[3])
            if sparse:
                sp_dest.append(dist[0])
                sp_vals.append(dist[1])
            else:
                H.index_add_(0, dist[0], dist[1].reshape(-1, 36))
        dxi = torch.zeros(F, 6, dtype=torch.float64, device=dev)
        if F > 0:
            b = v.reshape(-1)
            solved = False
            # ---- solve the reduced pose system (LM-damped; 10x / 100x more damping if it fails)
            if sparse:
                H_dest = torch.cat(sp_dest)
                Hs = sparse_block_matrix(torch.div(H_dest, F, rounding_mode="floor"), H_dest % F,
                                         torch.cat(sp_vals), F)
                del sp_vals, H_dest
                diag = torch.from_numpy(Hs.diagonal()).to(dev, torch.float64)
            else:
                S = H.reshape(F, F, 6, 6).permute(0, 2, 1, 3).reshape(6 * F, 6 * F)
                S = 0.5 * (S + S.T)
                del H
                diag = torch.diagonal(S).clone()
            for boost in (1.0, 10.0, 100.0):
                damp = ep * boost + lm * boost * diag
                x = sparse_solve(Hs, damp.cpu().numpy(), b) if sparse else solve_spd(S + torch.diag(damp), b)
                if x is not None:
                    dxi = x.reshape(F, 6)
                    solved = True
                    if boost > 1.0:
                        problems.append(f"iteration {it}: factorisation needed {boost:g}x damping")
                    break
            if not solved:
                report.iterations = it
                report.cost_before = report.cost_after = cost0 if cost0 is not None else float("nan")
                return _report_reject(report, f"dense_ba: pose system not positive definite even with 100x damping "
                                              f"(iteration {it}); previous estimate kept")
        # ---- back-substitute depths per source: dd = C^-1 (w - sum_e Ej (dxi_jj - Ad dxi_ii))
        dd = Cinv * wd
        if Ns > 0 and F > 0:
            xi_full = torch.zeros(N, 6, dtype=torch.float64, device=dev)
            xi_full[free_idx] = dxi
            done = None
            if kept is not None:
                (done, B, Ad), kept = kept, None
                s_ = slice(done.s0, done.s1)
                dd[s_] = backsub_chunk(done, B, Ad, xi_full, Cinv[s_], wd[s_])
                B = Ad = None
            for ch in chunks:  # the other chunks: E^T recomputed at the same linearisation point
                if ch.ns > 0 and ch is not done:
                    s_, m = slice(ch.s0, ch.s1), ch.n_src
                    _, _, out, wu, wv, _ = linearise(ch, "parts")
                    B = depth_rows(ch, out["JuT"], out["JvT"], wu[:m] * out["Jdu"][:m], wv[:m] * out["Jdv"][:m],
                                   Cinv[s_].sqrt())
                    dd[s_] = backsub_chunk(ch, B, out["Ad"].double(), xi_full, Cinv[s_], wd[s_])
                    del out, wu, wv, B
        if not (_all_finite(dxi) and _all_finite(dd)):
            report.iterations = it
            report.cost_before = report.cost_after = cost0 if cost0 is not None else float("nan")
            return _report_reject(report, "dense_ba: non-finite update; previous estimate kept")
        if F > 0:
            G[free_idx] = se3_mul(se3_exp(dxi), G[free_idx])
        if Ns > 0:
            d[src] = (d[src] + dd).clamp(min=DISP_MIN)
        report.iterations = it + 1
        if n_iters <= it + 1 < n_max:  # adaptive: stop once the last iteration gained too little
            cost1, rcost1 = current_cost(with_robust=True)
            if not rcost_it - rcost1 > rel_tol * rcost_it:
                break
            cost1 = None

    if cost1 is None:
        cost1 = current_cost(with_robust=False)[0]
    if cost0 is None:
        cost0 = cost1
    report.cost_before, report.cost_after = cost0, cost1
    newT = se3_inv(G)
    if not (math.isfinite(cost1) and _all_finite(newT) and _all_finite(d)):
        report.cost_after = cost0
        return _report_reject(report, "dense_ba: non-finite state after update; previous estimate kept")
    if F > 0:
        graph.set_poses(free_idx, newT[free_idx])
    if Ns > 0:
        graph.set_disps(src, d[src].reshape(Ns, h, w).float())
    if problems:
        report.message = "; ".join(problems)
        _log_once("dense_ba: " + report.message)
    return report


def motion_only_ba(
    pose_wc: torch.Tensor,
    kf_pose_wc: torch.Tensor,
    kf_disp: torch.Tensor,
    intr: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor,
    iters: int = 4,
    lm: float = 1e-4,
    ep: float = 0.1,
    min_depth: float = 0.2,
    weight_scale: float = WEIGHT_SCALE,
    robust: Optional[str] = None,
    robust_scale: float = 2.0,
):
    """Estimate the pose ``T_wc [7]`` of a new frame from flow targets of a fixed reference keyframe.

    ``target [2, h, w]``: positions in the new frame of the keyframe's pixels; ``weight [2, h, w]`` their
    confidences.  ``robust``/``robust_scale``: IRLS kernel as in :func:`dense_ba`.  Returns
    ``(pose_wc float64 [7], final cost)`` with the cost as in :func:`dense_ba` (no robust re-weighting).  On
    non-finite input or update the initial pose is returned (cost NaN if it could not be evaluated).

    Batched: ``pose_wc [F, 7]`` with ``target``/``weight [F, 2, h, w]`` solves ``F`` independent frames against the
    same keyframe at once (one set of tensor ops instead of ``F``: the frames between two keyframes are placed in
    one call) and returns ``(poses [F, 7], costs float64 [F])``; each frame behaves as if solved alone.
    """
    batched = pose_wc.dim() == 2
    dev = kf_disp.device
    dtype = torch.float64 if dev.type == "cpu" else torch.float32
    h, w = kf_disp.shape[-2:]
    pose0 = pose_wc.to(dev, torch.float64).reshape(-1, 7)  # [F, 7]
    F = pose0.shape[0]
    kf = kf_pose_wc.to(dev, torch.float64).reshape(1, 7)  # T_wc of the keyframe = G_kf^-1
    target = target.reshape(F, 2, -1)
    weight = weight.reshape(F, 2, -1)
    ok_in = torch.ones(F, dtype=torch.bool, device=dev)
    for t in (kf, kf_disp):
        if not _all_finite(t):
            ok_in[:] = False
    for t in (pose0, target, weight):
        if not _all_finite(t):
            ok_in &= torch.isfinite(t.reshape(F, -1)).all(-1).to(dev)
    if not bool(ok_in.all()):
        _log_once("motion_only_ba: non-finite input; initial pose returned")
        if not bool(ok_in.any()):
            out = pose0.clone()
            nan = torch.full((F,), float("nan"), dtype=torch.float64)
            return (out, nan) if batched else (out[0], float("nan"))
    tgt_u, tgt_v = target[:, 0].to(dtype), target[:, 1].to(dtype)  # [F, P]
    conf_u, conf_v = weight[:, 0].to(dtype).clamp(min=0), weight[:, 1].to(dtype).clamp(min=0)
    dd = kf_disp.reshape(1, -1).to(dtype).expand(F, -1)
    zero = torch.zeros_like(tgt_u)
    tgt_u, tgt_v = torch.where(ok_in[:, None], tgt_u, zero), torch.where(ok_in[:, None], tgt_v, zero)
    G = se3_inv(torch.where(ok_in[:, None], pose0, kf.expand(F, 7)))  # [F, 7] world-to-camera

    R_kf = quat_to_rotmat(kf[:, 3:])  # [1, 3, 3]
    t_kf = kf[:, :3].unsqueeze(-1)  # [1, 3, 1]

    def evaluate(G, jac):
        # camera kf -> camera new, G o T_kf, composed as rotation matrices (the quaternion product, its
        # normalisation and a second quaternion -> matrix conversion were ~40 tiny ops per evaluation)
        R_G = quat_to_rotmat(G[:, 3:])  # [F, 3, 3]
        R = torch.matmul(R_G, R_kf)
        t = torch.baddbmm(G[:, :3].unsqueeze(-1), R_G, t_kf.expand(F, 3, 1)).squeeze(-1)
        out = project_points(R.to(dtype), t.to(dtype), dd, intr, h, w, min_depth, "pose" if jac else False)
        return tgt_u - out["u"], tgt_v - out["v"], out

    active = ok_in.clone()  # a frame whose system fails to factorise stops (keeps its last pose)
    eye = torch.eye(6, dtype=torch.float64, device=dev)
    for _ in range(max(0, int(iters))):
        ru, rv, out = evaluate(G, True)
        valid = out["valid"].to(dtype)
        wu, wv = conf_u * valid * weight_scale, conf_v * valid * weight_scale  # [F, P]
        rw = _robust_weights(ru, rv, robust, robust_scale)
        if rw is not None:
            wu, wv = wu * rw, wv * rw
        JuT, JvT = out["JuT"], out["JvT"]  # [F, 6, P]
        Hm = torch.bmm(JuT * wu[:, None], JuT.transpose(1, 2)) + torch.bmm(JvT * wv[:, None], JvT.transpose(1, 2))
        b = rowvec(wu * ru, JuT) + rowvec(wv * rv, JvT)  # [F, 6]
        Hm = Hm.double()
        A = Hm + eye * (ep + lm * torch.diagonal(Hm, dim1=-2, dim2=-1)).unsqueeze(-1)
        L, info = torch.linalg.cholesky_ex(A)
        ok = info == 0
        if not bool(ok.all()):
            L = torch.where(ok[:, None, None], L, eye.expand_as(L))
        dx = torch.cholesky_solve(b.double().unsqueeze(-1), L).squeeze(-1)  # [F, 6]
        ok &= torch.isfinite(dx).all(-1)
        active &= ok
        if not bool(active.any()):
            break
        dx = torch.where(active[:, None], dx, torch.zeros_like(dx))
        G = se3_mul(se3_exp(dx), G)
    ru, rv, out = evaluate(G, False)
    valid = out["valid"].to(dtype)
    cost = ((conf_u * ru * ru + conf_v * rv * rv) * valid).sum(-1).double()  # [F]
    T = se3_inv(G)
    good = ok_in & torch.isfinite(cost) & torch.isfinite(T).all(-1)
    if not bool(good.all()):
        if bool((ok_in & ~good).any()):
            _log_once("motion_only_ba: non-finite result; initial pose returned")
        T = torch.where(good[:, None], T, pose0)
        cost = torch.where(good, cost, torch.full_like(cost, float("nan")))
    if batched:
        return T, cost
    return T[0], float(cost[0])
