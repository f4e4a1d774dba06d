"""Tracking recovery of the ``flow`` frontend: an initial flow from a global homography when DIS alone fails.

DIS is a coarse-to-fine patch search; its coarsest level bounds the displacement it finds (a few tens of pixels at
the flow resolution).  A head camera turning at 200-300 deg/s moves the whole image 20-50 flow px between two
frames, and more against a keyframe several frames back: on the synthetic ``handheld_fast`` scenario 80-100 % of
the pixels then failed the forward-backward check, the frame was declared lost, and four lost frames in a row
re-initialised the map (a new fragment, a new scale).  The motion that fails is mostly *rotation*, and the image
motion of a rotating camera is exactly a homography (``K R K^-1``), so:

1. corners of the reference (Shi-Tomasi) are followed into the frame by pyramidal Lucas-Kanade (``max_level``
   pyramid levels: displacements of ``~ 2^max_level x`` the window), kept when the backward track returns within
   ``fb_px``;
2. a RANSAC homography is fitted to them (``min_inliers`` inliers, else no recovery);
3. the flows it induces (reference -> frame and back) start DIS, which then refines the parallax and the moving
   objects the homography does not explain.

The caller (``FlowFrontend._track``) keeps whichever of the plain and the recovered flow passes more pixels of the
forward-backward check.  All arrays are at the flow resolution: ``uint8 [H, W]`` images, ``float32 [H, W, 2]``
flows.
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
    try:
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    h, w = g0.shape
    return _induced(H, h, w), _induced(H_inv, h, w), int(inl.sum())


def _induced(H: np.ndarray, h: int, w: int) -> np.ndarray:
    """float32 ``[h, w, 2]`` flow ``H x - x`` of every pixel (points mapped behind the camera get zero flow)."""
    xs, ys = pixel_grid_np(h, w)
    P = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3).astype(np.float64)
    Q = P @ H.T
    z = Q[:, 2:3]
    good = np.abs(z) > 1e-9
    Q = np.where(good, Q[:, :2] / np.where(good, z, 1.0), P[:, :2])
    return np.ascontiguousarray((Q - P[:, :2]).reshape(h, w, 2).astype(np.float32))
