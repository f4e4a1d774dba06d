"""A dynamic cue that does not depend on the map: the two-view epipolar geometry of one keyframe pair's own flow.

The residual test of :mod:`.dynamic` judges a pixel against the *current estimate* (poses and depths).  Once that
estimate has been dragged by a large vehicle, the vehicle fits it and the static scene does not: on the busy street
residual, depth and cheirality tests against the estimate flag the static scene at half the rate of the movers
(bench/RESULTS.md, moving objects).  This cue asks the flow of a single pair of views instead: a robust
essential-matrix fit (:func:`fit_motion`: OpenCV RANSAC on the confident BA pixels, known intrinsics) takes the
static majority's relative motion, and :func:`judge` makes a pixel a candidate when

- its target is off its epipolar line (Sampson distance) by more than ``max(thresh, rel x the inliers' median)``
  BA px: vehicles crossing the view, turning, or off the camera's direction of travel, or
- its parallax points *towards* the epipole by more than ``back`` BA px: a point behind the camera under the fit
  (negative depth), which no static point can be -- a vehicle overtaking the camera or pulling away ahead of it.

Why this split (bench/RESULTS.md, issue 13 busy street, session 2026-12-02 b): with ground-truth masks cut down to
the moving pixels that fail these two tests under the *true* two-view motion, the busy-street tune seeds reached
0.8-2.9 % of the path (the whole ground-truth masks: 1.0-3.9 %; HEAD 1.6-17.6 %); cut down to the other moving
pixels, 1.0-9.7 %.  Movers that drive along the camera's direction at a steady speed pass the tests (they are a
static point at another depth) and drag the estimate less.

Candidates are grouped into coherent regions (:func:`.dynamic.group_regions`, as the residual cue).  No mask when the
pair has too little parallax to fit (a stopped camera: the essential matrix is then noise), when the fit keeps too
few inliers, or when the regions would cover more than ``max_fraction`` of the image.

Masks are bool ``[h, w]`` at the BA resolution, 1 = dynamic; they reach the weights through PV-SLAM eq. 4 like the
other cues.  Cost: about 1 ms for a fit (OpenCV RANSAC) and 0.5 ms for a judgement at 40x30 BA pixels.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from pvslam_core.geometry.two_view import essential_motion, find_essential

from .dynamic import group_regions

Motion = tuple[torch.Tensor, torch.Tensor]  # (R [3, 3], t [3] unit) float64, X_1 = R X_0 + t


def _judged(target: torch.Tensor, weight: torch.Tensor, min_conf: float):
    """The pixels of ``target [2, h, w]`` that can be judged (confident, landing inside the view): bool [h, w],
    and their source / target positions ``p0, p1 [n, 2]`` float64 BA px."""
    h, w = weight.shape[-2:]
    tgt = target.detach().to(torch.float64).cpu()
    u1, v1 = tgt[0], tgt[1]
    judged = ((weight.detach().cpu() > min_conf) & torch.isfinite(u1) & torch.isfinite(v1)
              & (u1 >= 0) & (u1 <= w - 1) & (v1 >= 0) & (v1 <= h - 1))  # [h, w]
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                            indexing="ij")
    return judged, torch.stack([xs[judged], ys[judged]], -1), torch.stack([u1[judged], v1[judged]], -1)


def _K(intr) -> np.ndarray:
    fx, fy, cx, cy = (float(v) for v in intr)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _parallax(p0: torch.Tensor, p1: torch.Tensor, intr, R: torch.Tensor, t: torch.Tensor):
    """For correspondences ``p0 -> p1 [n, 2]`` (BA px) under the motion ``(R, t)``: the Sampson distance ``[n]`` to
    the epipolar geometry, the parallax ``[n, 2]`` (the target minus where the rotation alone puts the pixel: a
    point at infinity) and the unit direction ``[n, 2]`` along which a static point's parallax points, all in BA px.

    A static point of depth Z has ``x1 - inf_pt = (t_xy - t_z inf_pt) / (Z r_z + t_z)``, ``r = R x0``: along
    ``t_xy - t_z inf_pt`` for any depth in front of both cameras (for forward motion: away from the focus of
    expansion)."""
    fx, fy, cx, cy = (float(v) for v in intr)
    ones = torch.ones(p0.shape[0], dtype=torch.float64)
    x0 = torch.stack([(p0[:, 0] - cx) / fx, (p0[:, 1] - cy) / fy, ones], -1)  # [n, 3] normalised rays
    x1 = torch.stack([(p1[:, 0] - cx) / fx, (p1[:, 1] - cy) / fy, ones], -1)
    f = 0.5 * (fx + fy)
    # Sampson distance to x1^T E x0 = 0, E = [t]_x R, in normalised coordinates scaled back by the focal length
    Ess = torch.linalg.cross(t[None].expand(3, 3), torch.eye(3, dtype=torch.float64), dim=-1).T @ R
    Ex0, Etx1 = x0 @ Ess.T, x1 @ Ess  # [n, 3]
    den = Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2
    samp = (x1 * Ex0).sum(-1).abs() / den.clamp_min(1e-18).sqrt() * f  # [n]
    Rx0 = x0 @ R.T
    inf_pt = Rx0[:, :2] / Rx0[:, 2:3]  # [n, 2]
    away = t[None, :2] - t[2] * inf_pt  # [n, 2]
    away = away / away.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return samp, (x1[:, :2] - inf_pt) * f, away


def fit_motion(target: torch.Tensor, weight: torch.Tensor, intr: tuple[float, float, float, float], *,
               min_conf: float = 0.5, ransac_px: float = 0.25, min_inliers: float = 0.5,
               max_points: int = 2000, prior: Optional[torch.Tensor] = None) -> Optional[Motion]:
    """The static majority's relative motion of one flow ``target [2, h, w]`` (absolute (u, v) in the other view's
    BA pixels of each pixel, confidence ``weight [h, w]``; only pixels above ``min_conf`` count): an essential
    matrix by RANSAC (``ransac_px`` BA px; intrinsics ``intr`` (fx, fy, cx, cy) at the BA resolution) and its
    decomposition (``prior [3]``: the expected translation direction, the previous pair's fit).  None with fewer than
    16 pixels or fewer than ``min_inliers`` of them fitting."""
    _, p0, p1 = _judged(target, weight, min_conf)
    n = p0.shape[0]
    if n < 16:
        return None
    # an even subsample keeps RANSAC's cost bounded on larger BA grids (deterministic: no random choice here)
    sel = torch.arange(0, n, max(1, -(-n // max_points)))
    a, b, K = p0[sel].numpy(), p1[sel].numpy(), _K(intr)
    E, inl = find_essential(a, b, K, ransac_px)
    if E is None or float((inl > 0).mean()) < min_inliers:
        return None
    # E[:3]: RANSAC's best of stacked solutions.  Of its four decompositions, the rotation is the smaller one (the
    # other differs by a half turn about the baseline: never two keyframes of one video).  The translation's sign
    # is the one closer to ``prior`` (the previous pair's fit: the direction of travel does not flip between two
    # keyframes) when that decides clearly, else the one that puts most inliers' parallax in front of the cameras.
    # Not cheirality counts alone (cv2.recoverPose): on the busy street a bus receding ahead is as epipolar-
    # consistent as the static scene and, with the static scene far, outvotes it -- the backward motion won, and
    # every static point then looked like it was behind the camera.
    R, t = (torch.from_numpy(np.ascontiguousarray(m)).double() for m in essential_motion(E))
    if prior is not None and float(prior.norm()) > 0 and abs(float(t @ prior)) > 0.5 * float(prior.norm()):
        flip = float(t @ prior) < 0
    else:  # the parallax of most inliers (above 0.05 BA px of noise) must point away from the epipole
        m = torch.from_numpy(inl.reshape(-1) > 0)
        _, par, away = _parallax(p0[sel][m], p1[sel][m], intr, R, t)
        signed = (par * away).sum(-1)
        flip = int((signed > 0.05).sum()) < int((signed < -0.05).sum())
    if flip:
        t = -t
    return R, t


def invert(motion: Motion) -> Motion:
    """The motion of the opposite direction (view 1 -> view 0)."""
    R, t = motion
    return R.T, -(R.T @ t)


def judge(target: torch.Tensor, weight: torch.Tensor, intr: tuple[float, float, float, float], motion: Motion, *,
          min_conf: float = 0.5, inlier_px: float = 0.25, thresh: float = 0.5, rel: float = 3.0, back: float = 0.5,
          min_parallax: float = 0.05) -> Optional[torch.Tensor]:
    """Candidate pixels bool ``[h, w]`` of the flow ``target [2, h, w]`` (as :func:`fit_motion`) under ``motion``,
    or None when the pair cannot be judged: the pixels within ``inlier_px`` of their epipolar line have a median
    parallax (flow minus the rotation's) below ``min_parallax`` BA px (too little translation to tell a mover from
    noise).  ``thresh`` / ``back`` in BA px (see the module docstring)."""
    h, w = weight.shape[-2:]
    judged, p0, p1 = _judged(target, weight, min_conf)
    n = p0.shape[0]
    if n < 16:
        return None
    R, t = motion
    samp, par, away = _parallax(p0, p1, intr, R, t)
    signed = (par * away).sum(-1)  # [n] BA px, > 0 for static points
    inl = samp < inlier_px
    if int(inl.sum()) < 8 or float(par[inl].norm(dim=-1).median()) < min_parallax:
        return None
    thr = max(float(thresh), rel * float(samp[inl].median()))
    out = torch.zeros(h, w, dtype=torch.bool)
    out[judged] = (samp > thr) | (signed < -back)
    return out


def epipolar_candidates(target: torch.Tensor, weight: torch.Tensor, intr: tuple[float, float, float, float], *,
                        min_conf: float = 0.5, ransac_px: float = 0.25, min_inliers: float = 0.5,
                        **kw) -> Optional[torch.Tensor]:
    """:func:`fit_motion` then :func:`judge` on the same flow (``kw``: judge's thresholds)."""
    motion = fit_motion(target, weight, intr, min_conf=min_conf, ransac_px=ransac_px, min_inliers=min_inliers)
    if motion is None:
        return None
    return judge(target, weight, intr, motion, min_conf=min_conf, inlier_px=ransac_px, **kw)


def regions(cand: Optional[torch.Tensor], *, min_area: int = 4, grow: int = 1,
            max_fraction: float = 0.5) -> Optional[torch.Tensor]:
    """Candidates (bool ``[h, w]``) grouped into coherent regions (:func:`.dynamic.group_regions`); None when
    ``cand`` is None or the regions cover more than ``max_fraction`` of the image (the fit, not the scene, is then
    in doubt)."""
    if cand is None:
        return None
    reg = group_regions(cand[None], min_area, grow)[0]
    return None if float(reg.float().mean()) > max_fraction else reg


def epipolar_mask(target: torch.Tensor, weight: torch.Tensor, intr: tuple[float, float, float, float], *,
                  min_area: int = 4, grow: int = 1, max_fraction: float = 0.5, **kw) -> Optional[torch.Tensor]:
    """The cue's dynamic mask bool ``[h, w]`` of one flow: :func:`epipolar_candidates` grouped by :func:`regions`."""
    return regions(epipolar_candidates(target, weight, intr, **kw), min_area=min_area, grow=grow,
                   max_fraction=max_fraction)
