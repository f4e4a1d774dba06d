"""The VO's geometry between two consecutive frames, for the VPS head (:class:`~pvslam_core.interfaces.MotionCue`).

Both frames were tracked against keyframes; when they share the reference keyframe ``R`` (or the previous frame
*is* ``R``), each pixel ``p`` of ``R`` has a position ``P(p)`` in the previous frame and ``C(p)`` in the current one,
so the previous frame's pixel at ``P(p)`` moves by ``C(p) - P(p)``.  Splatting those vectors at the rounded
``P(p)`` gives the flow on the previous frame's grid (cells no point lands on are filled from their neighbours and
flagged in ``flow_valid``).  With an initialised map the z-depth of each point in the previous camera follows from
``R``'s inverse depth and the two poses (nearest point per cell).  Everything is at the BA resolution, as the
frontend's correspondences are; a head resizes.  Poses are T_wc.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from ..geometry.lie import se3_inv, se3_mul, quat_to_rotmat
from ..interfaces import MotionCue
from ..types import FrameResult


def _grid(h: int, w: int, device) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32, device=device),
                            torch.arange(w, dtype=torch.float32, device=device), indexing="ij")
    return torch.stack([xs, ys])  # [2, h, w]


def _positions(result: FrameResult, ref_id: int, h: int, w: int, device) -> Optional[torch.Tensor]:
    """float32 [2, h, w]: where the pixels of keyframe ``ref_id`` are in ``result``'s frame, if known."""
    if result.keyframe_id == ref_id:
        return _grid(h, w, device)
    if result.ref_id == ref_id and result.ref_target is not None and not result.failed:
        return result.ref_target.to(device, torch.float32)
    return None


def _fill_holes(flow: torch.Tensor, valid: torch.Tensor, passes: int = 4) -> torch.Tensor:
    """Fill cells without a value by the mean of their valid 3x3 neighbours, ``passes`` times, then by the mean."""
    flow = flow.clone()
    have = valid.clone()
    k = torch.ones(1, 1, 3, 3, dtype=flow.dtype, device=flow.device)
    for _ in range(passes):
        if bool(have.all()):
            break
        m = have.to(flow.dtype)[None, None]
        num = F.conv2d((flow * m[0])[:, None], k, padding=1)[:, 0]  # [2, h, w]
        den = F.conv2d(m, k, padding=1)[0, 0]
        new = (~have) & (den > 0)
        flow[:, new] = num[:, new] / den[new]
        have = have | new
    if not bool(have.all()):
        fill = flow[:, have].mean(dim=1) if bool(have.any()) else torch.zeros(2, dtype=flow.dtype, device=flow.device)
        flow[:, ~have] = fill[:, None]
    return flow


def motion_cue(prev: Optional[FrameResult], cur: FrameResult) -> MotionCue:
    """The motion cue from ``prev`` to ``cur`` (empty fields where the VO cannot tell)."""
    if prev is None:
        return MotionCue()
    cue = MotionCue()
    both_init = prev.initialized and cur.initialized
    if both_init:
        cue.pose_prev, cue.pose_cur = prev.pose.double().cpu(), cur.pose.double().cpu()
    if cur.ref_id is None or cur.ref_target is None or cur.failed:
        return cue
    C = cur.ref_target.float()
    h, w = C.shape[-2:]
    dev = C.device
    P = _positions(prev, cur.ref_id, h, w, dev)
    if P is None:
        return cue
    # splat the displacement C - P at round(P) on the previous frame's grid
    u, v = torch.round(P[0]).long().reshape(-1), torch.round(P[1]).long().reshape(-1)
    d = (C - P).reshape(2, -1)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & torch.isfinite(d).all(0)
    cell = (v * w + u)[inside]
    count = torch.zeros(h * w, device=dev).index_add_(0, cell, torch.ones_like(cell, dtype=torch.float32))
    flow = torch.zeros(2, h * w, device=dev)
    flow.index_add_(1, cell, d[:, inside])
    valid = count > 0
    flow[:, valid] /= count[valid]
    valid = valid.reshape(h, w)
    cue.flow = _fill_holes(flow.reshape(2, h, w), valid)
    cue.flow_valid = valid
    if both_init and cur.ref_disp is not None and cur.ref_pose is not None and cur.intrinsics is not None:
        fx, fy, cx, cy = (float(t) for t in cur.intrinsics[:4])
        disp = cur.ref_disp.float().reshape(-1).clamp(min=1e-6)
        g = _grid(h, w, dev).reshape(2, -1)
        X = torch.stack([(g[0] - cx) / fx, (g[1] - cy) / fy, torch.ones_like(g[0])]) / disp  # [3, P] in R's camera
        rel = se3_mul(se3_inv(prev.pose.double().cpu()), cur.ref_pose.double().cpu())  # T_prev^-1 T_R
        R = quat_to_rotmat(rel[3:]).float().to(dev)
        z = (R[2:3] @ X)[0] + float(rel[2])
        ok = inside & (z > 1e-6)
        zbuf = torch.full((h * w,), float("inf"), device=dev)
        zbuf.scatter_reduce_(0, (v * w + u)[ok], z[ok], reduce="amin")
        cue.depth_prev = torch.where(torch.isfinite(zbuf), zbuf, torch.zeros_like(zbuf)).reshape(h, w)
        cue.intrinsics = cur.intrinsics.float().cpu().clone()
    return cue
