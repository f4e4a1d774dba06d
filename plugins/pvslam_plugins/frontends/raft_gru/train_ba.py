"""A differentiable dense BA for training (DROID-SLAM's ``geom/ba.py``: the same maths as the inference BA, dense,
in autograd-friendly torch).

Why not :func:`pvslam_core.geometry.ba.dense_ba`: it is built for inference (in-place graph updates, chunked
scatters, float64 pose solves through ``cholesky_ex`` with fall-backs, no autograd).  DROID trains *through* its
BA - the loss on the poses after BA reaches the flow revisions, the confidences and the damping - so training needs
a BA whose output is a differentiable function of ``target``, ``weight`` and ``eta``.  Training clips are small
(a handful of frames at a reduced resolution), so the whole system is assembled densely: pose blocks ``H
(6N x 6N)``, pose-depth blocks ``E (6N x N P)``, the diagonal depth block ``C (N P)``, Schur complement on the
depths, a Cholesky solve of the free poses in float64, depth back-substitution.  The tests check one step against
the inference BA (same update to 1e-9 in float64 with ``damping="schur"``) and the gradients by finite
differences.

Conventions as :mod:`pvslam_core.geometry.ba`: poses ``T_wc [N, 7]`` (updated by the left retraction of the
world-to-camera pose, ``G <- Exp(xi) G``), inverse depths ``[N, h, w]``, targets ``[E, h, w, 2]`` channels-last
(the network's layout), residual weights ``1e-3 * weight * valid`` (DROID), points with ``z_j / z_i < 0.2``
invalid, inverse depths clamped to ``>= 1e-3`` after the update.  Damping: DROID's training BA adds ``eta +
1e-7`` to ``C`` (the inference BA uses ``0.2 * eta``) and ``ep + lm * H_kk`` to the pose diagonal *before* the Schur
complement (``damping="pose"``); ``damping="schur"`` damps the reduced system like the inference BA.
"""
from __future__ import annotations

import torch

from pvslam_core.geometry.lie import se3_exp, se3_inv, se3_mul
from pvslam_core.geometry.projective import edge_transforms, project_points

WEIGHT_SCALE = 1e-3
DISP_MIN = 1e-3


def ba_step(
    poses_wc: torch.Tensor,
    disps: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor,
    eta: torch.Tensor,
    intr: torch.Tensor,
    ii: torch.Tensor,
    jj: torch.Tensor,
    fixedp: int = 1,
    lm: float = 1e-4,
    ep: float = 0.1,
    min_depth: float = 0.2,
    damping: str = "pose",
    eta_offset: float = 1e-7,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One Gauss-Newton step; returns the new ``(poses_wc [N, 7], disps [N, h, w])`` (differentiable).

    Args:
        poses_wc: ``[N, 7]`` camera-to-world; the first ``fixedp`` stay fixed (the gauge, and with 2 the scale).
        disps: ``[N, h, w]`` inverse depths at the BA resolution.
        target: ``[E, h, w, 2]`` positions in frame ``jj[e]`` of the pixels of frame ``ii[e]``.
        weight: ``[E, h, w, 2]`` confidences in [0, 1].
        eta: ``[N, h, w]`` depth damping added to ``C`` (``+ eta_offset``).
        intr: ``[4]`` fx fy cx cy at the BA resolution.
    """
    N, h, w = disps.shape
    lin = _linearise(poses_wc, disps, target, weight, intr, ii, jj, min_depth)
    H, v, C, wz, Eb = _normal_equations(lin, ii, jj, N, h * w)
    C = C + eta.reshape(N, h * w).to(disps.dtype) + eta_offset
    dx, dz = _schur_solve(H, v, C, wz, Eb, N, fixedp, lm, ep, damping)
    G = se3_inv(poses_wc)
    G_new = torch.cat([G[:fixedp], se3_mul(se3_exp(dx.reshape(-1, 6).to(G.dtype)), G[fixedp:])])
    disps_new = (disps.reshape(-1) + dz).reshape(N, h, w).clamp(min=DISP_MIN)
    return se3_inv(G_new), disps_new


def _linearise(poses_wc, disps, target, weight, intr, ii, jj, min_depth) -> dict:
    """Residuals ``ru, rv``, weights ``wu, wv [E, P]`` and the Jacobian rows ``Ji*T, Jj*T [E, 6, P]``, ``Jdu, Jdv
    [E, P]`` of every edge at the current estimate."""
    N, h, w = disps.shape
    P = h * w
    E = int(ii.shape[0])
    dtype = disps.dtype
    R, t = edge_transforms(poses_wc, ii, jj)
    out = project_points(R.to(dtype), t.to(dtype), disps[ii].reshape(E, P), intr.to(dtype), h, w, min_depth,
                         jacobians="parts")
    ru = target[..., 0].reshape(E, P).to(dtype) - out["u"]
    rv = target[..., 1].reshape(E, P).to(dtype) - out["v"]
    valid = out["valid"].to(dtype)
    wu = WEIGHT_SCALE * weight[..., 0].reshape(E, P).to(dtype) * valid
    wv = WEIGHT_SCALE * weight[..., 1].reshape(E, P).to(dtype) * valid
    JjuT, JjvT, Ad = out["JuT"], out["JvT"], out["Ad"]  # [E, 6, P], [E, 6, 6]
    JiuT = -torch.bmm(Ad.transpose(1, 2), JjuT)  # Ji = -Jj Ad  ->  Ji^T = -Ad^T Jj^T
    JivT = -torch.bmm(Ad.transpose(1, 2), JjvT)
    return dict(ru=ru, rv=rv, wu=wu, wv=wv, JiuT=JiuT, JivT=JivT, JjuT=JjuT, JjvT=JjvT, Jdu=out["Jdu"],
                Jdv=out["Jdv"])


def _normal_equations(lin: dict, ii, jj, N: int, P: int):
    """Dense normal equations: pose blocks ``H [N*N, 6, 6]`` (row pose, column pose), gradient ``v [N, 6]``, the
    depth diagonal ``C [N, P]`` (without damping), depth gradient ``wz [N, P]`` and pose-depth blocks
    ``Eb [N*N, 6, P]`` (pose, source)."""
    ru, rv, wu, wv = lin["ru"], lin["rv"], lin["wu"], lin["wv"]
    JiuT, JivT, JjuT, JjvT, Jdu, Jdv = (lin[k] for k in ("JiuT", "JivT", "JjuT", "JjvT", "Jdu", "Jdv"))
    dtype, dev = ru.dtype, ru.device

    def quad(Au, Av, Bu, Bv):  # sum_p Au wu Bu^T + Av wv Bv^T  -> [E, 6, 6]
        return torch.bmm(Au * wu[:, None], Bu.transpose(1, 2)) + torch.bmm(Av * wv[:, None], Bv.transpose(1, 2))

    H = torch.zeros(N * N, 6, 6, dtype=dtype, device=dev)
    H = H.index_add(0, ii * N + ii, quad(JiuT, JivT, JiuT, JivT))
    H = H.index_add(0, ii * N + jj, quad(JiuT, JivT, JjuT, JjvT))
    H = H.index_add(0, jj * N + ii, quad(JjuT, JjvT, JiuT, JivT))
    H = H.index_add(0, jj * N + jj, quad(JjuT, JjvT, JjuT, JjvT))
    gi = (JiuT * (wu * ru)[:, None] + JivT * (wv * rv)[:, None]).sum(-1)
    gj = (JjuT * (wu * ru)[:, None] + JjvT * (wv * rv)[:, None]).sum(-1)
    v = torch.zeros(N, 6, dtype=dtype, device=dev).index_add(0, ii, gi).index_add(0, jj, gj)
    C = torch.zeros(N, P, dtype=dtype, device=dev).index_add(0, ii, wu * Jdu * Jdu + wv * Jdv * Jdv)
    wz = torch.zeros(N, P, dtype=dtype, device=dev).index_add(0, ii, wu * Jdu * ru + wv * Jdv * rv)
    Ei = JiuT * (wu * Jdu)[:, None] + JivT * (wv * Jdv)[:, None]  # [E, 6, P]
    Ej = JjuT * (wu * Jdu)[:, None] + JjvT * (wv * Jdv)[:, None]
    Eb = torch.zeros(N * N, 6, P, dtype=dtype, device=dev)
    Eb = Eb.index_add(0, ii * N + ii, Ei).index_add(0, jj * N + ii, Ej)
    return H, v, C, wz, Eb


def _schur_solve(H, v, C, wz, Eb, N: int, fixedp: int, lm: float, ep: float, damping: str):
    """Pose step ``dx [6F]`` of the free poses (Schur complement on the depths, Cholesky in float64) and depth step
    ``dz [N P]``."""
    dtype, dev = H.dtype, H.device
    P = C.shape[1]
    free = torch.arange(fixedp, N, device=dev)
    F_ = int(free.numel())
    Hf = H.reshape(N, N, 6, 6)[free][:, free].permute(0, 2, 1, 3).reshape(6 * F_, 6 * F_)
    Ef = Eb.reshape(N, N, 6, P)[free].permute(0, 2, 1, 3).reshape(6 * F_, N * P)  # [6F, N*P]
    vf = v[free].reshape(-1)
    Cinv = 1.0 / C.reshape(-1)
    eye = torch.eye(6 * F_, dtype=dtype, device=dev)
    if damping == "pose":
        Hf = Hf + (ep + lm * Hf) * eye
    S = Hf - (Ef * Cinv) @ Ef.T
    y = vf - Ef @ (Cinv * wz.reshape(-1))
    if damping == "schur":
        S = S + (ep + lm * S) * eye
    elif damping != "pose":
        raise ValueError(f"damping must be 'pose' or 'schur', got {damping!r}")
    S = 0.5 * (S + S.T)
    L = torch.linalg.cholesky(S.double())
    dx = torch.cholesky_solve(y.double()[:, None], L)[:, 0].to(dtype)  # [6F]
    dz = Cinv * (wz.reshape(-1) - Ef.T @ dx)
    return dx, dz
