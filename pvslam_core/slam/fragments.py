"""Map fragments and their merging (ORB-SLAM3 Atlas style).

After a tracking loss the mapper starts a new *fragment* (:class:`~.mapper.Mapper`): a map of its own,
placed at the last known pose but with its own scale (a new two-view initialisation) and an unknown offset.  The
frame graph holds every fragment, one after the other in keyframe order; :class:`Fragments` knows which keyframe
ids belong to which one (a fragment is a contiguous id range from its first keyframe; merged fragments share a
union-find root).

When the loop detector finds a verified loop between the current fragment (keyframe ``k``) and an older one
(keyframe ``j``), :func:`relocalise` places ``k`` in the old map and :func:`align_fragment` moves the whole current
fragment there:

1. pose from 2D-3D: the flow of the edge ``j -> k`` (``j``'s pixels in ``k``) with ``j``'s depth (old map, old
   scale) gives ``k``'s pose in the old map by motion-only BA, started from ``j``'s pose (a verified loop is the same
   place, seen from nearby; a few starts around it are tried and the lowest median reprojection error kept, which
   must be under a pixel of the BA grid);
2. scale: the same matches give each point's inverse depth in ``k`` in old units (``d_j / z_h``); ``k``'s own inverse
   depth (new units) sampled at the matched pixels over it is the scale ``s`` of the Sim(3) (median: robust to the
   flow's outliers), lengths_old = ``s`` x lengths_new;
3. the Sim(3) ``S = (s, R, t)`` that takes ``k``'s current pose to the relocalised one is applied to every keyframe
   of the fragment (poses; inverse depths divided by ``s``) and the relative translations of the frames anchored to
   them are multiplied by ``s`` (their rotations are unchanged).

The loop edges and the loop BA that follow (the loop closer's ordinary path, :mod:`.loop_closer`) then refine the
join.  The loop
policy's orientation check does not apply to such a loop (the two fragments' frames are unrelated until merged:
the loop that ends a fragment's isolation would otherwise be rejected for the very offset it corrects).

Poses are T_wc ``[t, q_xyzw]``.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import torch

from ..geometry.ba import motion_only_ba
from ..geometry.lie import quat_mul, quat_rotate, se3_exp, se3_interpolate, se3_mul
from ..geometry.projective import edge_transforms, project_points

if TYPE_CHECKING:  # pragma: no cover
    from .frame_poses import FramePoses
    from .graph import FrameGraph

LOG = logging.getLogger("pvslam")


class Fragments:
    """Which fragment each keyframe id belongs to; fragments merged so far share a root (union-find)."""

    def __init__(self) -> None:
        self.starts: list[int] = [0]  # first keyframe id of each fragment, ascending
        self._parent: dict[int, int] = {0: 0}
        self.merges = 0

    def start(self, kf_id: int) -> None:
        """A new fragment begins at keyframe id ``kf_id`` (newer than every stored one)."""
        if kf_id <= self.starts[-1]:
            raise ValueError(f"fragment start {kf_id} is not after the last one ({self.starts[-1]})")
        self.starts.append(kf_id)
        self._parent[kf_id] = kf_id

    def _find(self, x: int) -> int:
        while self._parent[x] != x:
            self._parent[x] = self._parent[self._parent[x]]
            x = self._parent[x]
        return x

    def of(self, kf_id: int) -> int:
        """The fragment (root start id) of keyframe id ``kf_id``."""
        import bisect

        s = self.starts[max(0, bisect.bisect_right(self.starts, int(kf_id)) - 1)]
        return self._find(s)

    def same(self, a_id: int, b_id: int) -> bool:
        return self.of(a_id) == self.of(b_id)

    def merge(self, a_id: int, b_id: int) -> None:
        """Merge the fragments of keyframes ``a_id`` and ``b_id`` (the older one's root stays)."""
        ra, rb = self.of(a_id), self.of(b_id)
        if ra != rb:
            self._parent[max(ra, rb)] = min(ra, rb)
            self.merges += 1

    @property
    def unmerged(self) -> int:
        """Number of separate maps (1 when everything is in one frame)."""
        return len({self._find(s) for s in self.starts})


@dataclass
class Relocalisation:
    pose: torch.Tensor  # float64 [7] T_wc of keyframe k in the old map
    scale: float  # lengths_old / lengths_new of k's fragment
    error: float  # median reprojection error of the confident matches (BA px)
    matched: int  # confident matches used


def _residuals(pose_j: torch.Tensor, pose_k: torch.Tensor, disp_j: torch.Tensor, intr: torch.Tensor,
               target: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """Reprojection error [h*w] (BA px) of ``j``'s pixels in ``k`` against the flow targets, and the projection."""
    h, w = disp_j.shape
    R, t = edge_transforms(torch.stack([pose_j, pose_k]), torch.tensor([0]), torch.tensor([1]))  # camera j -> k
    out = project_points(R.float(), t.float(), disp_j.float().reshape(1, -1).cpu(), intr.float().cpu(), h, w)
    tx, ty = target[0].float().reshape(-1).cpu(), target[1].float().reshape(-1).cpu()
    err = torch.hypot(out["u"][0] - tx, out["v"][0] - ty)
    return torch.where(out["valid"][0], err, torch.full_like(err, float("inf"))), out


def median_error(pose_j: torch.Tensor, pose_k: torch.Tensor, disp_j: torch.Tensor, intr: torch.Tensor,
                 target: torch.Tensor, weight: torch.Tensor, min_weight: float = 0.5) -> float:
    """Median reprojection error (BA px) of ``j``'s confidently matched pixels (mean weight >= ``min_weight``) in
    ``k`` at pose ``pose_k``, against the flow targets (inf when none is matched)."""
    conf = (weight.float().mean(0) >= min_weight).reshape(-1).cpu()
    if not bool(conf.any()):
        return float("inf")
    err, _ = _residuals(pose_j.double().cpu(), pose_k.double().cpu(), disp_j, intr, target)
    return float(err[conf].median())


def relocalise(pose_j: torch.Tensor, disp_j: torch.Tensor, disp_k: torch.Tensor, intr: torch.Tensor,
               target: torch.Tensor, weight: torch.Tensor, min_weight: float = 0.5, min_matched: int = 30,
               max_median_px: float = 1.0, iters: int = 10) -> Optional[Relocalisation]:
    """Pose and scale of keyframe ``k`` in the map of keyframe ``j`` (see the module docstring).

    ``pose_j`` T_wc [7]; ``disp_j``/``disp_k`` [h, w] inverse depths (old / new units); ``target`` [2, h, w]:
    positions in ``k`` of ``j``'s pixels (BA px); ``weight`` [2, h, w].  None when fewer than ``min_matched``
    confident matches (mean weight >= ``min_weight``), no finite solution, a median reprojection error of the
    confident matches above ``max_median_px`` (BA px), or a degenerate scale."""
    h, w = disp_j.shape
    pose_j = pose_j.double().cpu()
    disp_j, disp_k, target, weight = disp_j.cpu(), disp_k.cpu(), target.cpu(), weight.cpu()
    conf = (weight.float().mean(0) >= min_weight).reshape(-1)  # [h*w]
    if int(conf.sum()) < min_matched:
        LOG.info("relocalisation failed: %d confident matches (min %d)", int(conf.sum()), min_matched)
        return None
    # starts: j's pose and small rotations about the camera's vertical axis (a verified loop can be seen from a
    # somewhat different heading); the one with the lowest median reprojection error wins
    starts = [pose_j] + [se3_mul(pose_j, se3_exp(torch.tensor([0, 0, 0, 0, yaw, 0], dtype=torch.float64)))
                         for yaw in (-0.2, 0.2)]
    S = len(starts)
    poses, _costs = motion_only_ba(torch.stack(starts), pose_j, disp_j, intr, target[None].expand(S, 2, h, w),
                                   weight[None].expand(S, 2, h, w), iters=iters, robust="cauchy", robust_scale=1.0)
    best, best_med, best_out = None, float("inf"), None
    for p in poses.double().cpu():
        if not bool(torch.isfinite(p).all()):
            continue
        err, out = _residuals(pose_j, p, disp_j, intr, target)
        med = float(err[conf].median())
        if med < best_med:
            best, best_med, best_out = p, med, out
    if best is None or not best_med <= max_median_px:
        LOG.info("relocalisation failed: median reprojection error %.2f BA px (max %.2f)", best_med, max_median_px)
        return None
    # scale: inverse depth of j's matched points in k, old units (d_j / z_h), against k's own (new units)
    d_old = disp_j.float().reshape(-1) / best_out["z"][0].clamp(min=1e-6)
    u = torch.round(target[0].float().reshape(-1)).long()
    v = torch.round(target[1].float().reshape(-1)).long()
    ok = conf & best_out["valid"][0] & (u >= 0) & (u < w) & (v >= 0) & (v < h) & (d_old > 0)
    if int(ok.sum()) < min_matched:
        return None
    d_new = disp_k.float().reshape(-1)[v[ok] * w + u[ok]]
    ratio = d_new / d_old[ok]
    ratio = ratio[torch.isfinite(ratio) & (ratio > 0)]
    if ratio.numel() < min_matched:
        return None
    s = float(ratio.median())
    if not (1e-3 < s < 1e3):
        return None
    return Relocalisation(best, s, best_med, int(ok.sum()))


def sim3_between(pose_from: torch.Tensor, pose_to: torch.Tensor, s: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(q [4], t [3])`` of the Sim(3) ``x -> s R x + t`` that takes camera pose ``pose_from`` (T_wc) to
    ``pose_to``: ``R = R_to R_from^-1``, ``t = t_to - s R t_from``."""
    a, b = pose_from.double(), pose_to.double()
    q_from_inv = torch.cat([-a[3:6], a[6:]])
    q = quat_mul(b[3:], q_from_inv)
    t = b[:3] - s * quat_rotate(q, a[:3])
    return q / q.norm(), t


def apply_sim3(poses: torch.Tensor, q: torch.Tensor, t: torch.Tensor, s: float) -> torch.Tensor:
    """T_wc poses ``[N, 7]`` moved by the Sim(3) ``(s, q, t)``: positions ``s R p + t``, orientations ``R R_c``."""
    p = poses.double()
    qn = q.double().expand(len(p), 4)
    pos = s * quat_rotate(qn, p[:, :3]) + t.double()
    rot = quat_mul(qn, p[:, 3:])
    return torch.cat([pos, rot / rot.norm(dim=-1, keepdim=True)], dim=-1)


def align_fragment(g: "FrameGraph", frames: "FramePoses", idx: torch.Tensor, k: int, reloc: Relocalisation) -> None:
    """Move keyframes ``idx`` (graph indices of the current fragment, ``k`` among them) by the Sim(3) that takes
    ``k`` to ``reloc.pose`` with scale ``reloc.scale``; rescale the relative translations of the frames anchored
    to them (a frame's rotation relative to its anchor is unchanged by a similarity)."""
    s = reloc.scale
    idx = torch.as_tensor(idx, dtype=torch.int64)
    q, t = sim3_between(g.poses[k].double().cpu(), reloc.pose, s)
    g.set_poses(idx, apply_sim3(g.poses[idx.to(g.device)].double().cpu(), q, t, s))
    g.set_disps(idx, g.disps[idx.to(g.device)] / s)
    ids = set(int(x) for x in g.ids[idx.to(g.device)].tolist())
    for e in frames.entries:
        if e.anchor in ids and not e.is_keyframe:
            e.rel = torch.cat([e.rel[:3] * s, e.rel[3:]])


def fragment_indices(graph, fragments: Fragments, kf_id: int) -> torch.Tensor:
    """Graph indices (int64 [m]) of the keyframes in the fragment of ``kf_id``."""
    root = fragments.of(kf_id)
    return torch.tensor([k for k, x in enumerate(graph.ids.tolist()) if fragments.of(x) == root], dtype=torch.int64)


def replace_gap_frames(g: "FrameGraph", frames: "FramePoses", first: int) -> int:
    """After a merge: the frames that failed between the previous fragment's last keyframe (``first - 1``) and the
    merged fragment's first keyframe (``first``) were extrapolated from the former; both ends are now in one frame,
    so place them by interpolation in time between the two.  Returns how many were moved."""
    if first <= 0 or first >= g.n:
        return 0
    a_id, b_id = g.id_of(first - 1), g.id_of(first)
    ts_a, ts_b = float(g.timestamps[first - 1]), float(g.timestamps[first])
    gap = [e for e in frames.entries if e.failed and e.anchor == a_id and ts_a < e.timestamp < ts_b]
    if not gap or ts_b <= ts_a:
        return 0
    t_a, t_b = g.poses[first - 1].double().cpu(), g.poses[first].double().cpu()
    alpha = torch.tensor([(e.timestamp - ts_a) / (ts_b - ts_a) for e in gap], dtype=torch.float64)
    poses = se3_interpolate(t_a.expand(len(gap), 7), t_b.expand(len(gap), 7), alpha)
    for e, pose in zip(gap, poses):  # held between the two from now on: they follow both
        frames.hold_between(e, a_id, b_id, pose)
    return len(gap)
