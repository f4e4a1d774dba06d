"""Forward warping of a panoptic id map with a flow field (vectorised scatter with z-order or last-write-wins),
DIS optical flow, and the rigid flow induced by depth + camera motion."""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np
import torch

from pvslam_core.imaging import create_dis, to_gray

def dis_flow(prev: torch.Tensor, cur: torch.Tensor, preset: str = "medium", max_side: int = 640) -> np.ndarray:
    """float32 [2, H, W]: for each pixel of ``prev``, its offset into ``cur`` (OpenCV DIS)."""
    g0, g1 = to_gray(prev), to_gray(cur)
    if g0.shape != g1.shape:
        g1 = cv2.resize(g1, (g0.shape[1], g0.shape[0]), interpolation=cv2.INTER_AREA)
    h, w = g0.shape
    s = min(1.0, max_side / float(max(h, w)))
    if s < 1.0:
        size = (max(8, int(round(w * s))), max(8, int(round(h * s))))
        a, b = cv2.resize(g0, size, interpolation=cv2.INTER_AREA), cv2.resize(g1, size, interpolation=cv2.INTER_AREA)
    else:
        a, b = g0, g1
    dis = create_dis(preset)
    f = dis.calc(a, b, None)
    if s < 1.0:
        sx, sy = w / a.shape[1], h / a.shape[0]
        f = cv2.resize(f, (w, h), interpolation=cv2.INTER_LINEAR)
        f[..., 0] *= sx
        f[..., 1] *= sy
    return np.ascontiguousarray(f.transpose(2, 0, 1), dtype=np.float32)


def resize_flow(flow: np.ndarray, h: int, w: int) -> np.ndarray:
    """Resize a [2, h0, w0] flow to [2, h, w], scaling the vectors."""
    if flow.shape[1:] == (h, w):
        return flow
    h0, w0 = flow.shape[1:]
    f = cv2.resize(np.ascontiguousarray(flow.transpose(1, 2, 0)), (w, h), interpolation=cv2.INTER_LINEAR)
    f[..., 0] *= w / w0
    f[..., 1] *= h / h0
    return np.ascontiguousarray(f.transpose(2, 0, 1))


def _quat_to_rot(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


_GRIDS: dict = {}


def _pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Cached read-only float32 ``(ys, xs) [h, w]`` (``np.mgrid``; rebuilt per frame it cost ~0.2 ms)."""
    g = _GRIDS.get((h, w))
    if g is None:
        g = np.mgrid[0:h, 0:w].astype(np.float32)
        g.setflags(write=False)
        if len(_GRIDS) > 8:
            _GRIDS.clear()
        g = _GRIDS[(h, w)] = (g[0], g[1])
    return g


def rigid_flow(
    depth_prev: np.ndarray, pose_prev: np.ndarray, pose_cur: np.ndarray, intrinsics: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flow [2, H, W] of the static scene from camera motion, the z-depth in the current camera [H, W] and a
    validity mask [H, W] (depth > 0 and in front of the current camera).  Poses are T_wc ``[t, q_xyzw]``."""
    h, w = depth_prev.shape
    fx, fy, cx, cy = [float(v) for v in intrinsics[:4]]
    ys, xs = _pixel_grid(h, w)
    z = depth_prev.astype(np.float32)
    X = np.stack([(xs - cx) / fx * z, (ys - cy) / fy * z, z], axis=0).reshape(3, -1)
    R0, t0 = _quat_to_rot(np.asarray(pose_prev[3:7], np.float64)), np.asarray(pose_prev[:3], np.float64)
    R1, t1 = _quat_to_rot(np.asarray(pose_cur[3:7], np.float64)), np.asarray(pose_cur[:3], np.float64)
    # X_cur = R1^T (R0 X + t0 - t1) = R X + t  (composed in float64, applied in float32)
    R = (R1.T @ R0).astype(np.float32)
    t = (R1.T @ (t0 - t1)).astype(np.float32)
    Xc = R @ X + t[:, None]
    zc = Xc[2].reshape(h, w)
    valid = (z > 0) & (zc > 1e-6)
    zs = np.where(valid, zc, 1.0)
    u = fx * Xc[0].reshape(h, w) / zs + cx
    v = fy * Xc[1].reshape(h, w) / zs + cy
    flow = np.stack([u - xs, v - ys]).astype(np.float32)
    return flow, np.where(valid, zc, 0.0).astype(np.float32), valid


def forward_warp(
    ids: np.ndarray,
    flow: np.ndarray,
    depth: Optional[np.ndarray] = None,
    mask: Optional[np.ndarray] = None,
    splat: str = "bilinear",
) -> np.ndarray:
    """Forward-warp an int64 id map [H, W] with a flow [2, H, W] (source pixel -> offset into the target).

    Void (0) and masked-out source pixels are not written.  Several sources landing on one target pixel: the
    smallest ``depth`` wins when ``depth`` (> 0 where known) is given, otherwise the last source in raster order.
    ``splat="bilinear"`` writes the 4 integer neighbours of each target position (a source's own nearest pixel
    is always preferred over a neighbour's spill-over), ``"nearest"`` only the rounded position.
    """
    h, w = ids.shape
    src = ids.reshape(-1)
    keep = src != 0
    if mask is not None:
        keep &= mask.reshape(-1).astype(bool)
    out = np.zeros(h * w, dtype=ids.dtype)
    sel = None if keep.all() else np.nonzero(keep)[0]  # None: every pixel is a source (no gathers)
    if sel is not None and len(sel) == 0:
        return out.reshape(h, w)
    gy, gx = (g.reshape(-1) for g in _pixel_grid(h, w))  # float32 integers: exact in the float64 sums below
    f0, f1 = flow[0].reshape(-1), flow[1].reshape(-1)
    if sel is None:
        tx, ty, vals = np.add(gx, f0, dtype=np.float64), np.add(gy, f1, dtype=np.float64), src
    else:
        tx, ty, vals = np.add(gx[sel], f0[sel], dtype=np.float64), np.add(gy[sel], f1[sel], dtype=np.float64), src[sel]
    key = _priority(depth, sel, len(tx))
    finite = np.isfinite(tx) & np.isfinite(ty)
    if not finite.all():  # (dropping sources keeps the others' keys in order)
        fin = np.nonzero(finite)[0]
        tx, ty, vals, key = tx[fin], ty[fin], vals[fin], key[fin]
    rx, ry = np.rint(tx).astype(np.int64), np.rint(ty).astype(np.int64)
    inb = (rx >= 0) & (rx < w) & (ry >= 0) & (ry < h)
    filled = np.zeros(h * w, dtype=bool)
    if inb.all():
        _scatter_min(out, filled, ry * w + rx, key, vals)
    else:
        inb = np.nonzero(inb)[0]
        _scatter_min(out, filled, ry[inb] * w + rx[inb], key[inb], vals[inb])
    if splat != "nearest":
        _spill(out, ~filled, (h, w), tx, ty, rx, ry, key, vals)
    return out.reshape(h, w)


def _priority(depth: Optional[np.ndarray], sel: Optional[np.ndarray], n: int) -> np.ndarray:
    """int64 key of each of the ``n`` sources (pixels ``sel``, None: all), lower wins, unique: the depth (nearest
    first, unknown last) then raster order; without depth reversed raster order (the last source wins)."""
    order = np.arange(n, dtype=np.int64)
    if depth is None:
        return (n - 1) - order
    z = depth.reshape(-1) if sel is None else depth.reshape(-1)[sel]
    if z.dtype == np.float32:
        # a non-negative float32's bits order as the float does: the depth in the high word, raster order below
        # (one scatter-min over one key instead of one per criterion)
        bits = np.where(z > 0, z, np.float32(np.inf)).view(np.int32).astype(np.int64)
        return (bits << 32) | order
    z = z.astype(np.float64)
    rank = np.empty(n, dtype=np.int64)  # any other dtype: the rank of (depth, raster order)
    rank[np.argsort(np.where(z > 0, z, np.inf), kind="stable")] = order
    return rank


def _spill(out: np.ndarray, hole: np.ndarray, shape: tuple[int, int], tx: np.ndarray, ty: np.ndarray, rx: np.ndarray,
           ry: np.ndarray, key: np.ndarray, vals: np.ndarray) -> None:
    """Bilinear spill-over into ``out`` (flat ``[h * w]``): each source's integer neighbours of its target position
    ``tx, ty`` other than the rounded ``rx, ry``, written only on pixels no source landed on (``hole``), by the same
    priority.  Only sources whose 2x2 block of neighbours touches a hole can write (few): found on the grid first."""
    h, w = shape
    x0, y0 = np.floor(tx).astype(np.int64), np.floor(ty).astype(np.int64)
    hp = np.zeros((h + 2, w + 2), dtype=bool)
    hp[1:h + 1, 1:w + 1] = hole.reshape(h, w)
    near = (hp[:-1, :-1] | hp[1:, :-1] | hp[:-1, 1:] | hp[1:, 1:]).reshape(-1)  # block at (y0, x0): [y0 + 1, x0 + 1]
    blk = (x0 >= -1) & (x0 < w) & (y0 >= -1) & (y0 < h)
    c = np.nonzero(blk)[0]
    c = c[near[(y0[c] + 1) * (w + 1) + x0[c] + 1]]
    x0, y0 = x0[c], y0[c]
    # the rounded position is x0 or x0 + 1, so "not the nearest pixel" and the bounds are per-axis booleans
    up_x, up_y = rx[c] != x0, ry[c] != y0  # rounded up (rx == x0 + 1)
    in_x = ((x0 >= 0) & (x0 < w), (x0 >= -1) & (x0 < w - 1))  # x0 + dx inside, dx = 0, 1
    in_y = ((y0 >= 0) & (y0 < h), (y0 >= -1) & (y0 < h - 1))
    other_x, other_y = (up_x, ~up_x), (up_y, ~up_y)  # x0 + dx != rx
    t00 = y0 * w + x0
    tq, idx = [], []
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        i = np.nonzero(in_x[dx] & in_y[dy] & (other_x[dx] | other_y[dy]))[0]
        t = t00[i] + (dy * w + dx)
        on_hole = hole[t]
        tq.append(t[on_hole])
        idx.append(c[i[on_hole]])
    tq, idx = np.concatenate(tq), np.concatenate(idx)
    _scatter_min(out, None, tq, key[idx], vals[idx])


def _scatter_min(out: np.ndarray, written: Optional[np.ndarray], t: np.ndarray, key: np.ndarray,
                 vals: np.ndarray) -> None:
    """``out[t] = vals`` where the lowest ``key`` (unique per source) wins per target pixel ``t`` (flat, in bounds);
    ``written`` (if given) marks the pixels written."""
    if len(t) == 0:
        return
    best = np.full(out.shape[0], np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(best, t, key)
    win = key == best[t]
    tw = t[win]
    out[tw] = vals[win]
    if written is not None:
        written[tw] = True
