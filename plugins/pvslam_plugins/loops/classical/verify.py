"""Geometric verification of loop candidates: ORB matches (ratio test + mutual check) + essential-matrix RANSAC.

Keypoints are stored in *normalised* camera coordinates (undistorted with the keyframe's own intrinsics), so two
keyframes with different calibrations can be verified against each other.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from pvslam_core.types import Intrinsics


@dataclass
class OrbFeatures:
    points: np.ndarray  # float32 [N, 2] normalised camera coordinates (x/z, y/z)
    descriptors: np.ndarray  # uint8 [N, 32]
    focal: float  # mean focal length in pixels (converts the RANSAC threshold)

    @property
    def nbytes(self) -> int:
        return int(self.points.nbytes + self.descriptors.nbytes)


@dataclass
class Verification:
    accepted: bool
    matches: int  # tentative matches after the ratio / cross check
    inliers: int  # essential-matrix RANSAC inliers
    message: str = ""

    @property
    def ratio(self) -> float:
        return self.inliers / self.matches if self.matches else 0.0


_ORB_CACHE: dict[int, "cv2.ORB"] = {}


def _orb(n: int) -> "cv2.ORB":
    orb = _ORB_CACHE.get(n)
    if orb is None:
        orb = cv2.ORB_create(nfeatures=n, scaleFactor=1.2, nlevels=8, edgeThreshold=15, patchSize=31, fastThreshold=10)
        _ORB_CACHE[n] = orb
    return orb


def extract(gray: np.ndarray, intrinsics: Intrinsics, n_features: int = 1000) -> OrbFeatures:
    """ORB keypoints/descriptors of a uint8 grayscale image, keypoints undistorted and normalised."""
    if gray.dtype != np.uint8:
        gray = np.clip(gray, 0, 255).astype(np.uint8)
    kps, desc = _orb(n_features).detectAndCompute(gray, None)
    focal = 0.5 * (intrinsics.fx + intrinsics.fy)
    if desc is None or len(kps) == 0:
        return OrbFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), focal)
    px = np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 1, 2)
    K = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]], np.float64)
    dist = np.array(intrinsics.dist, np.float64) if intrinsics.has_distortion else None
    norm = cv2.undistortPoints(px, K, dist).reshape(-1, 2).astype(np.float32)
    return OrbFeatures(norm, np.ascontiguousarray(desc, dtype=np.uint8), focal)


def match(a: OrbFeatures, b: OrbFeatures, ratio: float = 0.8, cross_check: bool = True) -> np.ndarray:
    """int64 [M, 2] index pairs (into a, into b) passing the ratio test (and the mutual check)."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    fwd = bf.knnMatch(a.descriptors, b.descriptors, k=2)
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in fwd if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if not pairs:
        return np.zeros((0, 2), np.int64)
    out = np.array(pairs, dtype=np.int64)
    if cross_check:
        bwd = bf.match(b.descriptors, a.descriptors)
        back = np.full(len(b.descriptors), -1, np.int64)
        for m in bwd:
            back[m.queryIdx] = m.trainIdx
        out = out[back[out[:, 1]] == out[:, 0]]
    return out


def verify(
    a: OrbFeatures,
    b: OrbFeatures,
    *,
    min_inliers: int = 40,
    min_inlier_ratio: float = 0.3,
    ratio: float = 0.8,
    cross_check: bool = True,
    threshold_px: float = 1.5,
    seed: Optional[int] = 0,
) -> Verification:
    """Essential-matrix RANSAC between two keyframes' ORB features."""
    pairs = match(a, b, ratio, cross_check)
    n = len(pairs)
    if n < max(5, min_inliers):
        return Verification(False, n, 0, f"{n} tentative matches < {max(5, min_inliers)}")
    p1 = a.points[pairs[:, 0]].astype(np.float64)
    p2 = b.points[pairs[:, 1]].astype(np.float64)
    thr = threshold_px / (0.5 * (a.focal + b.focal))
    if seed is not None:
        cv2.setRNGSeed(int(seed))
    E, mask = cv2.findEssentialMat(p1, p2, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr)
    if E is None or mask is None:
        return Verification(False, n, 0, "essential matrix RANSAC failed")
    if E.shape[0] > 3:  # several solutions: keep the first
        E = E[:3]
    # no cheirality (recoverPose) filter: it is ill-conditioned for the near-zero baselines of good revisits
    inl = int(mask.sum())
    ok = inl >= min_inliers and inl >= min_inlier_ratio * n
    return Verification(ok, n, inl, f"{inl}/{n} inliers")
