"""Vectorised ray casting of a :class:`~.scene.Scene` (numpy, single core friendly).

For a pinhole camera the ray of pixel ``(x, y)`` is ``d_c = ((x - cx)/fx, (y - cy)/fy, 1)`` in the camera
frame, so the ray parameter at a hit *is* the z-depth.  Per frame:

1. the ground plane ``z = 0``: ``t = -c_z / d_z`` (one division per pixel);
2. boxes: every box's 8 corners are projected (clipped against the near plane) to get its screen rectangle;
   boxes off screen are culled, and the slab test runs only over each visible box's rectangle, vectorised over
   its pixels, updating a z-buffer (depth, primitive index);
3. shading of the winning primitive per pixel: world-space texture coordinates (attached to surfaces),
   trilinear texture sampling with a level of detail from the pixel footprint (no shimmer at distance),
   procedural windows and road paint with analytic anti-aliasing, Lambert + ambient lighting, sky gradient.

Nothing depends on the viewpoint except the level of detail, so static surfaces keep their colour across views.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .scene import BoxSet, Relief, Scene
from .shading import shade

NEAR = 0.05  # metres; hits closer than this are ignored
_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]])
_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)


HFOV_RANGE = (20.0, 150.0)  # degrees: a pinhole beyond ~150 stretches the border rows without bound


def check_hfov(hfov_deg: float) -> float:
    """``hfov_deg`` when it is a horizontal field of view a pinhole camera can have (:data:`HFOV_RANGE`)."""
    lo, hi = HFOV_RANGE
    if not (lo <= float(hfov_deg) <= hi):
        raise ValueError(f"hfov_deg must be within {lo:g}-{hi:g} degrees (a pinhole camera), got {hfov_deg}")
    return float(hfov_deg)


@dataclass(frozen=True)
class Camera:
    """Pinhole camera; pixel centres at integer coordinates."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @staticmethod
    def default(width: int = 320, height: int = 240, hfov_deg: Optional[float] = None) -> "Camera":
        """fx = fy = 0.85 W (about 61 degrees horizontal field of view), or the focal length of ``hfov_deg`` degrees
        horizontally (another camera: a wide action camera ~90, a narrow lens ~45); centred principal point."""
        f = 0.85 * width if hfov_deg is None else 0.5 * width / math.tan(math.radians(check_hfov(hfov_deg)) / 2)
        return Camera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height))

    def rays(self, u: np.ndarray | None = None, v: np.ndarray | None = None) -> np.ndarray:
        """Camera-frame rays with unit z ``[..., 3]`` float64 (the full pixel grid if ``u, v`` are None)."""
        if u is None or v is None:
            v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        u = np.asarray(u, np.float64)
        v = np.asarray(v, np.float64)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)


@dataclass
class RenderOutput:
    rgb: np.ndarray  # uint8 [H, W, 3]
    depth: np.ndarray  # float32 [H, W] z-depth in metres, 0 = sky/invalid
    panoptic: np.ndarray  # int64 [H, W]
    dynamic: np.ndarray  # bool [H, W]
    color: np.ndarray  # float32 [H, W, 3] in [0, 1] before quantisation


def _screen_rects(boxes: BoxSet, R: np.ndarray, c: np.ndarray, cam: Camera) -> np.ndarray:
    """Per box ``[x0, y0, x1, y1]`` (int, exclusive end) of the pixels its projection may cover; x1 = 0 if none."""
    B = len(boxes)
    if B == 0:
        return np.zeros((0, 4), np.int64)
    cy, sy = np.cos(boxes.yaw), np.sin(boxes.yaw)
    loc = boxes.half[:, None, :] * _SIGNS[None]  # [B, 8, 3]
    wx = boxes.center[:, None, 0] + cy[:, None] * loc[..., 0] - sy[:, None] * loc[..., 1]
    wy = boxes.center[:, None, 1] + sy[:, None] * loc[..., 0] + cy[:, None] * loc[..., 1]
    wz = boxes.center[:, None, 2] + loc[..., 2]
    pw = np.stack([wx, wy, wz], axis=-1) - c  # [B, 8, 3]
    pc = pw @ R  # camera frame (row vectors): X_c = R^T (X_w - c)
    z = pc[..., 2]
    # corners in front of the near plane plus crossings of the 12 edges with it
    a, b = pc[:, _EDGES[:, 0]], pc[:, _EDGES[:, 1]]  # [B, 12, 3]
    za, zb = a[..., 2] - NEAR, b[..., 2] - NEAR
    cross = (za * zb) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(cross, za / (za - zb), 0.0)
    pe = a + s[..., None] * (b - a)
    pts = np.concatenate([pc, pe], axis=1)  # [B, 20, 3]
    ok = np.concatenate([z >= NEAR, cross], axis=1)
    zz = np.where(ok, pts[..., 2], 1.0)
    u = cam.fx * pts[..., 0] / zz + cam.cx
    v = cam.fy * pts[..., 1] / zz + cam.cy
    big = 1e9
    umin = np.where(ok, u, big).min(1)
    umax = np.where(ok, u, -big).max(1)
    vmin = np.where(ok, v, big).min(1)
    vmax = np.where(ok, v, -big).max(1)
    x0 = np.clip(np.floor(umin), 0, cam.width).astype(np.int64)
    x1 = np.clip(np.floor(umax) + 2, 0, cam.width).astype(np.int64)
    y0 = np.clip(np.floor(vmin), 0, cam.height).astype(np.int64)
    y1 = np.clip(np.floor(vmax) + 2, 0, cam.height).astype(np.int64)
    empty = ~ok.any(1) | (x1 <= x0) | (y1 <= y0)
    x1[empty] = 0
    x0[empty] = 0
    return np.stack([x0, y0, x1, y1], axis=1)


def _slab(o: np.ndarray, half: np.ndarray, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """Entry distance of rays ``o + t d`` (box-local) into the box ``|p| <= half``; inf where missed."""
    tn = None
    tf = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for oi, hi, di in ((o[0], half[0], dx), (o[1], half[1], dy), (o[2], half[2], dz)):
            inv = 1.0 / di
            t1 = (-hi - oi) * inv
            t2 = (hi - oi) * inv
            lo = np.minimum(t1, t2)
            hi_ = np.maximum(t1, t2)
            tn = lo if tn is None else np.maximum(tn, lo)
            tf = hi_ if tf is None else np.minimum(tf, hi_)
    hit = (tn <= tf) & (tn > NEAR)
    return np.where(hit, tn, np.inf)


def _trace_batch(boxes: BoxSet, ks: np.ndarray, rects: np.ndarray, c: np.ndarray, dflat: np.ndarray, W: int,
                 bh: int, bw: int, t: np.ndarray, prim: np.ndarray) -> None:
    """Slab test of several small boxes at once, each over its rectangle padded to ``bh x bw`` pixels."""
    r = rects[ks]
    oy, ox = np.arange(bh), np.arange(bw)
    ys = r[:, 1, None] + oy[None]  # [nb, bh]
    xs = r[:, 0, None] + ox[None]
    valid = (ys < r[:, 3, None])[:, :, None] & (xs < r[:, 2, None])[:, None, :]
    idx = (np.minimum(ys, r[:, 3, None] - 1)[:, :, None] * W + np.minimum(xs, r[:, 2, None] - 1)[:, None, :])
    idx = idx.reshape(len(ks), -1)
    valid = valid.reshape(len(ks), -1)
    d = dflat[idx]  # [nb, P, 3]
    cyw, syw = np.cos(boxes.yaw[ks])[:, None], np.sin(boxes.yaw[ks])[:, None]
    rel = c[None] - boxes.center[ks]
    o = ((cyw[:, 0] * rel[:, 0] + syw[:, 0] * rel[:, 1])[:, None], (-syw[:, 0] * rel[:, 0] + cyw[:, 0] * rel[:, 1])[:, None],
         rel[:, 2, None])
    half = boxes.half[ks]
    dx = cyw * d[..., 0] + syw * d[..., 1]
    dy = -syw * d[..., 0] + cyw * d[..., 1]
    tk = _slab(o, (half[:, 0, None], half[:, 1, None], half[:, 2, None]), dx, dy, d[..., 2])
    tflat = t.reshape(-1)
    hit = valid & (tk < tflat[idx])
    if not hit.any():
        return
    bi, pi = np.nonzero(hit)
    pix, th = idx[bi, pi], tk[bi, pi]
    order = np.lexsort((th, pix))
    pix, th, kk = pix[order], th[order], ks[bi[order]]
    first = np.ones(len(pix), bool)
    first[1:] = pix[1:] != pix[:-1]
    tflat[pix[first]] = th[first]
    prim.reshape(-1)[pix[first]] = kk[first]


def _pow2(n: np.ndarray) -> np.ndarray:
    return np.maximum(8, 2 ** np.ceil(np.log2(np.maximum(n, 1))).astype(np.int64))


RELIEF_SAMPLES = 64  # samples of a ray over the relief's stretch (a crossing between two is found by bisection)
RELIEF_BISECT = 24  # bisection steps: the hit to ~1e-6 of the sampled interval
RELIEF_REACH = 2000.0  # m: the farthest a ray is followed over the relief


def _ground_hits(c: np.ndarray, dw: np.ndarray, relief: Optional[Relief] = None) -> np.ndarray:
    """Ray parameter ``t`` of each ray's ground hit (inf: none): the plane z = 0, or with a ``relief``
    (:class:`~.scene.Relief`, nonzero on ``|x - centre| < half_length`` only) the nearer of the plane's hit off
    that stretch and the first crossing of the stretch (``RELIEF_SAMPLES`` samples along the ray, then bisection)."""
    dz = dw[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(dz < -1e-9, np.float32(-c[2]) / dz, np.inf).astype(np.float32)
    if relief is None:
        if c[2] <= 0:  # a camera on or below the plane sees no ground
            tg[:] = np.inf
        return tg
    shape = tg.shape
    d = dw.reshape(-1, 3).astype(np.float64)
    x0, x1 = relief.centre - relief.half_length, relief.centre + relief.half_length
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (x0 - c[0]) / d[:, 0], (x1 - c[0]) / d[:, 0]
    lo = np.clip(np.nan_to_num(np.minimum(ta, tb), nan=0.0, neginf=0.0), 0.0, RELIEF_REACH)
    hi = np.clip(np.nan_to_num(np.maximum(ta, tb), nan=RELIEF_REACH, posinf=RELIEF_REACH), 0.0, RELIEF_REACH)
    if x0 <= c[0] <= x1:  # the camera stands on the stretch: every ray starts on it
        lo[:] = 0.0
    s = np.linspace(0.0, 1.0, RELIEF_SAMPLES)
    ts = lo[:, None] + (hi - lo)[:, None] * s[None]  # [N, S]

    def above(t):  # [N, k] the ray's height above the ground at t [N, k]
        return c[2] + t * d[:, 2:3] - relief.z(c[0] + t * d[:, 0:1])

    under = above(ts) <= 0.0
    has = under.any(1) & (hi > lo)
    k = np.argmax(under, 1)
    n = np.arange(len(d))
    a = np.where(k > 0, ts[n, np.maximum(k - 1, 0)], lo)
    b = ts[n, k]
    for _ in range(RELIEF_BISECT):
        m = 0.5 * (a + b)
        up = above(m[:, None])[:, 0] > 0.0
        a, b = np.where(up, m, a), np.where(up, b, m)
    plane = tg.reshape(-1).astype(np.float64)
    xp = c[0] + plane * d[:, 0]
    off = ~((xp > x0) & (xp < x1))  # the plane's hit lies off the stretch (before or beyond it): a hit there
    t = np.minimum(np.where(has, 0.5 * (a + b), np.inf), np.where(off, plane, np.inf))
    return t.reshape(shape).astype(np.float32)


def trace(boxes: BoxSet, c: np.ndarray, dw: np.ndarray, rects: np.ndarray | None,
          relief: Optional[Relief] = None) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit per ray: ``t`` (inf = nothing) and primitive (-1 ground, -2 none, >= 0 box index).

    ``dw`` is ``[H, W, 3]`` float32 world rays; ``rects`` restricts each box to a pixel rectangle (None: all).
    Boxes whose rectangle is small are tested in batches (rectangles padded to a common power-of-two size),
    large ones one by one over their rectangle.
    """
    H, W = dw.shape[:2]
    tg = _ground_hits(c, dw, relief)
    t = tg
    prim = np.where(np.isfinite(tg), -1, -2).astype(np.int32)
    if rects is None:
        rects = np.tile(np.array([[0, 0, W, H]], np.int64), (len(boxes), 1))
        singles = np.arange(len(boxes))
    else:
        vis = np.nonzero(rects[:, 2] > rects[:, 0])[0]
        rh = rects[vis, 3] - rects[vis, 1]
        rw = rects[vis, 2] - rects[vis, 0]
        small = (rh <= 64) & (rw <= 64)
        singles = vis[~small]
        if small.any():
            dflat = dw.reshape(-1, 3)
            kh, kw = _pow2(rh[small]), _pow2(rw[small])
            ks_small = vis[small]
            for bh in np.unique(kh):
                for bw in np.unique(kw[kh == bh]):
                    sel = ks_small[(kh == bh) & (kw == bw)]
                    _trace_batch(boxes, sel, rects, c, dflat, W, int(bh), int(bw), t, prim)
    for k in singles:
        x0, y0, x1, y1 = (int(v) for v in rects[k])
        cyw, syw = float(np.cos(boxes.yaw[k])), float(np.sin(boxes.yaw[k]))
        rel = c - boxes.center[k]
        o = (cyw * rel[0] + syw * rel[1], -syw * rel[0] + cyw * rel[1], rel[2])
        sub = dw[y0:y1, x0:x1]
        dx = cyw * sub[..., 0] + syw * sub[..., 1]
        dy = -syw * sub[..., 0] + cyw * sub[..., 1]
        tk = _slab(o, boxes.half[k], dx, dy, sub[..., 2])
        tcur = t[y0:y1, x0:x1]
        closer = tk < tcur
        if closer.any():
            tcur[closer] = tk[closer]
            prim[y0:y1, x0:x1][closer] = k
    return t, prim


def render(scene: Scene, frame: int, T_wc: np.ndarray, cam: Camera) -> RenderOutput:
    """Render frame ``frame`` of ``scene`` from camera pose ``T_wc`` (4x4)."""
    R = np.asarray(T_wc[:3, :3], np.float64)
    c = np.asarray(T_wc[:3, 3], np.float64)
    boxes = scene.boxes_at(frame)
    dw = (cam.rays() @ R.T).astype(np.float32)
    rects = _screen_rects(boxes, R, c, cam)
    t, prim = trace(boxes, c, dw, rects, scene.relief)
    H, W = cam.height, cam.width
    col, pid, dyn = shade(scene, boxes, c, dw.reshape(-1, 3), t.reshape(-1), prim.reshape(-1), 1.0 / cam.fx)
    depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)
    col = col.reshape(H, W, 3)
    if scene.look is not None:
        col = scene.look(col, depth, frame)
    rgb = np.round(col * 255.0).astype(np.uint8)
    return RenderOutput(rgb=rgb, depth=depth, panoptic=pid.reshape(H, W), dynamic=dyn.reshape(H, W), color=col)


def render_points(scene: Scene, frame: int, T_wc: np.ndarray, cam: Camera, u: np.ndarray, v: np.ndarray):
    """Ray-cast arbitrary (sub-)pixel positions ``u, v`` [N]: returns ``(color [N,3], depth [N], pid [N], dyn [N])``.

    Used by tests to check the ground truth exactly (no resampling of a rendered image involved).
    """
    R = np.asarray(T_wc[:3, :3], np.float64)
    c = np.asarray(T_wc[:3, 3], np.float64)
    boxes = scene.boxes_at(frame)
    dw = (cam.rays(u, v).reshape(1, -1, 3) @ R.T).astype(np.float32)
    t, prim = trace(boxes, c, dw, None, scene.relief)
    col, pid, dyn = shade(scene, boxes, c, dw.reshape(-1, 3), t.reshape(-1), prim.reshape(-1), 1.0 / cam.fx)
    depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32).reshape(-1)
    return col, depth, pid, dyn
