"""One dense BA call's problem (:func:`.ba.dense_ba`): the unknowns' index maps, the depth damping and disparity
prior per depth source, the chunk plan, and the pieces of a Gauss-Newton iteration: linearise and accumulate the
reduced pose system chunk by chunk, solve it, back-substitute the depths, apply the step.  The module docstring of
:mod:`.ba` states the maths; :mod:`.ba_schur` holds the per-chunk Schur algebra."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Optional

import numpy as np
import torch

from . import ba_linalg
from .ba_distance import distance_prior_terms
from .ba_linalg import sparse_block_matrix, sparse_solve
from .ba_residuals import DISP_MIN, chunk_obs, cost, edge_rt, residuals, robust_weights
from .ba_schur import assemble_chunk, backsub_chunk, depth_rows, plan_chunks, pose_blocks
from .lie import se3_exp, se3_inv, se3_mul
from .projective import _adjoint, _rays

if TYPE_CHECKING:  # pragma: no cover
    from ..slam.graph import FrameGraph
    from ..types import EdgeObservations
    from .ba import BAOptions

__all__ = ["BAInputs", "DenseBAProblem", "PoseSystem", "fused_available"]

FUSED_MIN_CONF = 1e-20  # confidences below this are zeroed for the compiled loops (DenseBAProblem._chunk_obs)
_UPPER = torch.triu_indices(6, 6)  # the order of ba_kernels' 21 block sums
_KERNELS: list = []  # the imported ba_kernels module, or None when numba is missing


def ba_kernels():
    """:mod:`.ba_kernels`, imported on first use (numba compiles or loads its cached loops then), or None."""
    if not _KERNELS:
        try:
            from . import ba_kernels as mod
        except ImportError:  # pragma: no cover - numba is a dependency; the torch path remains
            mod = None
        _KERNELS.append(mod)
    return _KERNELS[0]


def fused_available(opt: "BAOptions", dtype: torch.dtype, dev: torch.device, *tensors: torch.Tensor) -> bool:
    """Whether a call's per-pixel work runs through :mod:`.ba_kernels`: float32 on the CPU without autograd, the
    Cauchy kernel or none (Huber, float64 and CUDA take the torch path)."""
    return (opt.compiled and dtype == torch.float32 and dev.type == "cpu" and opt.robust in (None, "none", "cauchy")
            and not any(t.requires_grad for t in tensors) and ba_kernels() is not None)


@dataclass
class BAInputs:
    """The checked inputs of one call: edges, unknown masks and per-pixel arrays on the graph's device."""

    ii: torch.Tensor  # [E] int64 source keyframe of each edge
    jj: torch.Tensor  # [E] int64 target keyframe
    free: torch.Tensor  # [N] bool: pose unknown
    depth_free: torch.Tensor  # [N] bool: inverse depths unknown (only sources of an edge get them)
    target: torch.Tensor  # [E, 2, P] flow targets (cast / clamped per chunk when used)
    conf: torch.Tensor  # [E, 2, P] confidences
    eta: torch.Tensor  # [N, P] depth damping of each keyframe's pixels
    dtype: torch.dtype  # per-pixel arithmetic


@dataclass
class PoseSystem:
    """One iteration's reduced pose system and the per-source depth terms needed to back-substitute."""

    v: torch.Tensor  # [F, 6] float64 gradient
    H: Optional[torch.Tensor]  # [F * F, 36] float64 dense blocks (None: sparse, or no free pose)
    Cinv: torch.Tensor  # [Ns, P] inverse depth diagonal
    wd: torch.Tensor  # [Ns, P] depth gradient
    sp_dest: list = field(default_factory=list)  # sparse: block destinations in [F * F] ...
    sp_vals: list = field(default_factory=list)  # ... and their 6x6 values
    kept: Optional[tuple] = None  # (chunk, B, Ad) of the last chunk, reused by the back-substitution
    cost: float = 0.0  # the plain cost at the linearisation point (first iteration only)


class DenseBAProblem:
    """State of one :func:`.ba.dense_ba` call: poses ``G`` (world-to-camera, left retraction) and inverse depths
    ``d`` are copies; the graph is written only by :meth:`write` after the last iteration."""

    def __init__(self, graph: "FrameGraph", obs: "EdgeObservations", inp: BAInputs, opt: "BAOptions"):
        N = graph.n
        self.h, self.w = graph.ba_shape
        P = self.h * self.w
        dev = self.dev = graph.device
        self.opt, self.dtype, self.intr = opt, inp.dtype, graph.intrinsics
        self.target, self.conf, self.eta = inp.target, inp.conf, inp.eta
        self.free_idx = torch.nonzero(inp.free).squeeze(1)
        F = self.F = int(self.free_idx.shape[0])
        self.pose_map = torch.full((N,), -1, dtype=torch.int64, device=dev)
        self.pose_map[self.free_idx] = torch.arange(F, device=dev)
        src = torch.nonzero(inp.depth_free).squeeze(1)
        # only sources that actually have edges get depth unknowns
        has_edge = torch.zeros(N, dtype=torch.bool, device=dev)
        has_edge[inp.ii] = True
        self.src = src[has_edge[src]]
        Ns = self.Ns = int(self.src.shape[0])
        src_map = torch.full((N,), -1, dtype=torch.int64, device=dev)
        src_map[self.src] = torch.arange(Ns, device=dev)
        self.prior = self._disp_prior(obs.disp_prior, P) if obs.disp_prior is not None and Ns > 0 else None
        self.dist_prior = obs.dist_prior
        self.G = se3_inv(graph.poses)  # world-to-camera, updated by left retraction
        self.d = graph.disps.reshape(N, P).to(self.dtype, copy=True)
        # chunks of whole sources (then of fixed-depth edges) with their static scatter plans (.ba docstring)
        self.chunks = plan_chunks(inp.ii, inp.jj, self.pose_map, src_map[inp.ii], Ns, F, P, opt.max_chunk_pixels)
        self.fused = fused_available(opt, self.dtype, dev, self.target, self.conf, self.d, graph.poses)
        self.cached = self._chunk_obs(self.chunks[0]) if len(self.chunks) == 1 else None
        self.sparse = dev.type == "cpu" and F > ba_linalg.SPARSE_MIN_POSES

    def _disp_prior(self, dprior, P: int):
        """The disparity prior per depth source ``(target, alpha) [Ns, P]`` (DROID's disps_sens term: ``C +=
        alpha``, ``w += alpha (d_sens - d)``); sources without one get alpha 0.  None when no source has one."""
        dev, dtype, Ns = self.dev, self.dtype, self.Ns
        at = torch.full((self.pose_map.shape[0],), -1, dtype=torch.int64, device=dev)
        at[dprior.ids.to(dev, torch.int64)] = torch.arange(int(dprior.ids.shape[0]), device=dev)
        row = at[self.src]
        has = torch.nonzero(row >= 0).squeeze(1)
        if not has.numel():
            return None
        tgt_s = torch.zeros(Ns, P, dtype=dtype, device=dev)
        alpha_s = torch.zeros(Ns, P, dtype=dtype, device=dev)
        tgt_s[has] = dprior.disp.to(dev, dtype).reshape(-1, P)[row[has]]
        alpha_s[has] = dprior.weight.to(dev, dtype).reshape(-1, P)[row[has]]
        return tgt_s, alpha_s

    # ------------------------------------------------------------------------------------------ linearisation
    def _obs(self, ch):
        """``target, conf [Ec, 2, P]`` of one chunk (cast once when the problem is one chunk)."""
        return self.cached if self.cached is not None else self._chunk_obs(ch)

    def _chunk_obs(self, ch):
        """``target, conf [Ec, 2, P]`` of one chunk; for the compiled loops contiguous, with the confidences below
        ``FUSED_MIN_CONF`` zeroed (denormal floats slow every product they enter; such weights change no sum)."""
        if not self.fused:
            return chunk_obs(self.target, self.conf, ch.idx, self.dtype)
        cf = self.conf[ch.idx].to(self.dtype, copy=True)
        return self.target[ch.idx].to(self.dtype).contiguous(), cf.masked_fill_(~(cf >= FUSED_MIN_CONF), 0.0)

    def linearise(self, ch, jac):
        """Residuals, projection output, per-pixel weights ``wu, wv`` and ``conf`` of one chunk."""
        opt = self.opt
        tgt, cf = self._obs(ch)
        ru, rv, out = residuals(self.G, self.d, ch.ii, ch.jj, tgt, self.intr, self.h, self.w, opt.min_depth, jac)
        if not jac:
            return ru, rv, out, None, None, cf
        del out["u"], out["v"], out["z"]
        valid = out["valid"].to(self.dtype)
        rw = robust_weights(ru, rv, opt.robust, opt.robust_scale)
        vw = valid * opt.weight_scale if rw is None else valid * rw * opt.weight_scale
        return ru, rv, out, cf[:, 0] * vw, cf[:, 1] * vw, cf

    def _fused_args(self, ch) -> tuple[tuple, torch.Tensor]:
        """The arguments of :mod:`.ba_kernels`' passes for one chunk, and its adjoints ``Ad [Ec, 6, 6]`` (float64)."""
        opt, dtype = self.opt, self.dtype
        R, t = edge_rt(self.G, ch.ii, ch.jj, dtype)
        fx, fy, cx, cy = (float(v) for v in self.intr.tolist())
        rays = _rays(self.h, self.w, fx, fy, cx, cy, dtype, self.dev)
        tgt, cf = self._obs(ch)
        ls = ch.ls if ch.ls is not None else torch.zeros(0, dtype=torch.int64)
        inv_s2 = 1.0 / opt.robust_scale ** 2 if opt.robust == "cauchy" else 0.0
        args = (R.contiguous().numpy(), t.contiguous().numpy(), self.d.numpy(), ch.ii.contiguous().numpy(),
                rays[0].numpy(), rays[1].numpy(), tgt.numpy(), cf.numpy(), fx, fy, cx, cy, opt.min_depth, inv_s2,
                opt.weight_scale, ch.n_src, ls.contiguous().numpy())
        return args, _adjoint(R, t, dtype, self.dev).double()

    def _fused_rows(self, args: tuple, m: int, Cinv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, sC)``: the depth rows ``[m, 6, P]`` of a chunk's source edges (:func:`.ba_schur.depth_rows`)."""
        sC = Cinv.sqrt()
        B = torch.empty(m, 6, self.h * self.w, dtype=self.dtype)
        ba_kernels().pass_rows(*args, sC.numpy(), B.numpy())
        return B, sC

    def current_cost(self) -> float:
        """The reported plain cost at the current state (the flow residual's; no prior, no robust weights)."""
        total = 0.0
        if self.fused:
            for ch in self.chunks:
                args, _ = self._fused_args(ch)
                args = args[:-2] + (0, args[-1])  # no depth terms
                acc = torch.empty(len(ch.ii), 28, dtype=self.dtype)
                ba_kernels().pass_blocks(*args, np.empty((0, 0), np.float32), np.empty((0, 0), np.float32),
                                         acc.numpy())
                total += float(acc[:, 27].double().sum())
            return total
        for ch in self.chunks:
            ru, rv, out, _, _, cf = self.linearise(ch, False)
            total += cost(cf, out["valid"], ru, rv)
            del ru, rv, out, cf
        return total

    def dist_terms(self):
        """The distance prior's Gauss-Newton terms at the current poses (:mod:`.ba_distance`), or None."""
        lp = self.dist_prior
        if lp is None or lp.dist.numel() == 0:
            return None
        return distance_prior_terms(self.G, self.pose_map, lp.ii, lp.jj, lp.dist, lp.weight, self.opt.weight_scale,
                                    self.F)

    def assemble(self, with_cost: bool) -> PoseSystem:
        """Linearise every chunk and accumulate the reduced pose system; per-pixel temporaries live for one chunk
        only.  ``with_cost``: also sum the plain cost at this linearisation point."""
        F, Ns, P, dev, dtype = self.F, self.Ns, self.h * self.w, self.dev, self.dtype
        sysm = PoseSystem(v=torch.zeros(F, 6, dtype=torch.float64, device=dev),
                          H=torch.zeros(F * F, 36, dtype=torch.float64, device=dev)
                          if F > 0 and not self.sparse else None,
                          Cinv=torch.zeros(Ns, P, dtype=dtype, device=dev),
                          wd=torch.zeros(Ns, P, dtype=dtype, device=dev))
        for ci, ch in enumerate(self.chunks):
            if self.fused:
                self._add_chunk_fused(sysm, ch, with_cost, last=ci == len(self.chunks) - 1)
                continue
            ru, rv, out, wu, wv, cf = self.linearise(ch, "parts")
            if with_cost:
                sysm.cost += cost(cf, out["valid"], ru, rv)
            self._add_chunk(sysm, ch, ru, rv, out, wu, wv, last=ci == len(self.chunks) - 1)
            del ru, rv, out, wu, wv, cf
        dist = self.dist_terms() if F > 0 else None
        if dist is not None:  # the distance prior's blocks join the reduced pose system (ba_distance.py)
            sysm.v.index_add_(0, dist[2], dist[3])
            if self.sparse:
                sysm.sp_dest.append(dist[0])
                sysm.sp_vals.append(dist[1])
            else:
                sysm.H.index_add_(0, dist[0], dist[1].reshape(-1, 36))
        return sysm

    def _depth_start(self, ch):
        """``(eta, wd0)`` of the chunk's sources: the depth diagonal and gradient before the flow's terms (the
        prior's curvature joins the diagonal, its pull the gradient; ``wd0`` None without a prior)."""
        s_ch = self.src[ch.s0:ch.s1]
        eta_c, wd0 = self.eta[s_ch], None
        if self.prior is not None:
            a_ch = self.prior[1][ch.s0:ch.s1]
            eta_c, wd0 = eta_c + a_ch, a_ch * (self.prior[0][ch.s0:ch.s1] - self.d[s_ch])
        return eta_c, wd0

    def _add_chunk_fused(self, sysm: PoseSystem, ch, with_cost: bool, last: bool) -> None:
        """:meth:`linearise` and :func:`.ba_schur.assemble_chunk` of one chunk through the compiled loops."""
        args, Ad = self._fused_args(ch)
        eta_c, wd0 = self._depth_start(ch)
        C = eta_c.to(self.dtype, copy=True).contiguous()
        wd = torch.zeros_like(C) if wd0 is None else wd0.to(C.dtype, copy=True).contiguous()
        acc = torch.empty(len(ch.ii), 28, dtype=self.dtype)
        ba_kernels().pass_blocks(*args, C.numpy(), wd.numpy(), acc.numpy())
        if with_cost:
            sysm.cost += float(acc[:, 27].double().sum())
        Cinv = 1.0 / C.clamp(min=1e-12)
        B = sC = None
        if ch.ns > 0 and self.F > 0:
            B, sC = self._fused_rows(args, ch.n_src, Cinv)
        blocks, q = [], None
        if self.F > 0:
            Hjj = torch.zeros(len(ch.ii), 6, 6, dtype=torch.float64)
            up = acc[:, :21].double()
            Hjj[:, _UPPER[0], _UPPER[1]] = up
            Hjj[:, _UPPER[1], _UPPER[0]] = up
            blocks, q = pose_blocks(ch, Hjj, acc[:, 21:27].double(), Ad, B, sC, wd)
        self._add_terms(sysm, ch, blocks, q, Ad, Cinv, wd, B if last else None)

    def _add_chunk(self, sysm: PoseSystem, ch, ru, rv, out, wu, wv, last: bool) -> None:
        """One chunk's Schur terms into ``sysm`` (:func:`.ba_schur.assemble_chunk`)."""
        eta_c, wd0 = self._depth_start(ch)
        blocks, q, Ad, Ci, wdc, B = assemble_chunk(ch, ru, rv, wu, wv, out, eta_c, self.F, want_B=last, wd0=wd0)
        self._add_terms(sysm, ch, blocks, q, Ad, Ci, wdc, B)

    def _add_terms(self, sysm: PoseSystem, ch, blocks, q, Ad, Ci, wdc, B) -> None:
        """A chunk's blocks, gradients and depth terms into ``sysm`` (``B``: kept for the back-substitution)."""
        if ch.ns > 0:
            sysm.Cinv[ch.s0:ch.s1], sysm.wd[ch.s0:ch.s1] = Ci, wdc
        if B is not None:
            sysm.kept = (ch, B, Ad)
        if self.F > 0:
            qi = -torch.bmm(Ad.transpose(1, 2), q.unsqueeze(-1)).squeeze(-1)
            sysm.v.index_add_(0, ch.v_dest, torch.cat([q[ch.v_sel[0]], qi[ch.v_sel[1]]]))
            vals = torch.cat([blk[sel] for blk, sel in zip(blocks, ch.H_sel)])  # [nblocks, 6, 6]
            if self.sparse:
                sysm.sp_dest.append(ch.H_dest)
                sysm.sp_vals.append(vals)
            else:
                sysm.H.index_add_(0, ch.H_dest, vals.reshape(-1, 36))

    # ------------------------------------------------------------------------------------------ solve and step
    def solve(self, sysm: PoseSystem) -> tuple[Optional[torch.Tensor], float]:
        """The LM-damped pose step ``dxi [F, 6]`` and the damping boost it needed (10x / 100x more damping when
        the factorisation fails; ``(None, 0)`` when all three fail).  ``sysm.H`` is consumed."""
        F, opt = self.F, self.opt
        b = sysm.v.reshape(-1)
        Hs = S = None
        if self.sparse:
            H_dest = torch.cat(sysm.sp_dest)
            Hs = sparse_block_matrix(torch.div(H_dest, F, rounding_mode="floor"), H_dest % F,
                                     torch.cat(sysm.sp_vals), F)
            sysm.sp_vals = []
            del H_dest
            diag = torch.from_numpy(Hs.diagonal()).to(self.dev, torch.float64)
        else:
            S = sysm.H.reshape(F, F, 6, 6).permute(0, 2, 1, 3).reshape(6 * F, 6 * F)
            sysm.H = None
            S.add_(S.T.clone()).mul_(0.5)  # 0.5 (S + S^T) in place: two [6F, 6F] matrices at a time, not four
            diag = torch.diagonal(S).clone()
        for boost in (1.0, 10.0, 100.0):
            damp = opt.ep * boost + opt.lm * boost * diag
            if self.sparse:
                x = sparse_solve(Hs, damp.cpu().numpy(), b)
            else:
                torch.diagonal(S).copy_(diag + damp)  # S + diag(damp), in place (the diagonal is set anew each try)
                x = ba_linalg.solve_spd(S, b)
            if x is not None:
                return x.reshape(F, 6), boost
        return None, 0.0

    def back_substitute(self, sysm: PoseSystem, dxi: torch.Tensor) -> torch.Tensor:
        """Depth increments per source ``dd = C^-1 (w - sum_e Ej (dxi_jj - Ad dxi_ii))`` ``[Ns, P]``: the kept last
        chunk with its ``E^T``, the others with ``E^T`` recomputed at the same linearisation point."""
        Cinv, wd = sysm.Cinv, sysm.wd
        dd = Cinv * wd
        if not (self.Ns > 0 and self.F > 0):
            return dd
        xi_full = torch.zeros(self.pose_map.shape[0], 6, dtype=torch.float64, device=self.dev)
        xi_full[self.free_idx] = dxi
        done = None
        if sysm.kept is not None:
            (done, B, Ad), sysm.kept = sysm.kept, None
            s_ = slice(done.s0, done.s1)
            dd[s_] = backsub_chunk(done, B, Ad, xi_full, Cinv[s_], wd[s_])
            B = Ad = None
        for ch in self.chunks:
            if ch.ns > 0 and ch is not done and self.fused:
                s_ = slice(ch.s0, ch.s1)
                args, Ad = self._fused_args(ch)
                B, _ = self._fused_rows(args, ch.n_src, Cinv[s_])
                dd[s_] = backsub_chunk(ch, B, Ad, xi_full, Cinv[s_], wd[s_])
            elif ch.ns > 0 and ch is not done:
                s_, m = slice(ch.s0, ch.s1), ch.n_src
                _, _, out, wu, wv, _ = self.linearise(ch, "parts")
                B = depth_rows(ch, out["JuT"], out["JvT"], wu[:m] * out["Jdu"][:m], wv[:m] * out["Jdv"][:m],
                               Cinv[s_].sqrt())
                dd[s_] = backsub_chunk(ch, B, out["Ad"].double(), xi_full, Cinv[s_], wd[s_])
                del out, wu, wv, B
        return dd

    def apply(self, dxi: torch.Tensor, dd: torch.Tensor) -> None:
        """The step: left retraction of the free poses, depth increments clamped to ``>= DISP_MIN``."""
        if self.F > 0:
            self.G[self.free_idx] = se3_mul(se3_exp(dxi), self.G[self.free_idx])
        if self.Ns > 0:
            self.d[self.src] = (self.d[self.src] + dd).clamp(min=DISP_MIN)

    def write(self, graph: "FrameGraph", newT: torch.Tensor) -> None:
        """The estimate into the graph (camera-to-world poses ``newT [N, 7]``)."""
        if self.F > 0:
            graph.set_poses(self.free_idx, newT[self.free_idx])
        if self.Ns > 0:
            graph.set_disps(self.src, self.d[self.src].reshape(self.Ns, self.h, self.w).float())
