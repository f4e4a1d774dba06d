"""Textbook monocular visual odometry with OpenCV — a peer baseline for pvslam's benchmark.

What it does (and deliberately does not do):

1. **Tracking.** Shi–Tomasi (GFTT) or FAST corners are tracked frame to frame with pyramidal Lucas–Kanade
   (``cv2.calcOpticalFlowPyrLK``) and a forward–backward consistency check. Whenever the number of live tracks
   drops below ``min_tracks`` (and at every keyframe) new corners are detected away from the existing ones.
   Every track remembers where and in which frame it was born.
2. **Initialisation.** From the first frame on, the tracks are followed until their median displacement exceeds
   ``init_min_parallax_px``; then the essential matrix is estimated with RANSAC (``cv2.findEssentialMat``),
   decomposed with the cheirality test (``cv2.recoverPose``) and the inliers are triangulated
   (``cv2.triangulatePoints``). Initialisation is accepted when enough points triangulate in front of both
   cameras with small reprojection error and a sufficient parallax angle; otherwise it waits for more motion.
   The world frame is the first camera and the first baseline has unit length (monocular scale is arbitrary).
   Frames between the first frame and the initialisation frame are then localised by PnP against the new map.
3. **Tracking the map.** Each later frame is localised by PnP RANSAC (``cv2.solvePnPRansac``, then a
   Levenberg–Marquardt refinement on the inliers) against the 3-D points attached to the live tracks;
   PnP outliers lose their track.
4. **Keyframes / mapping.** When the fraction of map-tracked points falls below ``kf_ratio`` of what it was at the
   last keyframe, when too few remain, or every ``kf_max_gap`` frames, the frame becomes a keyframe: tracks that
   have no 3-D point yet are triangulated between their birth frame and this frame (accepted on positive depth,
   reprojection error and parallax angle), and new corners are detected.
5. **Fallback.** When PnP fails (too few inliers), the motion from the previous frame is taken from the essential
   matrix between the two frames with the translation scaled to the previous frame-to-frame distance (the
   "previous scale"); if that fails too, a constant-velocity prediction is used. A keyframe is then forced so
   that the map is rebuilt from the surviving tracks.

There is **no bundle adjustment, no local map / re-observation of lost points, no loop closure and no
relocalisation** — that is what "textbook" means here. Scale drifts; evaluate with Sim(3)-aligned ATE.

Output poses are camera-to-world ``T_wc`` ``[tx, ty, tz, qx, qy, qz, qw]`` for every input frame.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Optional

import cv2
import numpy as np

from pvslam_core.geometry.two_view import find_essential

from .common import load_sequence, pose_from_Rt_cw

__all__ = ["VOConfig", "TextbookVO", "run_textbook_vo"]


@dataclass
class VOConfig:
    detector: str = "gftt"  # "gftt" or "fast"
    max_corners: int = 500
    quality_level: float = 0.005
    min_distance: int = 8
    fast_threshold: int = 15
    min_tracks: int = 200  # re-detect below this many live tracks
    lk_win: int = 15
    lk_levels: int = 3
    fb_max_px: float = 1.0  # forward-backward consistency threshold
    init_min_parallax_px: float = 10.0  # median track displacement before trying the essential matrix
    init_min_points: int = 60
    init_min_angle_deg: float = 1.0  # median parallax angle of the initial points
    ransac_px: float = 1.0  # essential-matrix RANSAC threshold
    pnp_reproj_px: float = 2.0
    pnp_min_inliers: int = 15
    pnp_iterations: int = 100
    kf_ratio: float = 0.7
    kf_min_map_tracks: int = 120
    kf_max_gap: int = 5
    tri_min_angle_deg: float = 1.0
    tri_max_reproj_px: float = 2.0


def _project(K: np.ndarray, T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points X [n,3] with world-to-camera T [3,4] -> (pixels [n,2], depth [n])."""
    Xc = X @ T[:, :3].T + T[:, 3]
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (Xc[:, :2] / z[:, None]) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    return uv, z


def _compose(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """(T_a ∘ T_b) for 3x4 rigid transforms."""
    R = T_a[:, :3] @ T_b[:, :3]
    t = T_a[:, :3] @ T_b[:, 3] + T_a[:, 3]
    return np.concatenate([R, t[:, None]], axis=1)


def _orthonormal(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation projected back onto SO(3) (nearest in Frobenius norm, SVD).  Why: a long stretch of
    constant-velocity frames composes rotations computed from rotations, and the rounding compounds (handheld_fast,
    seed 141: after 174 such frames the "rotation" had entries of 2e4 and a negative determinant)."""
    U, _, Vt = np.linalg.svd(T[:, :3])
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return np.concatenate([R, T[:, 3:]], axis=1)


def _center(T_cw: np.ndarray) -> np.ndarray:
    return -T_cw[:, :3].T @ T_cw[:, 3]


def _relative(T_cur: np.ndarray, T_prev: np.ndarray) -> np.ndarray:
    """T_cur ∘ T_prev^-1 (previous camera -> current camera)."""
    R = T_cur[:, :3] @ T_prev[:, :3].T
    t = T_cur[:, 3] - R @ T_prev[:, 3]
    return np.concatenate([R, t[:, None]], axis=1)


class TextbookVO:
    """Frame-by-frame monocular VO; feed grayscale images with :meth:`process`, read :attr:`poses_cw`."""

    def __init__(self, K: np.ndarray, config: Optional[VOConfig] = None):
        self.K = np.asarray(K, dtype=np.float64)
        self.cfg = config or VOConfig()
        self.lk_params = dict(
            winSize=(self.cfg.lk_win, self.cfg.lk_win),
            maxLevel=self.cfg.lk_levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        self.poses_cw: list[Optional[np.ndarray]] = []  # 3x4 world-to-camera per frame
        self.initialized = False
        self.ref = 0  # reference frame of the initialisation
        self.history: list[tuple[int, np.ndarray, np.ndarray]] = []  # pre-init (frame, track ids, pts)
        self.prev_img: Optional[np.ndarray] = None
        # track arrays (all of length M)
        self.pts = np.zeros((0, 2), np.float32)
        self.prev_pts = np.zeros((0, 2), np.float32)
        self.birth_pts = np.zeros((0, 2), np.float32)
        self.birth_frame = np.zeros(0, np.int64)
        self.tid = np.zeros(0, np.int64)
        self.X = np.zeros((0, 3), np.float64)  # NaN: no 3-D point yet
        self._next_tid = 0
        self.last_kf = 0
        self.map_tracks_at_kf = 0
        self.stats = dict(pnp_failures=0, essential_fallbacks=0, const_velocity=0, keyframes=0,
                          map_points=0, init_frame=-1, resets=0)

    # ------------------------------------------------------------------------------------ tracks
    def _keep(self, m: np.ndarray) -> None:
        self.pts, self.prev_pts = self.pts[m], self.prev_pts[m]
        self.birth_pts, self.birth_frame = self.birth_pts[m], self.birth_frame[m]
        self.tid, self.X = self.tid[m], self.X[m]

    def _detect(self, img: np.ndarray, frame: int) -> None:
        cfg = self.cfg
        n_new = cfg.max_corners - len(self.pts)
        if n_new <= 0:
            return
        mask = np.full(img.shape[:2], 255, np.uint8)
        for x, y in self.pts.astype(np.int32):
            cv2.circle(mask, (int(x), int(y)), cfg.min_distance, 0, -1)
        if cfg.detector == "fast":
            fast = cv2.FastFeatureDetector_create(threshold=cfg.fast_threshold, nonmaxSuppression=True)
            kps = fast.detect(img, mask)
            kps = sorted(kps, key=lambda k: -k.response)[:n_new]
            new = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        else:
            c = cv2.goodFeaturesToTrack(img, maxCorners=n_new, qualityLevel=cfg.quality_level,
                                        minDistance=cfg.min_distance, mask=mask, blockSize=7)
            new = np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2).astype(np.float32)
        n = len(new)
        if n == 0:
            return
        self.pts = np.concatenate([self.pts, new])
        self.prev_pts = np.concatenate([self.prev_pts, new])
        self.birth_pts = np.concatenate([self.birth_pts, new])
        self.birth_frame = np.concatenate([self.birth_frame, np.full(n, frame, np.int64)])
        self.tid = np.concatenate([self.tid, np.arange(self._next_tid, self._next_tid + n)])
        self._next_tid += n
        self.X = np.concatenate([self.X, np.full((n, 3), np.nan)])

    def _track(self, img: np.ndarray) -> None:
        if len(self.pts) == 0:
            return
        p0 = self.pts.reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(self.prev_img, img, p0, None, **self.lk_params)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(img, self.prev_img, p1, None, **self.lk_params)
        fb = np.linalg.norm((p0 - p0b).reshape(-1, 2), axis=1)
        p1 = p1.reshape(-1, 2)
        h, w = img.shape[:2]
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < self.cfg.fb_max_px)
        ok &= (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        self.prev_pts = self.pts
        self.pts = p1.astype(np.float32)
        self._keep(ok)

    # ------------------------------------------------------------------------------------ geometry
    def _triangulate(self, T1: np.ndarray, T2: np.ndarray, x1: np.ndarray, x2: np.ndarray):
        """Triangulate and validate -> (X [n,3], good [n], angle_ok [n])."""
        K, cfg = self.K, self.cfg
        Xh = cv2.triangulatePoints(K @ T1, K @ T2, x1.T.astype(np.float64), x2.T.astype(np.float64))
        with np.errstate(divide="ignore", invalid="ignore"):
            X = (Xh[:3] / Xh[3]).T
        finite = np.all(np.isfinite(X), axis=1)
        X = np.where(finite[:, None], X, 0.0)
        uv1, z1 = _project(K, T1, X)
        uv2, z2 = _project(K, T2, X)
        e1 = np.linalg.norm(uv1 - x1, axis=1)
        e2 = np.linalg.norm(uv2 - x2, axis=1)
        r1 = X - _center(T1)
        r2 = X - _center(T2)
        cosang = np.sum(r1 * r2, 1) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1) + 1e-12)
        angle_ok = cosang < np.cos(np.deg2rad(cfg.tri_min_angle_deg))
        good = finite & (z1 > 0) & (z2 > 0) & (e1 < cfg.tri_max_reproj_px) & (e2 < cfg.tri_max_reproj_px)
        good &= np.nan_to_num(e1 + e2, nan=1e9) < 1e9
        return X, good, angle_ok, np.arccos(np.clip(cosang, -1, 1))

    def _pnp(self, obj: np.ndarray, img_pts: np.ndarray, T_guess: np.ndarray):
        cfg = self.cfg
        if len(obj) < max(cfg.pnp_min_inliers, 6):
            return None, None
        rvec, _ = cv2.Rodrigues(T_guess[:, :3])
        tvec = T_guess[:, 3].reshape(3, 1).copy()
        try:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                obj.astype(np.float64), img_pts.astype(np.float64), self.K, None, rvec, tvec,
                useExtrinsicGuess=True, iterationsCount=cfg.pnp_iterations,
                reprojectionError=cfg.pnp_reproj_px, confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
        except cv2.error:
            return None, None
        if not ok or inl is None or len(inl) < cfg.pnp_min_inliers:
            return None, None
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl].astype(np.float64), img_pts[inl].astype(np.float64),
                                          self.K, None, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        T = np.concatenate([R, tvec.reshape(3, 1)], axis=1)
        if not np.isfinite(T).all() or float(np.abs(tvec).max()) > 1e6:  # the LM refinement diverged: lost
            return None, None
        mask = np.zeros(len(obj), bool)
        mask[inl] = True
        return T, mask

    def _essential(self, x1: np.ndarray, x2: np.ndarray):
        if len(x1) < 8:
            return None
        E, mask = find_essential(x1, x2, self.K, self.cfg.ransac_px)  # OpenCV 5.1 raises on degenerate data
        if E is None or E.shape != (3, 3):
            return None
        n, R, t, mask2 = cv2.recoverPose(E, x1, x2, self.K, mask=mask.copy())
        if n < 8:
            return None
        return R, t.ravel(), mask2.ravel() > 0

    # ------------------------------------------------------------------------------------ stages
    def _try_init(self, i: int) -> bool:
        cfg = self.cfg
        x1, x2 = self.birth_pts, self.pts
        if np.median(np.linalg.norm(x2 - x1, axis=1)) < cfg.init_min_parallax_px:
            return False
        res = self._essential(x1, x2)
        if res is None:
            return False
        R, t, inl = res
        T1 = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
        T2 = np.concatenate([R, t.reshape(3, 1) / max(np.linalg.norm(t), 1e-12)], 1)
        X, good, _, ang = self._triangulate(T1, T2, x1, x2)
        good &= inl
        if good.sum() < cfg.init_min_points or np.rad2deg(np.median(ang[good])) < cfg.init_min_angle_deg:
            return False
        # accept: world = reference camera, unit baseline
        self.X[good] = X[good]
        self.poses_cw[self.ref] = T1
        self.poses_cw[i] = T2
        tid_to_X = dict(zip(self.tid[good].tolist(), X[good]))
        for f, tids, pts in self.history:
            if f == i or f == self.ref:
                continue
            sel = [k for k, t_ in enumerate(tids.tolist()) if t_ in tid_to_X]
            T = None
            if len(sel) >= cfg.pnp_min_inliers:
                obj = np.array([tid_to_X[tids[k]] for k in sel])
                a = (f - self.ref) / (i - self.ref)
                guess = np.concatenate([T2[:, :3], (a * T2[:, 3]).reshape(3, 1)], 1)
                T, _ = self._pnp(obj, pts[sel], guess)
            if T is None:  # interpolate the centre, keep the nearer rotation
                a = (f - self.ref) / (i - self.ref)
                Rf = T2[:, :3] if a > 0.5 else np.eye(3)
                c = a * _center(T2)
                T = np.concatenate([Rf, (-Rf @ c).reshape(3, 1)], 1)
            self.poses_cw[f] = T
        for f in range(self.ref):  # frames before a reset: keep them at the reference pose
            self.poses_cw[f] = T1
        self.history = []
        self.initialized = True
        self.stats["init_frame"] = i
        self.stats["map_points"] += int(good.sum())
        return True

    def _keyframe(self, img: np.ndarray, i: int) -> None:
        cand = ~np.all(np.isfinite(self.X), axis=1) & (self.birth_frame != i)
        drop = np.zeros(len(self.pts), bool)
        T2 = self.poses_cw[i]
        for b in np.unique(self.birth_frame[cand]):
            idx = np.nonzero(cand & (self.birth_frame == b))[0]
            T1 = self.poses_cw[b]
            if T1 is None:
                continue
            X, good, angle_ok, _ = self._triangulate(T1, T2, self.birth_pts[idx], self.pts[idx])
            acc = good & angle_ok
            self.X[idx[acc]] = X[acc]
            drop[idx[angle_ok & ~good]] = True
            self.stats["map_points"] += int(acc.sum())
        self._keep(~drop)
        self._detect(img, i)
        self.last_kf = i
        self.map_tracks_at_kf = int(np.all(np.isfinite(self.X), axis=1).sum())
        self.stats["keyframes"] += 1

    def _localise(self, i: int) -> bool:
        """Pose of frame i; returns True when PnP failed (a keyframe is then forced)."""
        T_prev = self.poses_cw[i - 1]
        T_prev2 = self.poses_cw[i - 2] if i >= 2 and self.poses_cw[i - 2] is not None else T_prev
        vel = _relative(T_prev, T_prev2)
        guess = _compose(vel, T_prev)
        has = np.all(np.isfinite(self.X), axis=1)
        idx = np.nonzero(has)[0]
        T, inl = self._pnp(self.X[idx], self.pts[idx], guess)
        if T is not None:
            drop = np.zeros(len(self.pts), bool)
            drop[idx[~inl]] = True
            self._keep(~drop)
            self.poses_cw[i] = T
            return False
        self.stats["pnp_failures"] += 1
        res = self._essential(self.prev_pts, self.pts)
        step = np.linalg.norm(_center(T_prev) - _center(T_prev2))
        if res is not None and step > 0:
            R, t, _ = res
            rel = np.concatenate([R, (step * t / max(np.linalg.norm(t), 1e-12)).reshape(3, 1)], 1)
            self.poses_cw[i] = _compose(rel, T_prev)
            self.stats["essential_fallbacks"] += 1
        else:
            self.poses_cw[i] = _orthonormal(guess)
            self.stats["const_velocity"] += 1
        return True

    def process(self, img: np.ndarray) -> None:
        """Consume the next grayscale frame."""
        i = len(self.poses_cw)
        self.poses_cw.append(None)
        cfg = self.cfg
        if i == 0:
            self.prev_img = img
            self.poses_cw[0] = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
            self._detect(img, 0)
            return
        self._track(img)
        if not self.initialized:
            self.history.append((i, self.tid.copy(), self.pts.copy()))
            if len(self.pts) < cfg.init_min_points:  # lost the reference: restart from this frame
                self.stats["resets"] += 1
                self._keep(np.zeros(len(self.pts), bool))
                self.ref = i
                self.history = []
                self._detect(img, i)
            elif self._try_init(i):
                self._detect(img, i)
                self.last_kf = i
                self.map_tracks_at_kf = int(np.all(np.isfinite(self.X), axis=1).sum())
            self.prev_img = img
            return
        failed = self._localise(i)
        n_map = int(np.all(np.isfinite(self.X), axis=1).sum())
        if (failed or n_map < cfg.kf_min_map_tracks or n_map < cfg.kf_ratio * self.map_tracks_at_kf
                or i - self.last_kf >= cfg.kf_max_gap or len(self.pts) < cfg.min_tracks):
            self._keyframe(img, i)
        self.prev_img = img

    def poses_wc(self) -> np.ndarray:
        """[N, 7] T_wc; frames never localised (no initialisation) get the identity."""
        out = np.zeros((len(self.poses_cw), 7))
        for k, T in enumerate(self.poses_cw):
            if T is None:
                T = np.concatenate([np.eye(3), np.zeros((3, 1))], 1)
            out[k] = pose_from_Rt_cw(T[:, :3], T[:, 3])
        return out


def run_textbook_vo(seq_dir, config: Optional[VOConfig] = None, max_frames: Optional[int] = None,
                    seed: int = 0) -> dict:
    """Run the textbook VO on a sequence folder.

    Returns ``dict(timestamps [N], poses [N, 7] T_wc, seconds, fps, cpu_seconds, stats, config)``;
    ``seconds`` is the wall time of the whole loop including image reading.
    """
    seq = load_sequence(seq_dir, max_frames=max_frames)
    cv2.setRNGSeed(seed)  # OpenCV's RANSAC draws from the global RNG: make runs repeatable
    vo = TextbookVO(seq.K, config)
    t0 = time.perf_counter()
    c0 = time.process_time()
    for p in seq.image_paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(f"cannot read image {p}")
        vo.process(img)
    seconds = time.perf_counter() - t0
    cpu_seconds = time.process_time() - c0
    n = len(seq)
    return {
        "timestamps": seq.timestamps.copy(),
        "poses": vo.poses_wc(),
        "seconds": seconds,
        "fps": n / seconds if seconds > 0 else float("inf"),
        "cpu_seconds": cpu_seconds,
        "stats": dict(vo.stats),
        "config": asdict(vo.cfg),
    }
