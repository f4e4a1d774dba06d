"""Sim(3) pose-graph optimisation for loop closure (DPV-SLAM style, anchors 3) and the loop-edge measurement.

Convention.  Nodes are camera-to-world similarities ``S_k = [t, q, s]`` (``X_w = s R X_k + t``: ``s`` converts
keyframe k's own (monocular) scale to the world scale).  An edge ``(a, b)`` carries a measurement
``Z_ab ~ S_a^-1 S_b`` (maps camera-b coordinates in b's scale to camera-a coordinates in a's scale).  Residual::

    r_ab = Log(Z_ab^-1 · S_a^-1 · S_b)          (7-vector [tau, phi, sigma])

Nodes are updated by a left retraction ``S <- Exp(delta) S``.  Levenberg-Marquardt with a dense normal matrix
(``7 F x 7 F``, F = free nodes) and central-difference Jacobians (float64; exact to ~1e-9, and the problem is
small).  The caller fixes at least one node (keyframe 0) - that removes the 7-dof gauge.

After optimisation a keyframe's new rigid pose is the ``[t, q]`` part of ``S_k`` and its inverse depth is
divided by ``s_k`` (its camera-frame points are scaled by ``s_k``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as nnf

from .ba_linalg import solve_spd, sparse_block_matrix, sparse_solve
from .ba_motion import motion_only_ba
from .lie import se3_inv, se3_mul, sim3_exp, sim3_from_se3, sim3_inv, sim3_log, sim3_mul
from .projective import edge_transforms, project_points

__all__ = ["PoseGraphResult", "sim3_pose_graph", "odometry_measurements", "loop_relative_sim3"]


@dataclass
class PoseGraphResult:
    poses: torch.Tensor  # float64 [N, 8] optimised Sim3 nodes
    cost_before: float
    cost_after: float
    iterations: int
    converged: bool


def _edge_residuals(S: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor, Zinv: torch.Tensor) -> torch.Tensor:
    return sim3_log(sim3_mul(Zinv, sim3_mul(sim3_inv(S[ii]), S[jj])))


def odometry_measurements(S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Edges ``(k, k+1)`` with their current relative Sim3 ``S_k^-1 S_{k+1}``."""
    n = S.shape[0]
    ii = torch.arange(n - 1, device=S.device)
    jj = ii + 1
    return ii, jj, sim3_mul(sim3_inv(S[ii]), S[jj])


def sim3_pose_graph(
    S0: torch.Tensor,
    ii: torch.Tensor,
    jj: torch.Tensor,
    Z: torch.Tensor,
    fixed: torch.Tensor,
    weights: Optional[torch.Tensor] = None,
    iters: int = 25,
    lm: float = 1e-4,
    fd_step: float = 1e-6,
    tol: float = 1e-10,
    sparse_min_nodes: int = 64,
) -> PoseGraphResult:
    """Optimise Sim3 nodes ``S0 [N, 8]`` against edge measurements ``Z [E, 8]`` (module docstring).

    ``fixed``: bool ``[N]``; ``weights``: ``[E]`` or ``[E, 7]`` information (diagonal), default 1.  ``lm``: the
    initial LM damping (relative to the diagonal; halved after an accepted step, x10 after a rejected one);
    ``fd_step``: the central differences' step; stops when the largest step component falls below ``tol``.
    On the CPU, graphs with more than ``sparse_min_nodes`` free nodes are solved with a sparse LU (the normal
    matrix of a chain with a few loops is block-sparse; a dense Cholesky of 7N x 7N would dominate).
    """
    pg = _PoseGraph(S0, ii, jj, Z, fixed, weights)
    S = S0.to(torch.float64).clone()
    c0 = pg.cost_of(S)
    if pg.F == 0 or pg.E == 0:
        return PoseGraphResult(S, c0, c0, 0, True)
    lam = lm
    cost = c0
    converged = False
    it = 0
    sparse = S.device.type == "cpu" and pg.F > sparse_min_nodes
    for it in range(1, int(iters) + 1):
        gv, br, bc, bv = pg.normal_equations(S, fd_step)
        S, cost, lam, step, rel = pg.lm_step(S, cost, lam, gv, br, bc, bv, sparse)
        if step is None or step < tol or rel < 1e-14:
            converged = True
            break
    return PoseGraphResult(S, c0, cost, it, converged)


class _PoseGraph:
    """The edges, weights and free-node slots of one :func:`sim3_pose_graph` problem (float64, ``S0``'s device)."""

    def __init__(self, S0, ii, jj, Z, fixed, weights):
        dev = self.dev = S0.device
        N, E = S0.shape[0], int(ii.shape[0])
        self.E = E
        self.ii, self.jj = ii.to(dev, torch.int64), jj.to(dev, torch.int64)
        self.Zinv = sim3_inv(Z.to(dev, torch.float64))
        Wt = torch.ones(E, 7, dtype=torch.float64, device=dev)
        if weights is not None:
            weights = weights.to(dev, torch.float64)
            Wt = Wt * (weights.unsqueeze(-1) if weights.dim() == 1 else weights)
        self.Wt = Wt
        fixed = fixed.to(dev, torch.bool)
        self.free_idx = torch.nonzero(~fixed).squeeze(1)
        F = self.F = int(self.free_idx.shape[0])
        self.slot = torch.full((N,), -1, dtype=torch.int64, device=dev)
        self.slot[self.free_idx] = torch.arange(F, device=dev)

    def cost_of(self, S_: torch.Tensor) -> float:
        r = _edge_residuals(S_, self.ii, self.jj, self.Zinv)
        return float((self.Wt * r * r).sum())

    def normal_equations(self, S: torch.Tensor, fd_step: float):
        """Gradient ``gv [7F]`` and the normal matrix as 7x7 blocks ``bv`` at block rows / columns ``br, bc`` (free
        slots), from central-difference Jacobians of every edge with respect to both of its nodes."""
        ii, jj, Zinv, Wt, slot, E = self.ii, self.jj, self.Zinv, self.Wt, self.slot, self.E
        r = _edge_residuals(S, ii, jj, Zinv)  # [E, 7]
        eye7 = torch.eye(7, dtype=torch.float64, device=self.dev)
        # central differences: perturb node i or j along each of 7 axes
        dl = torch.cat([eye7, -eye7], 0) * fd_step  # [14, 7]
        Pert = sim3_exp(dl)  # [14, 8]
        Si = S[ii].unsqueeze(1).expand(E, 14, 8)
        Sj = S[jj].unsqueeze(1).expand(E, 14, 8)
        Si_p = sim3_mul(Pert.unsqueeze(0).expand(E, 14, 8), Si)
        Sj_p = sim3_mul(Pert.unsqueeze(0).expand(E, 14, 8), Sj)
        Zi = Zinv.unsqueeze(1).expand(E, 14, 8)
        ri = sim3_log(sim3_mul(Zi, sim3_mul(sim3_inv(Si_p), Sj)))  # [E, 14, 7]
        rj = sim3_log(sim3_mul(Zi, sim3_mul(sim3_inv(Si), Sj_p)))
        Ji = ((ri[:, :7] - ri[:, 7:]) / (2 * fd_step)).transpose(1, 2)  # [E, 7(res), 7(var)]
        Jj = ((rj[:, :7] - rj[:, 7:]) / (2 * fd_step)).transpose(1, 2)
        g = torch.zeros(self.F, 7, dtype=torch.float64, device=self.dev)
        si, sj = slot[ii], slot[jj]
        WJi, WJj = Ji * Wt.unsqueeze(-1), Jj * Wt.unsqueeze(-1)
        blk_r, blk_c, blk_v = [], [], []
        for (sa, Ja, WJa) in ((si, Ji, WJi), (sj, Jj, WJj)):
            m = sa >= 0
            g.index_add_(0, sa[m], torch.einsum("erv,er->ev", WJa[m], r[m]))
            for (sb, Jb) in ((si, Ji), (sj, Jj)):
                mm = m & (sb >= 0)
                blk_r.append(sa[mm])
                blk_c.append(sb[mm])
                blk_v.append(torch.einsum("erv,erw->evw", WJa[mm], Jb[mm]))
        return g.reshape(-1), torch.cat(blk_r), torch.cat(blk_c), torch.cat(blk_v)

    def lm_step(self, S, cost, lam, gv, br, bc, bv, sparse: bool):
        """One Levenberg-Marquardt step: up to 8 tries with growing damping until the cost does not rise.
        Returns ``(S, cost, lam, step, rel)``; ``step`` (the largest component of the accepted update) and ``rel``
        (the relative cost decrease) are None when no try was accepted."""
        F = self.F
        if sparse:  # chain + loops: block-sparse normal matrix, solved with SuperLU
            Hs = sparse_block_matrix(br, bc, bv, F)
            hdiag = Hs.diagonal()
        else:
            H = torch.zeros(F * F, 49, dtype=torch.float64, device=self.dev)
            H.index_add_(0, br * F + bc, bv.reshape(-1, 49))
            Hm = H.reshape(F, F, 7, 7).permute(0, 2, 1, 3).reshape(7 * F, 7 * F)
            Hm = 0.5 * (Hm + Hm.T)
        for _ in range(8):
            if sparse:
                x = sparse_solve(Hs, hdiag * lam + 1e-9, -gv)
            else:
                A = Hm + lam * torch.diag(torch.diagonal(Hm)) + 1e-9 * torch.eye(7 * F, dtype=torch.float64,
                                                                                  device=self.dev)
                x = solve_spd(A, -gv)
            if x is None:
                lam *= 10
                continue
            delta = x.reshape(F, 7)
            S_new = S.clone()
            S_new[self.free_idx] = sim3_mul(sim3_exp(delta), S[self.free_idx])
            c_new = self.cost_of(S_new)
            if c_new <= cost:
                step = float(delta.abs().max())
                rel = (cost - c_new) / max(cost, 1e-300)
                return S_new, c_new, max(lam * 0.5, 1e-12), step, rel
            lam *= 10
        return S, cost, lam, None, None


def _bilinear(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Sample ``img [h, w]`` at float pixel positions (border clamp)."""
    h, w = img.shape
    gx = 2.0 * u / max(w - 1, 1) - 1.0
    gy = 2.0 * v / max(h - 1, 1) - 1.0
    grid = torch.stack([gx, gy], -1).reshape(1, 1, -1, 2).to(img.dtype)
    return nnf.grid_sample(img[None, None], grid, mode="bilinear", padding_mode="border", align_corners=True).reshape(-1)


def loop_relative_sim3(
    pose_a_wc: torch.Tensor,
    disp_a: torch.Tensor,
    pose_b_wc: torch.Tensor,
    disp_b: torch.Tensor,
    intr: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor,
    iters: int = 12,
    estimate_scale: bool = True,
    min_weight: float = 0.5,
) -> tuple[torch.Tensor, float, int]:
    """Measured relative Sim3 ``Z_ab ~ S_a^-1 S_b`` for a (loop) edge ``a -> b`` with flow targets of a's pixels
    in b.

    Keyframe a (pose and depth) is held fixed and b's pose is re-estimated with :func:`motion_only_ba` from the
    targets (starting from the current relative pose).  The scale ratio is the median over confidently matched
    pixels of ``depth of a's point in b (a's scale) / depth b's own map gives at the target``.
    Returns ``(Z_ab [8], scale ratio, pixels used)``; the ratio is 1 when it cannot be estimated.
    """
    pose_a = pose_a_wc.to(torch.float64)
    pose_b, _ = motion_only_ba(pose_b_wc.to(torch.float64), pose_a, disp_a, intr, target, weight, iters=iters,
                               lm=1e-5, ep=1e-3)
    T_ab = se3_mul(se3_inv(pose_a), pose_b)  # camera b -> camera a (a's scale)
    s, used = 1.0, 0
    if estimate_scale:
        h, w = disp_a.shape[-2:]
        R, t = edge_transforms(torch.stack([pose_a, pose_b]), torch.tensor([0]), torch.tensor([1]))
        dA = disp_a.reshape(1, -1).to(torch.float64)
        out = project_points(R, t, dA, intr, h, w, 0.2)
        z_b_ascale = out["z"].reshape(-1) / dA.reshape(-1).clamp(min=1e-6)  # metric depth in b, a's scale
        u, v = target[0].reshape(-1).double(), target[1].reshape(-1).double()
        inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        conf = weight.reshape(2, -1).double().min(0).values
        db = _bilinear(disp_b.double(), u, v)
        ok = inside & out["valid"].reshape(-1) & (conf >= min_weight * float(conf.max().clamp(min=1e-12))) & (db > 1e-6)
        used = int(ok.sum())
        if used >= 10:
            s = float(torch.median(z_b_ascale[ok] * db[ok]))
            if not (s > 0 and torch.isfinite(torch.tensor(s))):
                s, used = 1.0, 0
    # X_a(a) = T_ab X_b(a) and X_b(a) = s X_b(b)  =>  Z_ab = [t_ab, q_ab, s]
    Z = sim3_from_se3(T_ab, torch.tensor(s, dtype=torch.float64))
    return Z, s, used
