"""Poses of every input frame, anchored to keyframes.

Each frame's pose is stored as ``anchor keyframe (stable id)`` plus the relative transform ``T_a^-1 · T_f``, so
the full trajectory follows the keyframes when bundle adjustment or loop closure moves them.  Keyframes are
anchored to themselves with the identity.  For non-keyframes the frontend's correspondences to the anchor (at the
BA resolution) are kept so the relative pose can be re-estimated with motion-only BA once the anchor's depth is
final (:meth:`FramePoses.refill`).  When an anchor keyframe is removed, its frames re-anchor to the keyframe
before it (the graph tells, see :meth:`on_keyframe_removed`).  Poses are T_wc ``[t, q_xyzw]``
(:mod:`pvslam_core.types`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import torch

from ..geometry.lie import se3_inv, se3_mul

if TYPE_CHECKING:  # pragma: no cover
    from .graph import FrameGraph


@dataclass
class FrameEntry:
    index: int  # input frame index
    timestamp: float
    anchor: int  # stable id of the anchor keyframe
    rel: torch.Tensor  # float64 [7] T_anchor^-1 T_frame
    target: Optional[torch.Tensor] = None  # [2, h, w] anchor pixels -> this frame (for refill)
    weight: Optional[torch.Tensor] = None
    is_keyframe: bool = False
    failed: bool = False


IDENTITY = torch.tensor([0, 0, 0, 0, 0, 0, 1], dtype=torch.float64)


class FramePoses:
    """Every input frame's pose relative to an anchor keyframe of ``graph`` (a GraphListener of it)."""

    def __init__(self, graph: "FrameGraph", robust: Optional[str] = None, robust_scale: float = 1.0) -> None:
        self.graph = graph
        self.entries: list[FrameEntry] = []
        self.robust, self.robust_scale = robust, robust_scale  # IRLS kernel of the motion-only BA
        graph.add_listener(self)

    def __len__(self) -> int:
        return len(self.entries)

    def add_keyframe(self, index: int, timestamp: float, kf_id: int) -> None:
        self.entries.append(FrameEntry(index, timestamp, kf_id, IDENTITY.clone(), is_keyframe=True))

    def add_frame(self, index: int, timestamp: float, anchor: int, rel: torch.Tensor,
                  target: Optional[torch.Tensor] = None, weight: Optional[torch.Tensor] = None,
                  failed: bool = False) -> FrameEntry:
        e = FrameEntry(index, timestamp, anchor, rel.detach().to("cpu", torch.float64), target, weight, failed=failed)
        self.entries.append(e)
        return e

    def last_rel(self) -> torch.Tensor:
        return self.entries[-1].rel.clone() if self.entries else IDENTITY.clone()

    # ------------------------------------------------------------------------------------ GraphListener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        """Frames anchored to ``kf_id`` re-anchor to the keyframe before it (poses unchanged)."""
        g = self.graph
        k = g.index_of(kf_id)
        if k == 0:
            raise ValueError("the first keyframe cannot be removed (it anchors the map)")
        prev_id = g.id_of(k - 1)
        t_prev_k = se3_mul(se3_inv(g.poses[k - 1].double().cpu()), g.poses[k].double().cpu())  # T_{k-1}^-1 T_k
        for e in self.entries:
            if e.anchor == kf_id:
                e.rel = se3_mul(t_prev_k, e.rel)
                e.anchor = prev_id
                e.is_keyframe = False
                e.target = e.weight = None  # correspondences referred to the removed keyframe's pixels

    def on_edges_retired(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        pass

    # ----------------------------------------------------------------------------------------- queries --
    def pending(self, anchor: int) -> list[FrameEntry]:
        """Non-keyframes anchored to keyframe id ``anchor``."""
        return [e for e in self.entries if e.anchor == anchor and not e.is_keyframe]

    def poses(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(timestamps float64 [T], poses float64 [T, 7])`` for every frame so far, vectorised."""
        if not self.entries:
            return torch.zeros(0, dtype=torch.float64), torch.zeros(0, 7, dtype=torch.float64)
        ts = torch.tensor([e.timestamp for e in self.entries], dtype=torch.float64)
        anchors = self.graph.indices_of(torch.tensor([e.anchor for e in self.entries], dtype=torch.int64)).cpu()
        if bool((anchors < 0).any()):
            raise RuntimeError("a frame is anchored to a keyframe that is no longer in the graph")
        rel = torch.stack([e.rel for e in self.entries])
        return ts, se3_mul(self.graph.poses.double().cpu()[anchors], rel)

    def pose_of(self, e: FrameEntry) -> torch.Tensor:
        """float64 [7] T_wc of one entry under the current keyframe poses."""
        return se3_mul(self.graph.poses[self.graph.index_of(e.anchor)].double().cpu(), e.rel)

    # ---------------------------------------------------------------------------------- motion-only BA --
    def motion_only(self, init_wc: torch.Tensor, kf_pose: torch.Tensor, kf_disp: torch.Tensor, intr: torch.Tensor,
                    target: torch.Tensor, weight: torch.Tensor, iters: int = 4) -> Optional[torch.Tensor]:
        """Pose ``T_wc`` (float64 [7], CPU) of a frame from flow targets of a keyframe (pose ``kf_pose``, depth
        ``kf_disp``) by motion-only BA with this object's robust kernel, from ``init_wc``; None if not finite."""
        from ..geometry.ba import motion_only_ba

        t_a = kf_pose.double()
        pose, _cost = motion_only_ba(init_wc.to(t_a.device), t_a, kf_disp, intr, target, weight, iters=iters,
                                     robust=self.robust, robust_scale=self.robust_scale)
        return pose.double().cpu() if bool(torch.isfinite(pose).all()) else None

    def refine(self, e: FrameEntry, init_wc: torch.Tensor, iters: int = 4) -> bool:
        """Motion-only BA of entry ``e`` against its anchor keyframe, starting from ``init_wc``; stores the new
        relative pose. False (unchanged) when the result is not finite."""
        return self.refine_many([e], init_wc.reshape(1, 7), iters) == 1

    def refine_many(self, entries: list[FrameEntry], inits_wc: torch.Tensor, iters: int = 4) -> int:
        """:meth:`refine` for several entries (one batched motion-only BA per anchor keyframe, from ``inits_wc
        [len(entries), 7]``). Returns how many were updated."""
        from ..geometry.ba import motion_only_ba

        g = self.graph
        by_anchor: dict[int, list[int]] = {}
        for n, e in enumerate(entries):
            by_anchor.setdefault(e.anchor, []).append(n)
        done = 0
        for anchor, rows in by_anchor.items():
            a = g.index_of(anchor)
            t_a = g.poses[a].double()
            init = inits_wc[rows].to(t_a.device, torch.float64)
            target = torch.stack([entries[n].target for n in rows])
            weight = torch.stack([entries[n].weight for n in rows])
            poses, costs = motion_only_ba(init, t_a, g.disps[a], g.intrinsics, target, weight, iters=iters,
                                          robust=self.robust, robust_scale=self.robust_scale)
            ok = torch.isfinite(poses).all(-1).tolist()  # a failed solve returns its (finite) start pose
            inv_a = se3_inv(t_a.cpu())
            rel = se3_mul(inv_a.expand(len(rows), 7), poses.double().cpu())
            for m, n in enumerate(rows):
                if ok[m]:
                    entries[n].rel = rel[m]
                    done += 1
        return done

    def refill(self, iters: int = 4) -> int:
        """Re-estimate the relative pose of every non-keyframe that still has correspondences. Returns the count."""
        todo = [e for e in self.entries if not e.is_keyframe and e.target is not None]
        if not todo:
            return 0
        _, poses = self.poses()
        index = {id(e): n for n, e in enumerate(self.entries)}
        return self.refine_many(todo, poses[[index[id(e)] for e in todo]], iters)
