"""The ``classical`` loop detector: global-descriptor retrieval + ORB/essential-matrix verification."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np

from pvslam_core.interfaces import LoopDetector
from pvslam_core.types import Frame, LoopCandidate

from ..verification import KeyframeVerifier, Verification
from .config import ClassicalLoopConfig
from .descriptor import HOG_BINS, HOG_CELLS, THUMBNAIL_SIZE, THUMBNAIL_WEIGHT, ImageLike, global_descriptor, to_gray

#: adaptive threshold (ORB-SLAM's rule): the new keyframe's similarity to this many predecessors may lower it
ADAPTIVE_NEIGHBOURS = 2
#: the adaptive threshold never goes below this similarity
ADAPTIVE_FLOOR = 0.5
#: a candidate below ``threshold`` passes only when the new view sees the matched structure at least this large
#: relative to the old view (inlier spread new / old): a revisit of the spot (docs/decisions.md: ADAPTIVE_MIN_SPREAD)
ADAPTIVE_MIN_SPREAD = 0.9


@dataclass
class _Keyframe:
    kf_id: int  # stable keyframe id (the graph's)
    frame_index: int
    timestamp: float


class ClassicalLoopDetector(LoopDetector):
    """Keyframe database with a cosine-similarity retrieval step and geometric verification.

    ``add_keyframe(id, frame)`` describes and stores a keyframe (ids in time order); ``query(id, skip)`` returns
    its verified candidates (or, with ``verify = false``, retrieval-only candidates with ``verified = None``).
    Acceptance (consecutive hits, suppression near accepted loops, orientation) is the mapper's loop policy; its
    ``skip`` predicate spares the verification of candidates it would refuse anyway.  Per keyframe the detector
    stores a float32 descriptor (about 1.3 kB) and, for the shared :class:`~..verification.KeyframeVerifier`, a
    grayscale JPEG of the image (about 20 kB at 320x240).  ORB features are extracted lazily, only for keyframes
    that take part in a verification, and cached (LRU, ``FEATURE_CACHE`` keyframes of about 40 B per keypoint), so
    a keyframe without loop candidates costs ~2 ms.
    """

    def __init__(self, config: Optional[ClassicalLoopConfig] = None) -> None:
        self.config = config or ClassicalLoopConfig()
        self._kf: list[_Keyframe] = []  # rows in time order; a removed keyframe's row is deleted
        self._desc = np.zeros((0, 0), np.float32)  # [capacity, D]; rows [0, len(self._kf)) valid
        self._times = np.zeros(0, np.float64)  # [capacity] keyframe timestamps, same rows
        self.verifier = KeyframeVerifier(self.config) if self.config.verify else None
        self.last_verifications: list[tuple[int, int, float, Verification]] = []  # (i, j, score, result) of the
        # last query (stable ids), for diagnostics
        self._timings: dict[str, float] = {"describe": 0.0, "retrieve": 0.0}

    @property
    def timings(self) -> dict[str, float]:
        """Seconds spent per step: describe, retrieve (here), store, features, verify (the verifier's)."""
        v = self.verifier.timings if self.verifier is not None else {"store": 0.0, "features": 0.0, "verify": 0.0}
        return {**self._timings, **v}

    # --- descriptors ----------------------------------------------------------------------------------------
    def descriptor(self, image: ImageLike) -> np.ndarray:
        """The L2-normalised global descriptor (float32 [D]) of an image; cosine similarity = dot product."""
        return global_descriptor(image, THUMBNAIL_SIZE, HOG_CELLS, HOG_BINS, THUMBNAIL_WEIGHT)

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

    def keyframe_ids(self) -> list[int]:
        return [kf.kf_id for kf in self._kf]

    def keyframe_frame_indices(self) -> list[int]:
        return [kf.frame_index for kf in self._kf]

    def _row(self, kf_id: int) -> int:
        for r in range(len(self._kf) - 1, -1, -1):  # queries are for recent keyframes
            if self._kf[r].kf_id == kf_id:
                return r
        raise KeyError(f"classical loop detector: keyframe id {kf_id} is not stored")

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
    def add_keyframe(self, kf_id: int, frame: Frame) -> None:
        if self._kf and kf_id <= self._kf[-1].kf_id:
            raise ValueError(f"classical loop detector: keyframe id {kf_id} after {self._kf[-1].kf_id}; keyframes "
                             "must be added in time order")
        t0 = time.perf_counter()
        gray = to_gray(frame.image)
        if gray.dtype != np.uint8:
            gray = np.clip(gray, 0, 255).astype(np.uint8)
        d = self.descriptor(gray)
        self._timings["describe"] += time.perf_counter() - t0
        if self.verifier is not None:
            self.verifier.add(int(kf_id), gray, frame.intrinsics)
        self._append_descriptor(d, float(frame.timestamp))
        self._kf.append(_Keyframe(int(kf_id), int(frame.index), float(frame.timestamp)))

    def query(self, kf_id: int, skip: Optional[Callable[[int], bool]] = None) -> list[LoopCandidate]:
        r = self._row(kf_id)
        t1 = time.perf_counter()
        candidates = self._retrieve(r)
        self._timings["retrieve"] += time.perf_counter() - t1
        self.last_verifications = []
        out: list[LoopCandidate] = []
        for j_row, score in candidates:
            j_id = self._kf[j_row].kf_id
            if self.verifier is None:
                out.append(LoopCandidate(kf_id, j_id, score, verified=None, inliers=0))
                continue
            if skip is not None and skip(j_id):  # the policy would refuse it: skip the expensive verification
                continue
            res = self.verifier.verify(kf_id, j_id)
            if res is None:  # a side without intrinsics: cannot be verified
                continue
            self.last_verifications.append((kf_id, j_id, score, res))
            ok = bool(res.accepted)
            if ok and score < self.config.threshold and res.spread < ADAPTIVE_MIN_SPREAD:
                ok = False  # retrieved only through the adaptive threshold, and seen from farther away: _threshold
            out.append(LoopCandidate(kf_id, j_id, score, verified=ok, inliers=res.inliers))
        return out

    def on_keyframe_removed(self, kf_id: int) -> None:
        try:
            r = self._row(kf_id)
        except KeyError:
            return
        n = len(self._kf)
        if self.verifier is not None:
            self.verifier.remove(kf_id)
        del self._kf[r]
        self._desc[r : n - 1] = self._desc[r + 1 : n]
        self._times[r : n - 1] = self._times[r + 1 : n]

    # --- steps -------------------------------------------------------------------------------------------------
    def _threshold(self, r: int) -> float:
        """The retrieval threshold of row ``r``: ``threshold``, or the lowest similarity of the keyframe to its
        ``ADAPTIVE_NEIGHBOURS`` predecessors when lower (but not below ``ADAPTIVE_FLOOR``).  ORB-SLAM's rule (a loop
        candidate must look at least as similar as the keyframe's own neighbours do): a fixed threshold suits one
        camera and scene, and a hand-held camera's revisit of a spot scores as low as its neighbours a few frames
        apart.  Geometric verification still decides, and for these candidates also ``ADAPTIVE_MIN_SPREAD``: a
        lower threshold also admits verified views of the place from far away, whose loop BA bends the map
        (docs/decisions.md: ADAPTIVE_MIN_SPREAD)."""
        c = self.config
        if ADAPTIVE_NEIGHBOURS <= 0 or r == 0:
            return c.threshold
        nb = self._desc[max(0, r - ADAPTIVE_NEIGHBOURS): r] @ self._desc[r]
        return min(c.threshold, max(ADAPTIVE_FLOOR, float(nb.min())))  # only ever lowers `threshold`

    def _retrieve(self, r: int) -> list[tuple[int, float]]:
        """Best older rows outside the temporal exclusion window with similarity >= threshold: (row, score)."""
        c = self.config
        last = r - 1 - c.exclude_recent  # newest row allowed by the keyframe window
        if last < 0:
            return []
        d = self._desc[r]
        sims = self._desc[: last + 1] @ d
        times = self._times[: last + 1]
        ok = (sims >= self._threshold(r)) & (self._times[r] - times >= c.min_time_gap)
        idx = np.nonzero(ok)[0]
        if len(idx) == 0:
            return []
        idx = idx[np.argsort(-sims[idx], kind="stable")][: c.max_candidates]
        return [(int(j), float(sims[j])) for j in idx]


def make_loop_detector(config: ClassicalLoopConfig, context: Any = None) -> ClassicalLoopDetector:
    return ClassicalLoopDetector(config)
