"""Residuals, robust weights and costs of the dense BA (:mod:`.ba`) and the motion-only BA (:mod:`.ba_motion`).

The residual of a pixel ``p`` of edge ``i -> j`` is ``target - pi(G_ij pi^-1(p, d_i[p]))`` (:mod:`.projective`);
the reported cost is ``sum conf * valid * |r|^2`` (no ``WEIGHT_SCALE``, no robust re-weighting)."""
from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import torch

from ..types import EdgeObservations
from .lie import quat_to_rotmat, se3_inv
from .projective import project_points

if TYPE_CHECKING:  # pragma: no cover
    from ..slam.graph import FrameGraph

__all__ = ["DISP_MIN", "WEIGHT_SCALE", "robust_weights", "residuals", "cost", "weighted_cost", "flat_obs",
           "chunk_obs"]

DISP_MIN = 1e-3  # inverse depths are clamped to at least this after an update (DROID's disps.clamp_(min=0.001))
WEIGHT_SCALE = 1e-3  # residual weight per unit of confidence (DROID's ba kernel: w = 0.001 * confidence)


def robust_weights(ru: torch.Tensor, rv: torch.Tensor, kind: Optional[str], scale: float) -> Optional[torch.Tensor]:
    """Per-pixel IRLS factor from the 2D residual (None: no re-weighting)."""
    if kind is None or kind == "none":
        return None
    n = torch.sqrt(ru * ru + rv * rv)
    if kind == "huber":
        return torch.where(n <= scale, torch.ones_like(n), scale / n.clamp(min=1e-12))
    if kind == "cauchy":
        return 1.0 / (1.0 + (n / scale) ** 2)
    raise ValueError(f"unknown robust kernel {kind!r} (use None, 'huber' or 'cauchy')")


def edge_rt(G: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor, dtype: torch.dtype):
    """``R_ij, t_ij`` of ``G_ij = G_j G_i^-1`` (world-to-camera poses ``G [N, 7]``), via rotation matrices."""
    R = quat_to_rotmat(G[:, 3:])
    Rij = torch.bmm(R[jj], R[ii].transpose(1, 2))
    tij = G[jj, :3] - torch.bmm(Rij, G[ii, :3].unsqueeze(-1)).squeeze(-1)
    return Rij.to(dtype), tij.to(dtype)


def residuals(G, d, ii, jj, target, intr, h, w, min_depth, jacobians):
    """``target [E, 2, P]`` -> residuals ``ru, rv [E, P]`` and :func:`project_points`' output."""
    R, t = edge_rt(G, ii, jj, d.dtype)
    out = project_points(R, t, d[ii], intr, h, w, min_depth, jacobians)
    return target[:, 0] - out["u"], target[:, 1] - out["v"], out


def cost(conf, valid, ru, rv) -> float:
    """``sum valid * (conf_u ru^2 + conf_v rv^2)`` (``conf [E, 2, P]``)."""
    return float((valid * (conf[:, 0] * ru * ru + conf[:, 1] * rv * rv)).sum())


def flat_obs(obs: EdgeObservations, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``target, conf [E, 2, P]``."""
    E = obs.target.shape[0]
    return obs.target.reshape(E, 2, -1).to(dtype), obs.weight.reshape(E, 2, -1).to(dtype)


def chunk_obs(target: torch.Tensor, conf: torch.Tensor, idx, dtype: torch.dtype):
    """``target, conf [Ec, 2, P]`` of one chunk of edges (``conf`` clamped to >= 0)."""
    return target[idx].to(dtype), conf[idx].to(dtype).clamp(min=0.0)


def weighted_cost(graph: "FrameGraph", obs: EdgeObservations, min_depth: float = 0.2) -> float:
    """``sum conf * valid * |target - reprojection|^2`` for the graph's current state."""
    h, w = graph.ba_shape
    dtype = torch.float64 if graph.device.type == "cpu" else torch.float32
    target, conf = flat_obs(obs, dtype)
    G = se3_inv(graph.poses)
    ru, rv, out = residuals(G, graph.disps.reshape(graph.n, -1).to(dtype), obs.ii.to(graph.device),
                            obs.jj.to(graph.device), target, graph.intrinsics, h, w, min_depth, False)
    return cost(conf, out["valid"], ru, rv)
