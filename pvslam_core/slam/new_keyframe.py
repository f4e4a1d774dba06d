"""Where a new keyframe starts: its pose guess and its first inverse depth, before the window BA refines both.

* pose: a motion-only BA of the tracking target against the newest keyframe (its depth fixed), from the last
  frame's relative motion; only the measured pixels of that keyframe when there are enough of them
  (:meth:`.observed.ObservedMasks.guess_weight`);
* depth: the newest keyframe's depth moved into the new one (z-buffered splat at the BA resolution; holes filled by
  row, :func:`~..geometry.projective.fill_holes`), a far better start for the BA than a constant.  With it, the
  pixels that are measured (:mod:`.observed`): those a measured pixel of the newest keyframe lands on.  Before the
  map is initialised (or for a fragment's first keyframe) the frontend's guess, else a constant.

Poses are T_wc ``[t, q_xyzw]``; ``a`` is a graph index.
"""
from __future__ import annotations

from typing import Optional

import torch

from ..geometry.lie import se3_mul
from ..geometry.projective import edge_transforms, fill_holes, project_points
from ..types import TrackResult
from .map_state import MapState

# a row with at least this share of its pixels known fills its holes with its own median, the others with the
# image's (0: the image's median everywhere; docs/decisions.md: FILL_ROW_MIN_FRAC)
FILL_ROW_MIN_FRAC = 0.25
MIN_WARPED = 0.2  # the warped depth is used when at least this share of the new keyframe's pixels get a value


def pose_guess(state: MapState, a: int, track: TrackResult) -> torch.Tensor:
    """float64 [7] pose guess of a new keyframe tracked against keyframe ``a`` (CPU): ``a``'s pose before the map is
    initialised, without a target or when the motion-only BA fails."""
    g = state.graph
    t_a = g.poses[a].double()
    if not state.initialized or track.target is None:
        return t_a.cpu().clone()
    init = se3_mul(t_a.cpu(), state.frames.last_rel())
    weight = track.weight
    if state.observed.active:
        weight = state.observed.guess_weight(g.id_of(a), weight)
    pose = state.frames.motion_only(init, t_a, g.disps[a], g.intrinsics, track.target, weight)
    return pose if pose is not None else t_a.cpu().clone()


def warped_depth(state: MapState, a: int, pose_k: torch.Tensor) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
    """``(inverse depth [h, w], measured bool [h, w])`` of a new keyframe at ``pose_k``: keyframe ``a``'s depth moved
    into it (see the module docstring); None when too little of the view gets a value."""
    h, w = state.ba_shape
    g = state.graph
    poses = torch.stack([g.poses[a].double(), pose_k.to(g.device).double()])
    R, t = edge_transforms(poses, torch.tensor([0]), torch.tensor([1]))  # camera a -> camera k
    d_a = g.disps[a].float().reshape(1, -1)  # [1, P]
    # homogeneous projection: Z = z_k * d_a, so the inverse depth in camera k is d_a / Z
    out = project_points(R.float(), t.float(), d_a, g.intrinsics, h, w, min_depth=1e-6)
    u, v = torch.round(out["u"][0]), torch.round(out["v"][0])
    ok = out["valid"][0] & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if int(ok.sum()) < MIN_WARPED * h * w:
        return None
    idx = (v[ok] * w + u[ok]).long()
    disp_k = d_a[0, ok] / out["z"][0, ok]
    disp = torch.zeros(h * w, device=g.device).scatter_reduce(0, idx, disp_k, reduce="amax")
    disp = disp.reshape(h, w)
    known_a = state.observed.masks.get(g.id_of(a))
    src = known_a.to(g.device).reshape(-1)[ok].float() if known_a is not None else torch.ones_like(disp_k)
    known = torch.zeros(h * w, device=g.device).scatter_reduce(0, idx, src, reduce="amax")
    return fill_holes(disp, disp <= 0, FILL_ROW_MIN_FRAC), known.reshape(h, w) > 0


def initial_depth(state: MapState, frontend, pose: torch.Tensor) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """``(inverse depth [h, w], measured mask or None)`` of the keyframe about to be added at ``pose`` (see the
    module docstring; None: nothing measured)."""
    h, w = state.ba_shape
    g = state.graph
    k_new = g.n
    if state.initialized and k_new > state.fragment_start:
        warped = warped_depth(state, k_new - 1, pose)
        if warped is not None:
            return warped
    guess = frontend.initial_depth(g, g.next_id) if k_new > 0 else None
    if guess is not None:
        return guess, None
    if k_new > 0:
        return torch.full((h, w), float(g.disps[k_new - 1].median())), None
    return torch.ones(h, w), None
