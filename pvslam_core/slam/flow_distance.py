"""How far apart two keyframes are, in induced flow: the keyframe policy's redundancy test and the edge policy's
proximity-edge filter read it.

DROID-SLAM's frame distance (:func:`pvslam_core.geometry.projective.frame_distance`) is the *mean* induced flow
over all pixels, mostly translation-only (``beta = 0.3`` of the full flow).  Where most of the image is far away (a
wide street, sky, a highway) the mean stays small while the near road and vehicles move several BA px, so a
keyframe is kept when *either* the mean or a high quantile of the same per-pixel distance is large:
:func:`keyframe_distance` returns ``max(mean, q90 * thresh / max_flow)``, and the caller's one threshold test
(``< thresh``) reads "mean < thresh and q90 < max_flow" (docs/decisions.md: REDUNDANT_MAX_FLOW).

:func:`pair_flow_quantile` is the same quantile of the translation-only flow (the parallax), for the proximity edges
(docs/decisions.md: PROXIMITY_MAX_FLOW).

Poses are camera-to-world ``T_wc [7]``; depths are inverse depths at the BA resolution.
"""
from __future__ import annotations

import torch

from ..geometry.projective import edge_transforms, pixel_grid, project_points


def induced_flow(poses_wc: torch.Tensor, disp_i: torch.Tensor, intr: torch.Tensor, beta: float = 0.3,
                 min_depth: float = 0.25) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel DROID distance ``beta |full flow| + (1 - beta) |translation-only flow|`` ``[h*w]`` of keyframe
    ``i`` (``poses_wc[0]``, inverse depth ``disp_i [h, w]``) seen from ``poses_wc[1]``, and its valid mask."""
    h, w = disp_i.shape[-2:]
    dtype = disp_i.dtype
    R, t = edge_transforms(poses_wc.double(), torch.tensor([0]), torch.tensor([1]))
    R, t = R.to(disp_i.device, dtype), t.to(disp_i.device, dtype)
    d = disp_i.reshape(1, -1)
    full = project_points(R, t, d, intr.to(dtype), h, w, min_depth)
    tr = project_points(R, t, d, intr.to(dtype), h, w, min_depth, translation_only=True)
    grid = pixel_grid(h, w, disp_i.device, dtype).reshape(-1, 2)
    f_full = torch.sqrt((full["u"][0] - grid[:, 0]) ** 2 + (full["v"][0] - grid[:, 1]) ** 2)
    f_tr = torch.sqrt((tr["u"][0] - grid[:, 0]) ** 2 + (tr["v"][0] - grid[:, 1]) ** 2)
    return beta * f_full + (1 - beta) * f_tr, full["valid"][0] & tr["valid"][0]


def keyframe_distance(poses_wc: torch.Tensor, disp_i: torch.Tensor, intr: torch.Tensor, thresh: float,
                      max_flow: float, quantile: float = 0.9, min_valid: float = 0.75) -> float:
    """``max(mean, q * thresh / max_flow)`` of :func:`induced_flow` (BA px; see the module docstring), or the
    plain mean when ``max_flow <= 0``; 1000 when fewer than ``min_valid`` of the pixels stay in front of the
    second camera (as :func:`~pvslam_core.geometry.projective.frame_distance`)."""
    dist, valid = induced_flow(poses_wc, disp_i, intr)
    if float(valid.float().mean()) < min_valid:
        return 1000.0
    dv = dist[valid]
    mean = float(dv.mean())
    if max_flow <= 0:
        return mean
    return max(mean, float(torch.quantile(dv.float(), quantile)) * thresh / max_flow)


def pair_flow_quantile(poses_wc: torch.Tensor, disp_i: torch.Tensor, disp_j: torch.Tensor, intr: torch.Tensor,
                       quantile: float = 0.9, min_valid: float = 0.75) -> float:
    """The larger of the two directions' ``quantile`` of the *translation-only* induced flow (the parallax:
    :func:`induced_flow` with ``beta = 0``) between keyframes ``i`` (``poses_wc[0]``, inverse depth ``disp_i [h, w]``)
    and ``j`` (``poses_wc[1]``, ``disp_j``), BA px; 1000 when fewer than ``min_valid`` of either keyframe's pixels stay
    in front of the other camera (as :func:`keyframe_distance`).  Rotation is left out on purpose: its flow does not
    depend on the depth, so the frontend's flow started from the predicted motion follows it (a hand-held camera
    turning on the spot keeps its proximity edges); the parallax of a near field is what it cannot find."""
    out = 0.0
    for poses, disp in ((poses_wc, disp_i), (poses_wc.flip(0), disp_j)):
        dist, valid = induced_flow(poses, disp, intr, beta=0.0)
        if float(valid.float().mean()) < min_valid:
            return 1000.0
        out = max(out, float(torch.quantile(dist[valid].float(), quantile)))
    return out
