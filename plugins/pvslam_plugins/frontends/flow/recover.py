"""Tracking recovery of the ``flow`` frontend: an initial flow from a global homography when DIS alone fails.

DIS is a coarse-to-fine patch search; its coarsest level bounds the displacement it finds (a few tens of pixels at
the flow resolution).  A head camera turning at 200-300 deg/s moves the whole image 20-50 flow px between two
frames, and more against a keyframe several frames back: then most pixels fail the forward-backward check, the
frame is declared lost, and a few lost frames in a row re-initialise the map (a new fragment, a new scale).  The
motion that fails is mostly *rotation*, and the image motion of a rotating camera is exactly a homography
(``K R K^-1``), so:

1. corners of the reference (Shi-Tomasi) are followed into the frame by pyramidal Lucas-Kanade (``max_level``
   pyramid levels: displacements of ``~ 2^max_level x`` the window), kept when the backward track returns within
   ``fb_px``;
2. a RANSAC homography is fitted to them (``min_inliers`` inliers, else no recovery);
3. the flows it induces (reference -> frame and back) start DIS, which then refines the parallax and the moving
   objects the homography does not explain.

When the corners give no homography (a bare wall), :class:`MotionPredictor` extrapolates the last frames' image
motion at constant rate instead.  The caller (:class:`.track_starts.TrackStarts`) keeps whichever of the plain and
the recovered flows passes most pixels of the forward-backward check.  All arrays are at the flow resolution:
``uint8 [H, W]`` images, ``float32 [H, W, 2]`` flows.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from .flow_ops import pixel_grid_np


def homography_flow(g0: np.ndarray, g1: np.ndarray, max_corners: int = 300, max_level: int = 4,
                    win: int = 21, fb_px: float = 1.0, ransac_px: float = 2.0,
                    min_inliers: int = 25) -> Optional[tuple[np.ndarray, np.ndarray, int]]:
    """``(flow g0 -> g1, flow g1 -> g0, inliers)`` induced by the homography between the two gray images
    (see the module docstring), or None when too few corners track or fit one."""
    p0 = cv2.goodFeaturesToTrack(g0, maxCorners=max_corners, qualityLevel=0.01, minDistance=5, blockSize=5)
    if p0 is None or len(p0) < min_inliers:
        return None
    lk = dict(winSize=(win, win), maxLevel=max_level,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(g0, g1, p0, None, **lk)
    if p1 is None:
        return None
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(g1, g0, p1, None, **lk)
    ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1)
    ok &= np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1) < fb_px
    if int(ok.sum()) < min_inliers:
        return None
    a, b = p0.reshape(-1, 2)[ok], p1.reshape(-1, 2)[ok]
    H, inl = cv2.findHomography(a, b, cv2.RANSAC, ransac_px)
    if H is None or inl is None or int(inl.sum()) < min_inliers:
        return None
    pair = induced_flows(H, *g0.shape)
    return None if pair is None else (*pair, int(inl.sum()))


def flow_homography(fwd: np.ndarray, ok: np.ndarray, stride: int = 4, ransac_px: float = 1.0,
                    min_inliers: int = 25) -> Optional[np.ndarray]:
    """The homography (3x3 float64, flow-resolution pixels) best explaining the flow ``fwd [H, W, 2]`` at the pixels
    ``ok [H, W]`` (every ``stride``-th row and column; RANSAC), or None."""
    sub = ok[::stride, ::stride]
    if int(sub.sum()) < min_inliers:
        return None
    ys, xs = np.nonzero(sub)
    p0 = np.stack([xs * stride, ys * stride], -1).astype(np.float32)
    p1 = p0 + fwd[ys * stride, xs * stride].astype(np.float32)
    H, inl = cv2.findHomography(p0, p1, cv2.RANSAC, ransac_px)
    if H is None or inl is None or int(inl.sum()) < min_inliers or not np.isfinite(H).all():
        return None
    return H


class MotionPredictor:
    """The image motion of the next frame predicted at constant rate, for tracking recovery when the corners alone do
    not give a homography (a fast turn over a scene with few corners, such as a bare wall).

    Each tracked frame's flow against its reference is summarised by a homography (exact for a rotating camera, an
    approximation with parallax) and chained into ``G_t`` (a common image plane -> frame ``t``) along the references;
    the last two consecutive frames of the reference's chain give the per-frame motion ``M = G_a G_(a-1)^-1``, and the
    prediction for frame ``t`` against reference ``r`` is ``M^(t - a) G_a G_r^-1``.  A reference that is not on a chain
    (the first keyframe, after a failure) starts one.  Bounded: the ``keep`` most recent frames."""

    def __init__(self, keep: int = 64):
        self.keep = int(keep)
        self._g: dict[int, tuple[int, np.ndarray]] = {}  # frame index -> (chain id, G)
        self._chains = 0

    def observe(self, ref_index: int, index: int, fwd: np.ndarray, ok: np.ndarray) -> None:
        """Frame ``index`` tracked against the frame ``ref_index``: ``fwd`` its flow, ``ok`` the consistent pixels."""
        H = flow_homography(fwd, ok)
        if H is None:
            self._g.pop(index, None)
            return
        if ref_index not in self._g:
            self._chains += 1
            self._g[ref_index] = (self._chains, np.eye(3))
        chain, g_ref = self._g[ref_index]
        self._g[index] = (chain, H @ g_ref)
        if len(self._g) > self.keep:
            for k in sorted(self._g)[: len(self._g) - self.keep]:
                del self._g[k]

    def predict(self, ref_index: int, index: int) -> Optional[np.ndarray]:
        """The predicted homography reference -> frame ``index`` (flow-resolution pixels), or None."""
        if ref_index not in self._g:
            return None
        chain, g_ref = self._g[ref_index]
        for a in sorted((k for k in self._g if k < index), reverse=True):
            prev = self._g.get(a - 1)
            if self._g[a][0] == chain and prev is not None and prev[0] == chain:
                g_a = self._g[a][1]
                try:
                    M = g_a @ np.linalg.inv(prev[1])
                    H = np.linalg.matrix_power(M, index - a) @ g_a @ np.linalg.inv(g_ref)
                except np.linalg.LinAlgError:
                    return None
                return H if np.isfinite(H).all() and abs(H[2, 2]) > 1e-12 else None
        return None

    def flows(self, ref_index: int, index: int, h: int, w: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """The flows (reference -> frame, frame -> reference; ``[h, w, 2]``) of the predicted motion, or None."""
        H = self.predict(ref_index, index)
        return None if H is None else induced_flows(H, h, w)


def induced_flows(H: np.ndarray, h: int, w: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The flows ``H`` induces (``[h, w, 2]``: forward, and backward by its inverse), or None for a singular ``H``."""
    try:
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    return _induced(H, h, w), _induced(H_inv, h, w)


def _induced(H: np.ndarray, h: int, w: int) -> np.ndarray:
    """float32 ``[h, w, 2]`` flow ``H x - x`` of every pixel (points mapped behind the camera get zero flow)."""
    xs, ys = pixel_grid_np(h, w)
    P = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3).astype(np.float64)
    Q = P @ H.T
    z = Q[:, 2:3]
    good = np.abs(z) > 1e-9
    Q = np.where(good, Q[:, :2] / np.where(good, z, 1.0), P[:, :2])
    return np.ascontiguousarray((Q - P[:, :2]).reshape(h, w, 2).astype(np.float32))
