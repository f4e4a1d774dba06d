"""Geometric verification of loop candidates, shared by every loop detector (``classical``, ``deit``).

* :func:`extract` / :func:`match` / :func:`verify`: ORB matches (ratio test + mutual check) + essential-matrix
  RANSAC between two keyframes.  Keypoints are stored in *normalised* camera coordinates (undistorted with the
  keyframe's own intrinsics), so two keyframes with different calibrations can be verified against each other.
* :class:`VerificationConfig`: the config fields of the above (a mixin of each detector's flat config).
* :class:`KeyframeVerifier`: what a detector keeps per keyframe id to verify later (a reduced grayscale JPEG and
  its intrinsics), with ORB features extracted lazily, only for keyframes that take part in a verification, and
  cached (LRU).  A keyframe that never has a candidate costs one JPEG encode (~1 ms at 320x240).

Which verified candidates close a loop is the mapper's loop policy (:mod:`pvslam_core.slam.loops`), not this.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, ClassVar, Optional, Union

import cv2
import numpy as np
import torch
from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_core.geometry.two_view import find_essential
from pvslam_core.imaging import to_gray  # noqa: F401  (the classical detector reads its images with it)
from pvslam_core.types import Intrinsics

ImageLike = Union[torch.Tensor, np.ndarray]

#: ORB keypoints per keyframe (extracted lazily; matching cost grows with its square); min_inliers is set for it
ORB_FEATURES = 500
#: keyframe images are stored (grayscale JPEG) with the longer side reduced to at most this many pixels
STORE_MAX_SIDE = 640
#: JPEG quality of the stored keyframe images
JPEG_QUALITY = 90
#: ORB features of at most this many keyframes are kept in memory (LRU)
FEATURE_CACHE = 256
#: Lowe ratio test on Hamming distances
RATIO = 0.8
#: keep only mutual nearest-neighbour ORB matches
CROSS_CHECK = True
#: essential-matrix RANSAC threshold in pixels of the stored keyframe image
RANSAC_THRESHOLD_PX = 1.5


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
    # the inliers' spread in the first view over that in the second (RMS distance from their centroid, normalised
    # coordinates): < 1 when the first view sees the matched structure from farther away (a smaller image of it)
    spread: float = 1.0

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
    E, mask = find_essential(p1, p2, np.eye(3), thr)
    if E is None:  # (find_essential returns no mask without a matrix)
        return Verification(False, n, 0, "essential matrix RANSAC failed")
    if E.shape[0] > 3:  # several solutions: keep the first
        E = E[:3]
    # no cheirality (recoverPose) filter: it is ill-conditioned for the near-zero baselines of good revisits
    inl = int(mask.sum())
    ok = inl >= min_inliers and inl >= min_inlier_ratio * n
    m = mask.reshape(-1) > 0
    s1, s2 = (float(np.sqrt(((p[m] - p[m].mean(0)) ** 2).sum(1).mean())) if inl else 0.0 for p in (p1, p2))
    return Verification(ok, n, inl, f"{inl}/{n} inliers", spread=s1 / s2 if s2 > 0 else 1.0)


# ------------------------------------------------------------------------------------------------ config --
class VerificationConfig(PluginConfig):
    """Geometric-verification fields of a loop detector's (flat) config; the matching settings are the constants
    above."""

    verify: bool = Field(
        True, description="geometric verification (ORB + essential-matrix RANSAC); false: retrieval-only candidates "
        "(verified = None), accepted on score when loop_closure.accept_unverified (false loops at look-alikes)")
    min_inliers: int = Field(
        80, ge=5, description="accept a candidate when the essential-matrix RANSAC keeps at least this many ORB "
        "matches; set for 500 ORB keypoints per keyframe (docs/decisions.md: loop.min_inliers)")
    min_inlier_ratio: float = Field(
        0.5, ge=0.0, le=1.0, description="... and at least this fraction of the tentative ORB matches")
    retired: ClassVar[dict[str, Any]] = {"orb_features": ORB_FEATURES, "store_max_side": STORE_MAX_SIDE,
                                         "jpeg_quality": JPEG_QUALITY, "feature_cache": FEATURE_CACHE,
                                         "ratio": RATIO, "cross_check": CROSS_CHECK,
                                         "ransac_threshold_px": RANSAC_THRESHOLD_PX}


# ------------------------------------------------------------------------------------------- keyframes --
@dataclass
class _Stored:
    jpeg: Optional[np.ndarray]  # grayscale JPEG of the (reduced) keyframe image
    intrinsics: Intrinsics  # of the stored image


class KeyframeVerifier:
    """Per-keyframe-id storage for verification and the pairwise check (see the module docstring).

    ``add(kf_id, image, intrinsics)`` stores a keyframe; ``verify(i_id, j_id)`` checks a pair (None when a side
    cannot be verified: unknown id, no intrinsics); ``remove(kf_id)`` forgets one.  The newest keyframe's reduced
    image is also kept decoded, since it is the one queried next.  ``timings`` accumulates seconds per step.
    """

    def __init__(self, config: Optional[VerificationConfig] = None) -> None:
        self.config = config or VerificationConfig()
        self._kf: dict[int, _Stored] = {}
        self._newest: Optional[tuple[int, np.ndarray]] = None  # (id, reduced gray)
        self._features: "OrderedDict[int, OrbFeatures]" = OrderedDict()  # LRU, keyed by keyframe id
        self.timings: dict[str, float] = {"store": 0.0, "features": 0.0, "verify": 0.0}

    def __len__(self) -> int:
        return len(self._kf)

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._kf

    def add(self, kf_id: int, image: ImageLike, intrinsics: Optional[Intrinsics]) -> None:
        """Store keyframe ``kf_id``: ``image`` RGB ``[3, H, W]`` (torch) / ``[H, W, 3]`` or grayscale."""
        if intrinsics is None:  # nothing to verify with; the keyframe simply never verifies
            return
        t0 = time.perf_counter()
        gray = to_gray(image)
        small, K = self._reduce(gray, intrinsics)
        ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, int(JPEG_QUALITY)])
        self._kf[int(kf_id)] = _Stored(buf if ok else None, K)
        self._newest = (int(kf_id), small)
        self.timings["store"] += time.perf_counter() - t0

    def remove(self, kf_id: int) -> None:
        self._kf.pop(int(kf_id), None)
        self._features.pop(int(kf_id), None)
        if self._newest is not None and self._newest[0] == int(kf_id):
            self._newest = None

    def verify(self, i_id: int, j_id: int) -> Optional[Verification]:
        fa, fb = self.features(i_id), self.features(j_id)
        if fa is None or fb is None:
            return None
        c = self.config
        t = time.perf_counter()
        res = verify(fa, fb, min_inliers=c.min_inliers, min_inlier_ratio=c.min_inlier_ratio, ratio=RATIO,
                     cross_check=CROSS_CHECK, threshold_px=RANSAC_THRESHOLD_PX)
        self.timings["verify"] += time.perf_counter() - t
        return res

    def features(self, kf_id: int) -> Optional[OrbFeatures]:
        """ORB features of a stored keyframe (extracted on first use, LRU-cached); None if it is not stored."""
        key = int(kf_id)
        feats = self._features.get(key)
        if feats is not None:
            self._features.move_to_end(key)
            return feats
        kf = self._kf.get(key)
        if kf is None:
            return None
        t = time.perf_counter()
        if self._newest is not None and self._newest[0] == key:
            gray = self._newest[1]
        elif kf.jpeg is not None:
            gray = cv2.imdecode(kf.jpeg, cv2.IMREAD_GRAYSCALE)
        else:
            return None
        feats = extract(gray, kf.intrinsics, ORB_FEATURES)
        self.timings["features"] += time.perf_counter() - t
        self._features[key] = feats
        while len(self._features) > FEATURE_CACHE:
            self._features.popitem(last=False)
        return feats

    def _reduce(self, gray: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
        h, w = gray.shape
        s = min(1.0, STORE_MAX_SIDE / float(max(h, w)))
        if s >= 1.0:
            return gray, K
        nw, nh = max(1, int(round(w * s))), max(1, int(round(h * s)))
        small = cv2.resize(gray, (nw, nh), interpolation=cv2.INTER_AREA)
        return small, K.scaled(nw / w, nh / h)
