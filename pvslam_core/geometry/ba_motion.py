"""Motion-only BA: the pose of new frames from flow targets of one fixed keyframe (its pose and inverse depths held),
with the residuals, weights and robust kernel of the dense BA (:mod:`.ba_residuals`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from .ba_linalg import all_finite, log_once
from .ba_residuals import WEIGHT_SCALE, robust_weights
from .ba_schur import rowvec
from .lie import quat_to_rotmat, se3_exp, se3_inv, se3_mul
from .projective import project_points

__all__ = ["motion_only_ba"]


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
    confidences.  ``lm``, ``ep``, ``min_depth``, ``weight_scale``, ``robust``/``robust_scale``: as in
    :class:`.ba.BAOptions`.  Returns ``(pose_wc float64 [7], final cost)`` with the cost as in :func:`.ba.dense_ba`
    (no robust re-weighting).  On non-finite input or update the initial pose is returned (cost NaN if it could not
    be evaluated).

    Batched: ``pose_wc [F, 7]`` with ``target``/``weight [F, 2, h, w]`` solves ``F`` independent frames against the
    same keyframe at once (one set of tensor ops instead of ``F``: the frames between two keyframes are placed in
    one call) and returns ``(poses [F, 7], costs float64 [F])``; each frame behaves as if solved alone.
    """
    batched = pose_wc.dim() == 2
    dev = kf_disp.device
    pose0 = pose_wc.to(dev, torch.float64).reshape(-1, 7)  # [F, 7]
    F = pose0.shape[0]
    kf = kf_pose_wc.to(dev, torch.float64).reshape(1, 7)  # T_wc of the keyframe = G_kf^-1
    target = target.reshape(F, 2, -1)
    weight = weight.reshape(F, 2, -1)
    ok_in = _finite_inputs(pose0, kf, kf_disp, target, weight)
    if not bool(ok_in.all()):
        log_once("motion_only_ba: non-finite input; initial pose returned")
        if not bool(ok_in.any()):
            out = pose0.clone()
            nan = torch.full((F,), float("nan"), dtype=torch.float64)
            return (out, nan) if batched else (out[0], float("nan"))
    fr = _Frames.build(kf, kf_disp, intr, target, weight, ok_in, min_depth)
    G = se3_inv(torch.where(ok_in[:, None], pose0, kf.expand(F, 7)))  # [F, 7] world-to-camera
    active = ok_in.clone()  # a frame whose system fails to factorise stops (keeps its last pose)
    eye = torch.eye(6, dtype=torch.float64, device=dev)
    for _ in range(max(0, int(iters))):
        dx = fr.gn_step(G, lm, ep, weight_scale, robust, robust_scale, eye, active)
        if dx is None:
            break
        G = se3_mul(se3_exp(dx), G)
    T, cost = fr.result(G, pose0, ok_in)
    if batched:
        return T, cost
    return T[0], float(cost[0])


def _finite_inputs(pose0, kf, kf_disp, target, weight) -> torch.Tensor:
    """``[F]`` bool: the frames whose inputs are all finite (none when the keyframe's are not)."""
    F = pose0.shape[0]
    ok_in = torch.ones(F, dtype=torch.bool, device=kf_disp.device)
    for t in (kf, kf_disp):
        if not all_finite(t):
            ok_in[:] = False
    for t in (pose0, target, weight):
        if not all_finite(t):
            ok_in &= torch.isfinite(t.reshape(F, -1)).all(-1).to(kf_disp.device)
    return ok_in


@dataclass
class _Frames:
    """The per-pixel data of ``F`` frames against one keyframe (frames with bad input get zero targets)."""

    tgt_u: torch.Tensor  # [F, P]
    tgt_v: torch.Tensor
    conf_u: torch.Tensor  # [F, P] clamped to >= 0
    conf_v: torch.Tensor
    dd: torch.Tensor  # [F, P] the keyframe's inverse depths
    R_kf: torch.Tensor  # [1, 3, 3] and [1, 3, 1]: T_wc of the keyframe
    t_kf: torch.Tensor
    intr: torch.Tensor
    h: int
    w: int
    min_depth: float

    @classmethod
    def build(cls, kf, kf_disp, intr, target, weight, ok_in, min_depth) -> "_Frames":
        dtype = torch.float64 if kf_disp.device.type == "cpu" else torch.float32
        F = target.shape[0]
        h, w = kf_disp.shape[-2:]
        tgt_u, tgt_v = target[:, 0].to(dtype), target[:, 1].to(dtype)  # [F, P]
        conf_u, conf_v = weight[:, 0].to(dtype).clamp(min=0), weight[:, 1].to(dtype).clamp(min=0)
        dd = kf_disp.reshape(1, -1).to(dtype).expand(F, -1)
        zero = torch.zeros_like(tgt_u)
        tgt_u, tgt_v = torch.where(ok_in[:, None], tgt_u, zero), torch.where(ok_in[:, None], tgt_v, zero)
        return cls(tgt_u, tgt_v, conf_u, conf_v, dd, quat_to_rotmat(kf[:, 3:]), kf[:, :3].unsqueeze(-1), intr, h, w,
                   min_depth)

    def evaluate(self, G: torch.Tensor, jac: bool):
        """Residuals ``ru, rv [F, P]`` and :func:`project_points`' output at world-to-camera poses ``G [F, 7]``."""
        # camera kf -> camera new, G o T_kf, composed as rotation matrices (the quaternion product, its
        # normalisation and a second quaternion -> matrix conversion were ~40 tiny ops per evaluation)
        F, dtype = G.shape[0], self.dd.dtype
        R_G = quat_to_rotmat(G[:, 3:])  # [F, 3, 3]
        R = torch.matmul(R_G, self.R_kf)
        t = torch.baddbmm(G[:, :3].unsqueeze(-1), R_G, self.t_kf.expand(F, 3, 1)).squeeze(-1)
        out = project_points(R.to(dtype), t.to(dtype), self.dd, self.intr, self.h, self.w, self.min_depth,
                             "pose" if jac else False)
        return self.tgt_u - out["u"], self.tgt_v - out["v"], out

    def gn_step(self, G, lm, ep, weight_scale, robust, robust_scale, eye, active) -> Optional[torch.Tensor]:
        """One LM-damped Gauss-Newton step ``dx [F, 6]`` (zero for frames no longer ``active``, which this
        updates in place); None when no frame is active any more."""
        ru, rv, out = self.evaluate(G, True)
        valid = out["valid"].to(self.dd.dtype)
        wu, wv = self.conf_u * valid * weight_scale, self.conf_v * valid * weight_scale  # [F, P]
        rw = robust_weights(ru, rv, robust, robust_scale)
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
            return None
        return torch.where(active[:, None], dx, torch.zeros_like(dx))

    def result(self, G, pose0, ok_in) -> tuple[torch.Tensor, torch.Tensor]:
        """``(T_wc [F, 7], plain cost float64 [F])``; frames with bad input or a non-finite result get their initial
        pose (cost NaN)."""
        ru, rv, out = self.evaluate(G, False)
        valid = out["valid"].to(self.dd.dtype)
        cost = ((self.conf_u * ru * ru + self.conf_v * rv * rv) * valid).sum(-1).double()  # [F]
        T = se3_inv(G)
        good = ok_in & torch.isfinite(cost) & torch.isfinite(T).all(-1)
        if not bool(good.all()):
            if bool((ok_in & ~good).any()):
                log_once("motion_only_ba: non-finite result; initial pose returned")
            T = torch.where(good[:, None], T, pose0)
            cost = torch.where(good, cost, torch.full_like(cost, float("nan")))
        return T, cost
