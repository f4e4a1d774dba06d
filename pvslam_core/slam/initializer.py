"""Monocular map initialisation from two views: essential matrix + triangulation (OpenCV).

Given dense correspondences from keyframe 0 to a later keyframe at the BA resolution, estimate the relative pose
(RANSAC essential matrix, cheirality check) and the inverse depth of keyframe 0.  The map scale is arbitrary in
monocular SLAM; it is fixed here so that the median inverse depth of keyframe 0 is 1.
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


def two_view_init(
    target: torch.Tensor,  # [2, h, w] positions in view 1 of view-0 pixels (BA resolution)
    weight: torch.Tensor,  # [2, h, w]
    intr: torch.Tensor,  # [4] fx fy cx cy at the BA resolution
    min_inliers: int = 60,
    min_parallax_deg: float = 1.0,
    ransac_px: float = 0.3,
) -> Optional[TwoViewInit]:
    import cv2

    h, w = target.shape[-2:]
    ys, xs = np.mgrid[0:h, 0:w]
    p0 = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)  # [P, 2]
    p1 = target.detach().cpu().double().numpy().reshape(2, -1).T  # [P, 2]
    good = (weight.detach().cpu().numpy().reshape(2, -1).min(0) > 0.5) & np.isfinite(p1).all(1)
    if good.sum() < min_inliers:
        LOG.debug("two-view init: %d confident correspondences < %d", int(good.sum()), min_inliers)
        return None
    p0g, p1g = p0[good], p1[good]
    fx, fy, cx, cy = [float(v) for v in intr.detach().cpu()]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    E, mask = cv2.findEssentialMat(p0g, p1g, K, method=cv2.RANSAC, prob=0.999, threshold=ransac_px)
    if E is None or E.shape != (3, 3):
        return None
    n_in, R, t, mask2 = cv2.recoverPose(E, p0g, p1g, K, mask=mask.copy())
    if n_in < min_inliers:
        LOG.debug("two-view init: %d inliers after the cheirality check < %d", n_in, min_inliers)
        return None
    inl = mask2.ravel() > 0
    P0 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = K @ np.hstack([R, t])
    X = cv2.triangulatePoints(P0, P1, p0g[inl].T, p1g[inl].T)  # [4, M]
    X = (X[:3] / X[3:]).T  # [M, 3] in view 0
    c1 = (-R.T @ t).ravel()  # centre of view 1 in view-0 coordinates
    ray0 = X / np.linalg.norm(X, axis=1, keepdims=True)
    ray1 = (X - c1) / np.linalg.norm(X - c1, axis=1, keepdims=True)
    parallax = np.degrees(np.arccos(np.clip((ray0 * ray1).sum(1), -1, 1)))
    z = X[:, 2]
    ok = (z > 0) & np.isfinite(z)
    if ok.sum() < min_inliers:
        return None
    med_par = float(np.median(parallax[ok]))
    if med_par < min_parallax_deg:
        LOG.debug("two-view init: median parallax %.2f deg < %.2f", med_par, min_parallax_deg)
        return None
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
    LOG.info("two-view initialisation: %d inliers, median parallax %.2f deg", int(ok.sum()), med_par)
    return TwoViewInit(pose, torch.from_numpy(disp0.reshape(h, w)).float(), int(ok.sum()), med_par)
