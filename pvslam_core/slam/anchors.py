"""Poses of every input frame, anchored to keyframes.

Each frame's pose is stored as ``anchor keyframe index a`` plus the relative transform ``T_a^-1 · T_f``, so the
full trajectory follows the keyframes when bundle adjustment or loop closure moves them.  Keyframes are anchored
to themselves with the identity.  For non-keyframes the frontend's correspondences to the anchor (at the BA
resolution) are kept so the relative pose can be re-estimated with motion-only BA once the anchor's depth is
final (:meth:`FrameAnchors.refill`).  Poses are T_wc ``[t, q_xyzw]`` (pvslam_core.types).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from ..geometry.lie import se3_inv, se3_mul


@dataclass
class _Entry:
    index: int  # input frame index
    timestamp: float
    anchor: int  # keyframe index in the graph
    rel: torch.Tensor  # float64 [7] T_anchor^-1 T_frame
    target: Optional[torch.Tensor] = None  # [2, h, w] anchor pixels -> this frame (for refill)
    weight: Optional[torch.Tensor] = None
    is_keyframe: bool = False
    failed: bool = False


IDENTITY = torch.tensor([0, 0, 0, 0, 0, 0, 1], dtype=torch.float64)


class FrameAnchors:
    def __init__(self, robust: Optional[str] = None, robust_scale: float = 1.0) -> None:
        self.entries: list[_Entry] = []
        self.robust, self.robust_scale = robust, robust_scale  # IRLS kernel of the motion-only BA

    def __len__(self) -> int:
        return len(self.entries)

    def add_keyframe(self, index: int, timestamp: float, k: int) -> None:
        self.entries.append(_Entry(index, timestamp, k, IDENTITY.clone(), is_keyframe=True))

    def add_frame(self, index: int, timestamp: float, anchor: int, rel: torch.Tensor,
                  target: Optional[torch.Tensor] = None, weight: Optional[torch.Tensor] = None,
                  failed: bool = False) -> None:
        self.entries.append(_Entry(index, timestamp, anchor, rel.detach().to("cpu", torch.float64), target, weight,
                                   failed=failed))

    def last_rel(self) -> torch.Tensor:
        return self.entries[-1].rel.clone() if self.entries else IDENTITY.clone()

    def remove_keyframe(self, k: int, kf_poses: torch.Tensor) -> None:
        """Keyframe ``k`` leaves the graph: frames anchored to it re-anchor to ``k-1``; later anchors shift down."""
        if k == 0:
            raise ValueError("keyframe 0 cannot be removed")
        t_prev_k = se3_mul(se3_inv(kf_poses[k - 1].double().cpu()), kf_poses[k].double().cpu())  # T_{k-1}^-1 T_k
        for e in self.entries:
            if e.anchor == k:
                e.rel = se3_mul(t_prev_k, e.rel)
                e.anchor = k - 1
                e.is_keyframe = False
                e.target = e.weight = None  # correspondences referred to keyframe k's pixels
            elif e.anchor > k:
                e.anchor -= 1

    def pending(self, anchor: int) -> list[_Entry]:
        return [e for e in self.entries if e.anchor == anchor and not e.is_keyframe]

    def poses(self, kf_poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(timestamps float64 [T], poses float64 [T, 7])`` for every frame so far, vectorised."""
        if not self.entries:
            return torch.zeros(0, dtype=torch.float64), torch.zeros(0, 7, dtype=torch.float64)
        ts = torch.tensor([e.timestamp for e in self.entries], dtype=torch.float64)
        anchors = torch.tensor([e.anchor for e in self.entries], dtype=torch.int64)
        rel = torch.stack([e.rel for e in self.entries])
        return ts, se3_mul(kf_poses.double().cpu()[anchors], rel)

    def motion_only(self, init_wc: torch.Tensor, kf_pose: torch.Tensor, kf_disp: torch.Tensor, intr: torch.Tensor,
                    target: torch.Tensor, weight: torch.Tensor, iters: int = 4) -> Optional[torch.Tensor]:
        """Pose ``T_wc`` (float64 [7], CPU) of a frame from flow targets of a keyframe (pose ``kf_pose``, depth
        ``kf_disp``) by motion-only BA with this object's robust kernel, from ``init_wc``; None if not finite."""
        from ..geometry.ba import motion_only_ba

        t_a = kf_pose.double()
        pose, _cost = motion_only_ba(init_wc.to(t_a.device), t_a, kf_disp, intr, target, weight, iters=iters,
                                     robust=self.robust, robust_scale=self.robust_scale)
        return pose.double().cpu() if bool(torch.isfinite(pose).all()) else None

    def refine(self, e: _Entry, init_wc: torch.Tensor, kf_pose: torch.Tensor, kf_disp: torch.Tensor, intr: torch.Tensor,
               iters: int = 4) -> bool:
        """Motion-only BA of entry ``e`` against its anchor keyframe (pose ``kf_pose``, depth ``kf_disp``),
        starting from ``init_wc``; stores the new relative pose. False (unchanged) when the result is not finite."""
        pose = self.motion_only(init_wc, kf_pose, kf_disp, intr, e.target, e.weight, iters)
        if pose is None:
            return False
        e.rel = se3_mul(se3_inv(kf_pose.double().cpu()), pose)
        return True

    def refill(self, kf_poses: torch.Tensor, kf_disps: torch.Tensor, intr: torch.Tensor, iters: int = 4) -> int:
        """Re-estimate the relative pose of every non-keyframe that still has correspondences. Returns the count."""
        n = 0
        for e in self.entries:
            if e.is_keyframe or e.target is None or e.anchor >= kf_poses.shape[0]:
                continue
            init = se3_mul(kf_poses[e.anchor].double().cpu(), e.rel)
            n += self.refine(e, init, kf_poses[e.anchor], kf_disps[e.anchor], intr, iters)
        return n
