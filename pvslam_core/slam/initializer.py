"""Monocular map initialisation from two views: model selection (homography or essential matrix, as ORB-SLAM),
RANSAC, cheirality check and triangulation (OpenCV).

Given dense correspondences from one keyframe to a later keyframe at the BA resolution, estimate the relative pose
and the inverse depth of the first view.  Both models are fitted (RANSAC) and scored as ORB-SLAM does (the
truncated chi-square score of the symmetric transfer errors, ``R_H = S_H / (S_H + S_F)``): with ``R_H > 0.45``
the scene is (nearly) planar or the motion nearly a pure rotation and the homography is decomposed (the
decomposition whose triangulated points lie in front of both views, with the smallest reprojection error); else
the essential matrix gives the pose.  Either way the pair must show enough parallax.  The map scale is arbitrary
in monocular SLAM; it is fixed here so that the median inverse depth of the first view is 1.

:func:`two_view_init_why` also says why a pair was declined (the mapper prints it while it keeps trying).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..geometry.lie import se3_from_matrix

LOG = logging.getLogger("pvslam.init")


@dataclass
class TwoViewInit:
    pose_wc: torch.Tensor  # float64 [7] pose of the second view; the first is the identity
    disp0: torch.Tensor  # float32 [h, w] inverse depth of the first view
    inliers: int
    parallax_deg: float
    model: str = "E"  # "E" (essential matrix) or "H" (homography)


def two_view_init(
    target: torch.Tensor,  # [2, h, w] positions in view 1 of view-0 pixels (BA resolution)
    weight: torch.Tensor,  # [2, h, w]
    intr: torch.Tensor,  # [4] fx fy cx cy at the BA resolution
    min_inliers: int = 60,
    min_parallax_deg: float = 1.0,
    ransac_px: float = 0.3,
) -> Optional[TwoViewInit]:
    """The two-view initialisation of a keyframe pair, or None (see :func:`two_view_init_why`)."""
    return two_view_init_why(target, weight, intr, min_inliers, min_parallax_deg, ransac_px)[0]


def two_view_init_why(
    target: torch.Tensor,
    weight: torch.Tensor,
    intr: torch.Tensor,
    min_inliers: int = 60,
    min_parallax_deg: float = 1.0,
    ransac_px: float = 0.3,
    homography_ratio: float = 0.45,
) -> tuple[Optional[TwoViewInit], str]:
    """``(init or None, reason)``: the reason says why the pair was declined ("" on success)."""
    import cv2

    h, w = target.shape[-2:]
    ys, xs = np.mgrid[0:h, 0:w]
    p0 = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)  # [P, 2]
    p1 = target.detach().cpu().double().numpy().reshape(2, -1).T  # [P, 2]
    good = (weight.detach().cpu().numpy().reshape(2, -1).min(0) > 0.5) & np.isfinite(p1).all(1)
    if good.sum() < min_inliers:
        return None, f"{int(good.sum())} confident correspondences < {min_inliers} (the views do not overlap)"
    p0g, p1g = p0[good], p1[good]
    fx, fy, cx, cy = [float(v) for v in intr.detach().cpu()]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    if float(np.median(np.linalg.norm(p1g - p0g, axis=1))) < 1e-3:
        return None, "no motion between the views"
    E, mask = cv2.findEssentialMat(p0g, p1g, K, method=cv2.RANSAC, prob=0.999, threshold=ransac_px)
    if E is None or E.shape != (3, 3):
        return None, "no essential matrix found"
    H, _ = cv2.findHomography(p0g, p1g, cv2.RANSAC, 2.0 * ransac_px)
    r_h = homography_score_ratio(H, E, p0g, p1g, K, sigma=max(ransac_px, 0.5)) if H is not None else 0.0
    cands = []  # (R, t, inlier mask) candidates from the chosen model
    model = "H" if r_h > homography_ratio else "E"
    if model == "E":
        n_in, R, t, mask2 = cv2.recoverPose(E, p0g, p1g, K, mask=mask.copy())
        if n_in < min_inliers:
            return None, f"{n_in} essential-matrix inliers in front of both views < {min_inliers}"
        cands.append((R, t, mask2.ravel() > 0))
    else:
        n_sol, Rs, ts, _ = cv2.decomposeHomographyMat(H, K)
        err = _transfer_error(H, p0g, p1g)
        inl = err < 2.0 * ransac_px
        for R, t in zip(Rs, ts):
            if float(np.linalg.norm(t)) > 1e-9:
                cands.append((R, t / np.linalg.norm(t), inl))
    best = None
    for R, t, inl in cands:
        tri = _triangulate(K, R, t, p0g[inl], p1g[inl])
        if tri is None:
            continue
        X, z_ok, err = tri
        score = (int(z_ok.sum()), -err)
        if best is None or score > best[0]:
            best = (score, R, t, inl, X, z_ok)
    if best is None or best[0][0] < min_inliers:
        return None, f"too few points triangulate in front of both views ({model} model)"
    _, R, t, inl, X, ok = best
    c1 = (-R.T @ t).ravel()  # centre of view 1 in view-0 coordinates
    ray0 = X / np.linalg.norm(X, axis=1, keepdims=True)
    ray1 = (X - c1) / np.linalg.norm(X - c1, axis=1, keepdims=True)
    parallax = np.degrees(np.arccos(np.clip((ray0 * ray1).sum(1), -1, 1)))
    med_par = float(np.median(parallax[ok]))
    if med_par < min_parallax_deg:
        what = "mostly a rotation or a far scene" if model == "H" else "too short a baseline"
        return None, f"median parallax {med_par:.2f} deg < {min_parallax_deg:.2f} ({what}; R_H {r_h:.2f})"
    z = X[:, 2]
    disp_pts = 1.0 / z[ok]
    scale = float(np.median(disp_pts))  # make the median inverse depth 1
    disp0 = np.full(h * w, 1.0, dtype=np.float64)
    idx = np.flatnonzero(good)[inl][ok]
    disp0[idx] = disp_pts / scale
    disp0 = np.clip(disp0, 1e-3, 1e3)
    # unfilled pixels: a median filter of the filled map is overkill; use the median (=1)
    T_c1_c0 = np.eye(4)
    T_c1_c0[:3, :3] = R
    T_c1_c0[:3, 3] = t.ravel() * scale  # inverse depths were divided by `scale`, so depths and translation grow by it
    T_wc1 = np.linalg.inv(T_c1_c0)
    pose = se3_from_matrix(torch.from_numpy(T_wc1))
    LOG.info("two-view initialisation (%s model, R_H %.2f): %d inliers, median parallax %.2f deg", model, r_h,
             int(ok.sum()), med_par)
    return TwoViewInit(pose, torch.from_numpy(disp0.reshape(h, w)).float(), int(ok.sum()), med_par, model), ""


def _transfer_error(H: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Symmetric transfer error ``max(|p1 - H p0|, |p0 - H^-1 p1|)`` [N] in pixels."""
    def apply(M, p):
        q = np.hstack([p, np.ones((len(p), 1))]) @ M.T
        return q[:, :2] / np.where(np.abs(q[:, 2:]) < 1e-12, 1e-12, q[:, 2:])

    Hinv = np.linalg.inv(H)
    return np.maximum(np.linalg.norm(p1 - apply(H, p0), axis=1), np.linalg.norm(p0 - apply(Hinv, p1), axis=1))


def homography_score_ratio(H: np.ndarray, E: np.ndarray, p0: np.ndarray, p1: np.ndarray, K: np.ndarray,
                           sigma: float = 0.5) -> float:
    """ORB-SLAM's model selection ratio ``R_H = S_H / (S_H + S_F)``: ``S_M`` sums, over both transfer directions
    of every correspondence, ``5.991 - e^2 / sigma^2`` where that is positive (``e``: the transfer error of the
    homography; the distance to the epipolar line for the fundamental matrix ``K^-T E K^-1``, whose chi-square
    gate is 3.841 for one degree of freedom but whose score uses the same 5.991 so both models compete fairly)."""
    th_score, th_f = 5.991, 3.841
    hp0 = np.hstack([p0, np.ones((len(p0), 1))])
    hp1 = np.hstack([p1, np.ones((len(p1), 1))])

    def h_err(M, a, b):
        q = a @ M.T
        q = q[:, :2] / np.where(np.abs(q[:, 2:]) < 1e-12, 1e-12, q[:, 2:])
        return ((b[:, :2] - q) ** 2).sum(1) / sigma ** 2

    s_h = 0.0
    for e2 in (h_err(H, hp0, hp1), h_err(np.linalg.inv(H), hp1, hp0)):
        s_h += float(np.where(e2 < th_score, th_score - e2, 0.0).sum())
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ E @ Kinv
    s_f = 0.0
    for l_, x in ((hp0 @ F.T, hp1), (hp1 @ F, hp0)):  # epipolar lines in view 1 (of p0) and in view 0 (of p1)
        e2 = (l_ * x).sum(1) ** 2 / np.maximum(l_[:, 0] ** 2 + l_[:, 1] ** 2, 1e-12) / sigma ** 2
        s_f += float(np.where(e2 < th_f, th_score - e2, 0.0).sum())
    return s_h / max(s_h + s_f, 1e-12)


def _triangulate(K: np.ndarray, R: np.ndarray, t: np.ndarray, p0: np.ndarray, p1: np.ndarray):
    """Points ``X [M, 3]`` (view 0), the mask of those in front of both views, and the median reprojection error
    of those in view 1; None without points."""
    import cv2

    if len(p0) == 0:
        return None
    P0 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = K @ np.hstack([R, t.reshape(3, 1)])
    X = cv2.triangulatePoints(P0, P1, p0.T, p1.T)  # [4, M]
    X = (X[:3] / np.where(np.abs(X[3:]) < 1e-12, 1e-12, X[3:])).T  # [M, 3] in view 0
    X1 = X @ R.T + t.reshape(1, 3)
    ok = (X[:, 2] > 0) & (X1[:, 2] > 0) & np.isfinite(X).all(1)
    if not ok.any():
        return X, ok, float("inf")
    q = X1[ok] @ K.T
    err = np.linalg.norm(q[:, :2] / q[:, 2:] - p1[ok], axis=1)
    return X, ok, float(np.median(err))
