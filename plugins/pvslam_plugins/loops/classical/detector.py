"""The ``classical`` loop detector: global-descriptor retrieval + ORB/essential-matrix verification."""
from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Optional

import cv2
import numpy as np

from pvslam_core.interfaces import LoopDetector
from pvslam_core.types import Frame, Intrinsics, LoopCandidate

from .config import ClassicalLoopConfig
from .descriptor import ImageLike, global_descriptor, to_gray
from .verify import OrbFeatures, Verification, extract, verify


@dataclass
class _Keyframe:
    frame_index: int
    timestamp: float
    jpeg: Optional[np.ndarray]  # grayscale JPEG of the (reduced) keyframe image, for lazy ORB extraction
    intrinsics: Optional[Intrinsics]  # of the stored image
    uid: int = 0  # unique within the detector (feature-cache key)
    hits: list[int] = field(default_factory=list)  # older keyframes this one verified against (before the
    # consecutive / NMS filters), for the consecutive-hit rule


class ClassicalLoopDetector(LoopDetector):
    """Keyframe database with a cosine-similarity retrieval step and geometric verification.

    ``add_keyframe(k, frame)`` must be called with ``k`` = the number of keyframes stored (the next index);
    ``remove_keyframe(k)`` shifts the later indices down, as in the frame graph.  Per keyframe it stores a float32
    descriptor (about 1.3 kB) and a grayscale JPEG of the image (about 20 kB at 320x240).  ORB features are
    extracted lazily, only for keyframes that take part in a verification, and cached (LRU, ``feature_cache``
    keyframes of about 40 B per keypoint), so a keyframe without loop candidates costs ~2 ms at 320x240.
    """

    def __init__(self, config: Optional[ClassicalLoopConfig] = None) -> None:
        self.config = config or ClassicalLoopConfig()
        self._kf: list[_Keyframe] = []
        self._desc = np.zeros((0, 0), np.float32)  # [capacity, D]; rows [0, len(self._kf)) valid
        self._times = np.zeros(0, np.float64)  # [capacity] keyframe timestamps, same rows
        self.accepted: list[LoopCandidate] = []  # every loop returned so far (indices kept current on removal)
        self.last_verifications: list[tuple[int, int, float, Verification]] = []  # (i, j, score, result) of the
        # last add_keyframe call, for diagnostics
        self.timings: dict[str, float] = {"describe": 0.0, "retrieve": 0.0, "store": 0.0, "features": 0.0,
                                          "verify": 0.0}
        self._features: "OrderedDict[int, OrbFeatures]" = OrderedDict()  # keyed by _Keyframe.uid
        self._next_uid = 0

    # --- descriptors ----------------------------------------------------------------------------------------
    def descriptor(self, image: ImageLike) -> np.ndarray:
        """The L2-normalised global descriptor (float32 [D]) of an image; cosine similarity = dot product."""
        c = self.config
        return global_descriptor(image, c.thumbnail_size, c.hog_cells, c.hog_bins, c.thumbnail_weight)

    def __len__(self) -> int:
        return len(self._kf)

    @property
    def descriptors(self) -> np.ndarray:
        """float32 [K, D] descriptors of the stored keyframes (a view)."""
        return self._desc[: len(self._kf)]

    def similarity_matrix(self) -> np.ndarray:
        """float32 [K, K] cosine similarities between all stored keyframes."""
        d = self.descriptors
        return d @ d.T

    def keyframe_frame_indices(self) -> list[int]:
        return [kf.frame_index for kf in self._kf]

    def _append_descriptor(self, d: np.ndarray, timestamp: float) -> None:
        n = len(self._kf)
        if self._desc.shape[1] != d.shape[0]:
            if n:
                raise ValueError("descriptor size changed between keyframes")
            self._desc = np.zeros((16, d.shape[0]), np.float32)
            self._times = np.zeros(16, np.float64)
        if n >= self._desc.shape[0]:
            grown = np.zeros((2 * self._desc.shape[0], self._desc.shape[1]), np.float32)
            grown[:n] = self._desc[:n]
            self._desc = grown
            times = np.zeros(len(grown), np.float64)
            times[:n] = self._times[:n]
            self._times = times
        self._desc[n] = d
        self._times[n] = timestamp

    # --- LoopDetector -------------------------------------------------------------------------------------------
    def add_keyframe(self, k: int, frame: Frame) -> list[LoopCandidate]:
        c = self.config
        if k != len(self._kf):
            raise ValueError(f"classical loop detector: add_keyframe({k}) but {len(self._kf)} keyframes are stored; "
                             "keyframes must be added in order (k = next index)")
        t0 = time.perf_counter()
        gray = to_gray(frame.image)
        if gray.dtype != np.uint8:
            gray = np.clip(gray, 0, 255).astype(np.uint8)
        d = self.descriptor(gray)
        t1 = time.perf_counter()
        self.timings["describe"] += t1 - t0

        candidates = self._retrieve(d, float(frame.timestamp))
        t2 = time.perf_counter()
        self.timings["retrieve"] += t2 - t1

        small, K = self._reduce(gray, frame.intrinsics) if c.verify else (None, None)
        jpeg = None
        if small is not None:
            ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, int(c.jpeg_quality)])
            jpeg = buf if ok else None
        kf = _Keyframe(int(frame.index), float(frame.timestamp), jpeg, K, uid=self._next_uid)
        self._next_uid += 1
        self._append_descriptor(d, float(frame.timestamp))
        self._kf.append(kf)
        self.timings["store"] += time.perf_counter() - t2

        self.last_verifications = []
        verified: list[LoopCandidate] = []
        for j, score in candidates:
            if not c.verify:
                verified.append(LoopCandidate(k, j, score, verified=False, inliers=0))
                continue
            if self._suppressed(k, j):  # would be dropped anyway: skip the expensive verification
                continue
            fa = self._get_features(kf, small)
            fb = self._get_features(self._kf[j])
            t3 = time.perf_counter()
            if fa is None or fb is None:
                continue
            res = verify(fa, fb, min_inliers=c.min_inliers, min_inlier_ratio=c.min_inlier_ratio,
                         ratio=c.ratio, cross_check=c.cross_check, threshold_px=c.ransac_threshold_px)
            self.timings["verify"] += time.perf_counter() - t3
            self.last_verifications.append((k, j, score, res))
            if res.accepted:
                verified.append(LoopCandidate(k, j, score, verified=True, inliers=res.inliers))

        kf.hits = [lc.j for lc in verified]
        out = [lc for lc in verified if self._consecutive_ok(k, lc.j) and not self._suppressed(k, lc.j)]
        self.accepted.extend(out)
        return out

    def _reduce(self, gray: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
        h, w = gray.shape
        s = min(1.0, self.config.store_max_side / float(max(h, w)))
        if s >= 1.0:
            return gray, K
        nw, nh = max(1, int(round(w * s))), max(1, int(round(h * s)))
        small = cv2.resize(gray, (nw, nh), interpolation=cv2.INTER_AREA)
        return small, K.scaled(nw / w, nh / h)

    def _get_features(self, kf: _Keyframe, gray: Optional[np.ndarray] = None) -> Optional[OrbFeatures]:
        key = kf.uid
        feats = self._features.get(key)
        if feats is not None:
            self._features.move_to_end(key)
            return feats
        if kf.intrinsics is None or (gray is None and kf.jpeg is None):
            return None
        t = time.perf_counter()
        if gray is None:
            gray = cv2.imdecode(kf.jpeg, cv2.IMREAD_GRAYSCALE)
        feats = extract(gray, kf.intrinsics, self.config.orb_features)
        self.timings["features"] += time.perf_counter() - t
        self._features[key] = feats
        while len(self._features) > self.config.feature_cache:
            self._features.popitem(last=False)
        return feats

    def remove_keyframe(self, k: int) -> None:
        n = len(self._kf)
        if not 0 <= k < n:
            raise IndexError(f"classical loop detector: remove_keyframe({k}) with {n} keyframes stored")
        self._features.pop(self._kf[k].uid, None)
        del self._kf[k]
        self._desc[k : n - 1] = self._desc[k + 1 : n]
        self._times[k : n - 1] = self._times[k + 1 : n]
        for kf in self._kf:
            kf.hits = [j - (j > k) for j in kf.hits if j != k]
        kept = []
        for lc in self.accepted:
            if lc.i == k or lc.j == k:
                continue
            lc.i -= lc.i > k
            lc.j -= lc.j > k
            kept.append(lc)
        self.accepted = kept

    # --- steps -------------------------------------------------------------------------------------------------
    def _retrieve(self, d: np.ndarray, timestamp: float) -> list[tuple[int, float]]:
        """Best older keyframes outside the temporal exclusion window with similarity >= threshold."""
        c = self.config
        n = len(self._kf)
        last = n - 1 - c.exclude_recent  # newest index allowed by the keyframe window (new keyframe has index n)
        if last < 0:
            return []
        sims = self._desc[: last + 1] @ d
        times = self._times[: last + 1]
        ok = (sims >= c.threshold) & (timestamp - times >= c.min_time_gap)
        idx = np.nonzero(ok)[0]
        if len(idx) == 0:
            return []
        idx = idx[np.argsort(-sims[idx], kind="stable")][: c.max_candidates]
        return [(int(j), float(sims[j])) for j in idx]

    def _consecutive_ok(self, k: int, j: int) -> bool:
        c = self.config
        for m in range(1, c.consecutive):
            if k - m < 0:
                return False
            if not any(abs(j - jp) <= c.consecutive_tolerance + m for jp in self._kf[k - m].hits):
                return False
        return True

    def _suppressed(self, k: int, j: int) -> bool:
        n = self.config.nms_keyframes
        if n <= 0:
            return False
        return any(lc.i != k and abs(lc.i - k) <= n and abs(lc.j - j) <= n for lc in self.accepted)


def make_loop_detector(config: ClassicalLoopConfig, context: Any = None) -> ClassicalLoopDetector:
    return ClassicalLoopDetector(config)
