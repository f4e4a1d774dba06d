"""Projective operations on keyframes: back-projection with inverse depth, reprojection into another keyframe
with analytic Jacobians, and DROID-SLAM's frame distance.

Public functions take **camera-to-world** poses ``T_wc [N, 7]`` (pvslam's convention).  Internally they work
with world-to-camera ``G_k = T_wc_k^-1`` as DROID-SLAM does, and the relative transform of an edge ``i -> j``
is ``G_ij = G_j G_i^-1 = T_wc_j^-1 T_wc_i`` (camera i -> camera j).

Points are homogeneous ``P = (X, Y, 1, d)`` with ``X = (x - cx) / fx``, ``Y = (y - cy) / fy`` and ``d`` the
inverse depth of pixel ``(x, y)``; ``G_ij P = R (X, Y, 1) + t d`` keeps the homogeneous scale, so its third
component ``z_h`` is the depth in camera j divided by the depth in camera i.  A point is *valid* when
``z_h > min_depth`` (DROID's test, which is scale-free and so meaningful for monocular maps; it implies the
point is in front of camera j since camera-i depths are positive).

Jacobian convention (used by :mod:`pvslam_core.geometry.ba`): the tangent ``xi = [tau, phi]`` of a keyframe
is a **left** retraction of its world-to-camera pose, ``G_k <- Exp(xi) G_k``, which is
``T_wc_k <- T_wc_k Exp(-xi)`` on the camera-to-world pose.  ``Jd`` is the derivative with respect to the
inverse depth of the source pixel.
"""
from __future__ import annotations

import torch

from .lie import quat_to_rotmat, se3_inv, se3_mul

__all__ = ["pixel_grid", "reproject", "frame_distance", "depth_to_points", "edge_transforms", "project_points"]


def pixel_grid(h: int, w: int, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``[h, w, 2]`` pixel coordinates with ``[..., 0] = x`` (column) and ``[..., 1] = y`` (row)."""
    y, x = torch.meshgrid(
        torch.arange(h, device=device, dtype=dtype), torch.arange(w, device=device, dtype=dtype), indexing="ij"
    )
    return torch.stack([x, y], dim=-1)


_RAYS: dict = {}


def _rays(h: int, w: int, fx: float, fy: float, cx: float, cy: float, dtype, device) -> torch.Tensor:
    """Normalised rays ``[3, h*w] = (X0, Y0, 1)`` of the pixel grid (cached: the BA calls this every iteration)."""
    key = (h, w, fx, fy, cx, cy, dtype, str(device))
    hit = _RAYS.get(key)
    if hit is None:
        grid = pixel_grid(h, w, device, dtype).reshape(-1, 2)
        hit = torch.stack([(grid[:, 0] - cx) / fx, (grid[:, 1] - cy) / fy, torch.ones_like(grid[:, 0])])
        if len(_RAYS) > 32:
            _RAYS.clear()
        _RAYS[key] = hit
    return hit


def edge_transforms(poses_wc: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation ``[E, 3, 3]`` and translation ``[E, 3]`` of ``G_ij = T_wc_j^-1 T_wc_i`` (camera i -> camera j)."""
    Gij = se3_mul(se3_inv(poses_wc[jj]), poses_wc[ii])
    return quat_to_rotmat(Gij[:, 3:]), Gij[:, :3]


def project_points(
    R: torch.Tensor,
    t: torch.Tensor,
    d: torch.Tensor,
    intr: torch.Tensor,
    h: int,
    w: int,
    min_depth: float = 0.2,
    jacobians: bool | str = False,
    translation_only: bool = False,
) -> dict:
    """Core of :func:`reproject` on flattened pixels.

    ``R [E,3,3]``, ``t [E,3]``, ``d [E, h*w]`` in one dtype.  Returns a dict with ``u, v [E, P]``, ``valid``,
    ``z`` (homogeneous depth) and with ``jacobians``: ``Ji, Jj [E, P, 2, 6]`` and ``Jd [E, P, 2]``.
    ``jacobians="j"`` skips ``Ji`` (it is ``-Jj Ad`` with ``Ad = out["Ad"]``, the adjoint of ``G_ij``);
    ``jacobians="parts"`` returns only the rows ``JuT, JvT [E, 6, P]`` (transposed), ``Jdu, Jdv [E, P]`` and ``Ad``;
    ``jacobians="pose"`` only ``JuT, JvT`` (motion-only BA).
    ``translation_only`` uses ``R = I`` (for the frame distance).
    """
    dtype, device = d.dtype, d.device
    fx, fy, cx, cy = (float(v) for v in intr.tolist())
    rays = _rays(h, w, fx, fy, cx, cy, dtype, device)  # [3, P]
    if translation_only:
        X = rays[0] + t[:, 0:1] * d
        Y = rays[1] + t[:, 1:2] * d
        Z = 1.0 + t[:, 2:3] * d
    else:
        # R (X0, Y0, 1) + t d: one [3E, 3] x [3, P] product (matmul folds the batch) instead of 21 element-wise ops
        # (in the promoted dtype of R, t, d, as the element-wise formula was)
        ct = torch.promote_types(torch.promote_types(R.dtype, t.dtype), dtype)
        XYZ = torch.matmul(R.to(ct), rays.to(ct)).addcmul_(t.unsqueeze(-1), d.unsqueeze(1))  # [E, 3, P]
        X, Y, Z = XYZ.unbind(1)
    valid = Z > min_depth
    Zs = torch.where(valid, Z, torch.ones_like(Z))
    iz = Zs.reciprocal()
    xn, yn = X * iz, Y * iz  # normalised image coordinates in camera j
    out = {"u": fx * xn + cx, "v": fy * yn + cy, "valid": valid, "z": Z}
    if not jacobians:
        return out
    hz = d * iz  # homogeneous coordinate (inverse depth of the source pixel) / z
    differentiable = torch.is_grad_enabled() and any(x.requires_grad for x in (R, t, d))
    JuT, JvT = _pose_jacobian_rows(xn, yn, hz, fx, fy, differentiable)
    out.update(JuT=JuT, JvT=JvT)
    if jacobians == "pose":
        return out
    Jdu = (fx * iz) * (t[:, 0:1] - t[:, 2:3] * xn)
    Jdv = (fy * iz) * (t[:, 1:2] - t[:, 2:3] * yn)
    Ad = _adjoint(R, t, dtype, device)
    out.update(Jdu=Jdu, Jdv=Jdv, Ad=Ad)
    if jacobians == "parts":
        return out
    E, P = xn.shape
    Jj = torch.stack([JuT.transpose(1, 2), JvT.transpose(1, 2)], dim=-2)  # [E, P, 2, 6]
    out.update(Jj=Jj, Jd=torch.stack([Jdu, Jdv], dim=-1))
    if jacobians != "j":
        out["Ji"] = -torch.bmm(Jj.reshape(E, 2 * P, 6), Ad).reshape(E, P, 2, 6)
    return out


def _pose_jacobian_rows(xn, yn, hz, fx: float, fy: float, differentiable: bool):
    """``JuT, JvT [E, 6, P]``: d(u, v) / d xi_j with ``G_j <- Exp(xi_j) G_j`` (DROID: ``fx [h d', 0, -X h d'^2,
    -X Y d'^2, 1 + X^2 d'^2, -Y d']``), stored transposed, which is the layout the BA's batched matmuls want.
    ``differentiable``: built with autograd-friendly ops (the raft_gru trainer's BA layer), else each row is
    written once into its place (no stack copy, no extra pass for the focal length)."""
    if differentiable:
        zero = torch.zeros_like(xn)
        JuT = torch.stack([hz, zero, -xn * hz, -xn * yn, 1 + xn * xn, -yn], dim=1) * fx
        JvT = torch.stack([zero, hz, -yn * hz, -1 - yn * yn, xn * yn, xn], dim=1) * fy
        return JuT, JvT
    JuT, JvT = torch.empty(2, xn.shape[0], 6, xn.shape[1], dtype=xn.dtype, device=xn.device).unbind(0)
    torch.mul(hz, fx, out=JuT[:, 0])
    JuT[:, 1].zero_()
    torch.mul(xn * hz, -fx, out=JuT[:, 2])
    xy = xn * yn
    torch.mul(xy, -fx, out=JuT[:, 3])
    torch.mul(xn, xn, out=JuT[:, 4]).add_(1.0).mul_(fx)
    torch.mul(yn, -fx, out=JuT[:, 5])
    JvT[:, 0].zero_()
    torch.mul(hz, fy, out=JvT[:, 1])
    torch.mul(yn * hz, -fy, out=JvT[:, 2])
    torch.mul(yn, yn, out=JvT[:, 3]).add_(1.0).mul_(-fy)
    torch.mul(xy, fy, out=JvT[:, 4])
    torch.mul(xn, fy, out=JvT[:, 5])
    return JuT, JvT


def _adjoint(R: torch.Tensor, t: torch.Tensor, dtype, device) -> torch.Tensor:
    """``Ad(G_ij) = [[R, t^ R], [0, R]] [E, 6, 6]`` (d / d xi_i = -Jj Ad)."""
    tR = torch.cross(t.unsqueeze(-1).expand(-1, 3, 3), R, dim=1)  # column-wise t x R[:, k] = (t^ R)[:, :, k]
    Ad = torch.zeros(R.shape[0], 6, 6, dtype=dtype, device=device)
    Ad[:, :3, :3] = R
    Ad[:, :3, 3:] = tR
    Ad[:, 3:, 3:] = R
    return Ad


def reproject(
    poses_wc: torch.Tensor,
    disps: torch.Tensor,
    intr: torch.Tensor,
    ii: torch.Tensor,
    jj: torch.Tensor,
    jacobians: bool = False,
    min_depth: float = 0.2,
):
    """Reproject every pixel of keyframe ``ii[e]`` into keyframe ``jj[e]``.

    Returns ``coords [E, h, w, 2]`` (u, v), ``valid [E, h, w]`` and, with ``jacobians=True``, also
    ``Ji, Jj [E, h, w, 2, 6]`` and ``Jd [E, h, w, 2]`` (module docstring: left retraction of world-to-camera
    poses; inverse depth of the ``ii`` pixel).  Computed in the dtype of ``disps``.
    """
    N, h, w = disps.shape
    ii = torch.as_tensor(ii, dtype=torch.long, device=disps.device)
    jj = torch.as_tensor(jj, dtype=torch.long, device=disps.device)
    dtype = disps.dtype
    R, t = edge_transforms(poses_wc, ii, jj)
    out = project_points(R.to(dtype), t.to(dtype), disps[ii].reshape(len(ii), -1), intr, h, w, min_depth, jacobians)
    E = len(ii)
    coords = torch.stack([out["u"], out["v"]], dim=-1).reshape(E, h, w, 2)
    valid = out["valid"].reshape(E, h, w)
    if not jacobians:
        return coords, valid
    return (coords, valid, out["Ji"].reshape(E, h, w, 2, 6), out["Jj"].reshape(E, h, w, 2, 6),
            out["Jd"].reshape(E, h, w, 2))


def frame_distance(
    poses_wc: torch.Tensor,
    disps: torch.Tensor,
    intr: torch.Tensor,
    ii: torch.Tensor,
    jj: torch.Tensor,
    beta: float = 0.3,
    min_depth: float = 0.25,
    stride: int = 1,
    min_valid: float = 0.75,
) -> torch.Tensor:
    """DROID-SLAM's frame distance ``[E]`` (anchors 1.5), in pixels of the depth maps' resolution:

    ``sum_valid [beta |pi(G_ij X) - x| + (1 - beta) |pi(X + d t_ij) - x|] / #valid``, and ``1000`` where fewer
    than ``min_valid`` of the pixels are valid (``z_h > min_depth`` for both motions).  ``stride`` subsamples the
    pixel grid (the intrinsics are adjusted accordingly; distances stay in full-map pixels).
    """
    ii = torch.as_tensor(ii, dtype=torch.long, device=disps.device)
    jj = torch.as_tensor(jj, dtype=torch.long, device=disps.device)
    E = len(ii)
    if E == 0:
        return torch.zeros(0, dtype=disps.dtype, device=disps.device)
    intr = intr.to(disps.dtype)
    if stride > 1:
        disps = disps[:, ::stride, ::stride]
        intr = torch.stack([intr[0] / stride, intr[1] / stride, intr[2] / stride, intr[3] / stride])
    _, h, w = disps.shape
    R, t = edge_transforms(poses_wc, ii, jj)
    R, t = R.to(disps.dtype), t.to(disps.dtype)
    d = disps[ii].reshape(E, -1)
    full = project_points(R, t, d, intr, h, w, min_depth)
    tr = project_points(R, t, d, intr, h, w, min_depth, translation_only=True)
    grid = pixel_grid(h, w, disps.device, disps.dtype).reshape(-1, 2)
    f_full = torch.sqrt((full["u"] - grid[:, 0]) ** 2 + (full["v"] - grid[:, 1]) ** 2)
    f_tr = torch.sqrt((tr["u"] - grid[:, 0]) ** 2 + (tr["v"] - grid[:, 1]) ** 2)
    valid = (full["valid"] & tr["valid"]).to(disps.dtype)
    nvalid = valid.sum(-1)
    dist = ((beta * f_full + (1 - beta) * f_tr) * valid).sum(-1) / nvalid.clamp(min=1)
    dist = dist * stride
    dist = torch.where(nvalid / d.shape[1] < min_valid, torch.full_like(dist, 1000.0), dist)
    return dist


def depth_to_points(disps: torch.Tensor, intr: torch.Tensor, min_disp: float = 1e-6) -> torch.Tensor:
    """Inverse depth ``[h, w]`` -> camera-frame points ``[h, w, 3]`` (``z = 1 / disp``; NaN where disp <= min_disp)."""
    h, w = disps.shape[-2:]
    fx, fy, cx, cy = (float(v) for v in intr.tolist())
    grid = pixel_grid(h, w, disps.device, disps.dtype)
    good = disps > min_disp
    z = torch.where(good, 1.0 / torch.where(good, disps, torch.ones_like(disps)), torch.full_like(disps, float("nan")))
    return torch.stack([(grid[..., 0] - cx) / fx * z, (grid[..., 1] - cy) / fy * z, z], dim=-1)


def fill_holes(disp: torch.Tensor, hole: torch.Tensor, row_min_frac: float = 0.0) -> torch.Tensor:
    """Fill the ``hole`` pixels of an inverse-depth map ``disp [h, w]``: with the median of the known pixels of the
    same row where at least ``row_min_frac`` of that row is known, else with the median of the whole map
    (``row_min_frac = 0`` or no known row: the whole map's median everywhere).

    Why rows: for a camera with little roll, a horizontal plane (floor, road, ceiling) has the same depth all
    along an image row, so the known part of a row predicts the row's new part better than the image's median.
    It matters where a keyframe sees mostly new pixels and nothing can measure their depth yet: through a turn
    on the spot the median of the previous view walks the map's scale off (docs/decisions.md:
    FILL_ROW_MIN_FRAC)."""
    known = ~hole
    whole = disp[known].median()
    if row_min_frac > 0:
        rows = torch.where(known, disp, torch.full_like(disp, float("nan"))).nanmedian(dim=1).values  # [h]
        use = known.float().mean(dim=1) >= row_min_frac
        fill = torch.where(use, rows, whole)[:, None].expand_as(disp)
    else:
        fill = whole.expand_as(disp)
    return torch.where(hole, fill, disp)
