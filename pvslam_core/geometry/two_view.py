"""OpenCV's two-view RANSAC, with one behaviour for every OpenCV version.

Every essential-matrix fit in pvslam (the map initialisation, loop verification, the pose graph's loop check)
goes through :func:`find_essential`.  Why a wrapper: OpenCV 5.1 raises ``cv2.error`` from
``cv2.findEssentialMat`` when the correspondences are degenerate -- a camera that did not move (identical points),
a pure rotation, collinear points -- (``solvePoly``: "std::abs(coeffs[n].re) + std::abs(coeffs[n].im) >
DBL_EPSILON"), where 5.0 and 4.x returned a meaningless matrix.  A turn on the spot, a stopped car or a revisit
from the same place would have ended a run with that error; every caller already handles "no essential matrix".
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

__all__ = ["find_essential", "essential_motion", "translation_direction"]


def find_essential(p0: np.ndarray, p1: np.ndarray, K: np.ndarray, threshold: float,
                   prob: float = 0.999) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """``cv2.findEssentialMat(p0, p1, K, RANSAC, prob, threshold)`` for correspondences ``p0, p1 [N, 2]`` (pixels of
    the camera ``K [3, 3]``; ``threshold`` in the same pixels): ``(E, inlier mask)`` as OpenCV returns them (``E``
    may stack several ``3 x 3`` solutions), or ``(None, None)`` when OpenCV finds none or fails on degenerate data
    (see the module docstring)."""
    try:
        E, mask = cv2.findEssentialMat(p0, p1, K, method=cv2.RANSAC, prob=prob, threshold=float(threshold))
    except cv2.error:
        return None, None
    if E is None or mask is None or E.shape[0] < 3:
        return None, None
    return E, mask


def essential_motion(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R [3, 3], t [3])`` of ``X_1 = R X_0 + t`` from an essential matrix (the first ``3 x 3`` of OpenCV's stack:
    RANSAC's best): of its decompositions the smaller rotation -- the other is a half turn about the baseline, never
    the motion between two frames of one video -- and the unit translation, sign undecided (the caller's choice)."""
    R1, R2, t = cv2.decomposeEssentialMat(E[:3])
    return (R1 if np.trace(R1) >= np.trace(R2) else R2), t.reshape(3)


def translation_direction(p0: np.ndarray, p1: np.ndarray, K: np.ndarray, threshold: float,
                          min_parallax: float = 1.0, rotation: Optional[np.ndarray] = None,
                          max_rotation_deg: float = 3.0) -> Optional[np.ndarray]:
    """The unit translation ``t [3]`` of the motion ``X_1 = R X_0 + t`` (camera 0 -> camera 1) between two views'
    correspondences ``p0 -> p1 [N, 2]`` (pixels of ``K``), from their essential matrix alone: no depth, no map.  The
    sign is arbitrary.  None without a fit, when the fit's rotation is more than ``max_rotation_deg`` from an
    expected ``rotation [3, 3]`` (given), or when the inliers' median parallax (their displacement once the rotation
    is removed) is below ``min_parallax`` pixels: with little parallax RANSAC fits noise, typically with a rotation
    that is off and a large false "parallax", so both checks are needed."""
    E, mask = find_essential(p0, p1, K, threshold)
    if E is None:
        return None
    R, t = essential_motion(E)
    if rotation is not None:
        cos = (np.trace(R @ np.asarray(rotation, float).T) - 1.0) / 2.0
        if np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) > max_rotation_deg:
            return None
    inl = mask.reshape(-1) > 0
    if not inl.any():
        return None
    rays = np.c_[p0[inl], np.ones(int(inl.sum()))] @ np.linalg.inv(K).T @ R.T  # [n, 3] rotated into view 1
    rot_only = (rays[:, :2] / rays[:, 2:3]) * np.diag(K)[:2] + K[:2, 2]
    if float(np.median(np.linalg.norm(p1[inl] - rot_only, axis=1))) < min_parallax:
        return None
    return t / max(float(np.linalg.norm(t)), 1e-12)
