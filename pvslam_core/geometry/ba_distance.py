"""A prior on the distance between two keyframes' camera centres, for the dense BA (:func:`.ba.dense_ba`).

Why: a monocular map's scale is a gauge the flow observes only through parallax.  On a highway at 20 m/s and
10 Hz the keyframes are 4 frames (8 m) apart, the near road has left the view by the next keyframe (its pixels
carry no weight on any keyframe edge) and the far scene barely moves: the scale then drifts within a few hundred
frames (docs/decisions.md: frontend.road.distance_weight).  A frontend that measures the motion
between keyframes in a metric of its own (the flow frontend's road plane: the translation in camera heights,
frame to frame, where the near road is still in view) states it as ``|c_i - c_j| = L_ij`` in map units, which
holds the scale where the flow cannot.

The factor: residual ``r = (L - |c_i - c_j|) / L`` (relative, so the weight against the flow's terms does not
depend on the map's scale, as the road's depth prior), weight ``alpha`` in the units of the flow cost (one pixel
with a 1 px residual weighs ``weight_scale``; the factor ``alpha weight_scale``).  Only the distance is stated:
the direction stays the flow's.  With ``G = (R, t)`` world-to-camera and the BA's left update ``G <- Exp(xi) G``,
``xi = [tau, phi]``, the camera centre ``c = -R^T t`` moves by ``-R^T tau`` (to first order; the rotation part does
not move it), so ``d|c_i - c_j| / d tau_i = -u^T R_i^T`` and ``/ d tau_j = u^T R_j^T`` with ``u`` the unit
vector from ``c_j`` to ``c_i``.
"""
from __future__ import annotations

import torch

from .lie import quat_to_rotmat


def distance_prior_terms(G: torch.Tensor, pose_map: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
                         dist: torch.Tensor, alpha: torch.Tensor, weight_scale: float, F: int
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """Gauss-Newton terms of the distance prior on pairs ``ii[m], jj[m]`` (graph indices) at world-to-camera poses
    ``G [N, 7]`` (float64): ``(H_dest [k], H_vals [k, 6, 6], v_dest [l], v_vals [l, 6], cost)`` in the layout of
    the reduced pose system of :func:`.ba.dense_ba` (block ``(a, b)`` of the ``F`` free poses at ``a * F + b``;
    ``pose_map``: graph index -> free index or -1), and the prior's cost in flow-cost units.  Pairs whose poses
    are both fixed, or whose centres coincide, add nothing (but their cost)."""
    dev = G.device
    ii, jj = ii.to(dev, torch.int64), jj.to(dev, torch.int64)
    L = dist.to(dev, torch.float64)
    a = alpha.to(dev, torch.float64)
    Ri, Rj = quat_to_rotmat(G[ii, 3:]), quat_to_rotmat(G[jj, 3:])  # [m, 3, 3]
    ci = -(Ri.transpose(1, 2) @ G[ii, :3].unsqueeze(-1)).squeeze(-1)  # camera centres [m, 3]
    cj = -(Rj.transpose(1, 2) @ G[jj, :3].unsqueeze(-1)).squeeze(-1)
    diff = ci - cj
    norm = diff.norm(dim=-1)
    r = (L - norm) / L  # [m]
    cost = float((a * r * r).sum())
    ok = (norm > 1e-12) & (a > 0)
    u = diff / norm.clamp(min=1e-12).unsqueeze(-1)
    zeros3 = torch.zeros_like(u)
    # Jacobians of the prediction |c_i - c_j| / L w.r.t. xi_i, xi_j (translation rows only) [m, 6]
    Ji = torch.cat([-(u.unsqueeze(1) @ Ri.transpose(1, 2)).squeeze(1), zeros3], -1) / L.unsqueeze(-1)
    Jj = torch.cat([(u.unsqueeze(1) @ Rj.transpose(1, 2)).squeeze(1), zeros3], -1) / L.unsqueeze(-1)
    wgt = (a * weight_scale * ok)[:, None]
    fi, fj = pose_map[ii], pose_map[jj]
    H_dest, H_vals, v_dest, v_vals = [], [], [], []
    for (fa, Ja), (fb, Jb) in (((fi, Ji), (fi, Ji)), ((fi, Ji), (fj, Jj)), ((fj, Jj), (fi, Ji)), ((fj, Jj), (fj, Jj))):
        m = (fa >= 0) & (fb >= 0) & ok
        H_dest.append(fa[m] * F + fb[m])
        H_vals.append(wgt[m, :, None] * Ja[m, :, None] * Jb[m, None, :])
    for fa, Ja in ((fi, Ji), (fj, Jj)):
        m = (fa >= 0) & ok
        v_dest.append(fa[m])
        v_vals.append(wgt[m] * Ja[m] * r[m, None])
    return torch.cat(H_dest), torch.cat(H_vals), torch.cat(v_dest), torch.cat(v_vals), cost
