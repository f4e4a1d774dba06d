"""Shading of ray hits: texture coordinates attached to surfaces, level of detail, windows, paint, lighting, sky.

Only the level of detail (from the pixel footprint) depends on the viewpoint; everything else is a function of
the surface point, so a static surface keeps its colour across views (what optical flow and the ground-truth
reprojection test rely on).
"""
from __future__ import annotations

import numpy as np

from . import textures
from .scene import BoxSet, Scene, hash01, stuff_id

_SKY_HORIZON = np.array([0.78, 0.84, 0.9], np.float32)
_SKY_ZENITH = np.array([0.33, 0.52, 0.8], np.float32)
_GLASS_LIT = np.array([0.85, 0.74, 0.45], np.float32)
_GLASS_DARK = np.array([0.16, 0.2, 0.26], np.float32)
_NOISE = textures.tex_id("noise")


def _coverage(f: np.ndarray, frac: np.ndarray, period: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Anti-aliased indicator of ``|f - 0.5| < frac / 2`` (f = fractional cell position) for a footprint ``fp``."""
    return np.clip((frac / 2.0 - np.abs(f - 0.5)) * period / np.maximum(fp, 1e-4) + 0.5, 0.0, 1.0)


def _sky(d: np.ndarray) -> np.ndarray:
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    e = np.clip(d[:, 2], 0.0, 1.0)[:, None]
    base = _SKY_HORIZON + (_SKY_ZENITH - _SKY_HORIZON) * np.clip(e * 2.5, 0, 1)
    dzc = np.maximum(d[:, 2], 0.05)
    cu, cv = 60.0 * d[:, 0] / dzc, 60.0 * d[:, 1] / dzc
    cloud = textures.sample(np.full(len(d), _NOISE), cu, cv, np.full(len(d), 3.0))[:, :1]
    a = np.clip((cloud - 0.45) * 2.0, 0, 1) * np.clip(e * 6.0, 0, 1) * 0.7
    return (base * (1 - a) + a * 0.97).astype(np.float32)


def _box_table(boxes: BoxSet, c: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Per-box float32 parameters packed for one gather per pixel (see ``shade``)."""
    cy, sy = np.cos(boxes.yaw), np.sin(boxes.yaw)
    ll = np.stack([cy * light[0] + sy * light[1], -sy * light[0] + cy * light[1], np.full_like(cy, light[2])], 1)
    return np.concatenate([c[None] - boxes.center, cy[:, None], sy[:, None], boxes.half, boxes.tint,
                           boxes.scale[:, None], boxes.off, boxes.win, ll], axis=1).astype(np.float32)


def _windows(win, key, axis, sgn, fu, hz, half_u, fp):
    """Coverage [n] and colour [n,3] of procedural windows on vertical faces (zero elsewhere)."""
    n = len(axis)
    cov = np.zeros(n, np.float32)
    col = np.zeros((n, 3), np.float32)
    wm = (win[:, 0] > 0) & (axis != 2)
    if not wm.any():
        return cov, col
    su, sv, wu, wv = win[wm, 0], win[wm, 1], win[wm, 2], win[wm, 3]
    hu = fu[wm] + half_u[wm]
    h = hz[wm]
    cu, cv = hu / su, h / sv
    iu, iv = np.floor(cu), np.floor(cv)
    c = _coverage(cu - iu, wu, su, fp[wm]) * _coverage(cv - iv, wv, sv, fp[wm])
    c *= h > 0.8 * sv  # no windows at street level
    r = hash01(key[wm], iu.astype(np.int64), iv.astype(np.int64), axis[wm] * 2 + (sgn[wm] > 0)).astype(np.float32)
    lit = (r > 0.72)[:, None]
    glass = np.where(lit, _GLASS_LIT * (0.7 + 0.4 * r[:, None]), _GLASS_DARK * (0.6 + 0.9 * r[:, None]))
    cov[wm] = c
    col[wm] = glass
    return cov, col


class _Hits:
    """Per-hit surface attributes [n], filled by the ground pass (first ``ng``) and the box pass (the rest)."""

    def __init__(self, n: int) -> None:
        self.u = np.empty(n, np.float64)  # texture coordinates (m)
        self.v = np.empty(n, np.float64)
        self.tex = np.empty(n, np.int64)
        self.tint = np.empty((n, 3), np.float32)
        self.scale = np.empty(n, np.float32)  # texture period (m)
        self.fp = np.empty(n, np.float32)  # pixel footprint (m)
        self.lam = np.empty(n, np.float32)  # Lambert factor
        self.pid = np.empty(n, np.int64)


def shade(scene: Scene, boxes: BoxSet, c: np.ndarray, dw: np.ndarray, t: np.ndarray, prim: np.ndarray,
          inv_f: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour float32 [N,3] in [0,1], panoptic id int64 [N] and dynamic flag [N] for flat rays ``dw`` [N,3].

    Hit pixels are ordered ground first, then boxes, so each group is a contiguous slice of the per-hit arrays.
    """
    N = dw.shape[0]
    col = np.zeros((N, 3), np.float32)
    pid = np.zeros(N, np.int64)
    dyn = np.zeros(N, bool)
    sky = prim == -2
    if sky.any():
        col[sky] = _sky(dw[sky])
        pid[sky] = stuff_id("sky") if scene.sky else 0
    gi = np.nonzero(prim == -1)[0]
    bi = np.nonzero(prim >= 0)[0]
    ng, nb = len(gi), len(bi)
    n = ng + nb
    if n == 0:
        return col, pid, dyn
    L = np.asarray(scene.light, np.float64)
    L = L / np.linalg.norm(L)
    h = _Hits(n)
    gs = _ground(h, scene, c, dw[gi], t[gi], inv_f, L) if ng else None
    k = prim[bi]
    win = _boxes(h, ng, boxes, c, k, dw[bi], t[bi][:, None], inv_f, L) if nb else None
    shaded = _texture_and_light(h, scene, ng, gs, win)
    order = np.concatenate([gi, bi])
    col[order] = shaded
    pid[order] = h.pid
    if nb:
        dyn[bi] = boxes.dynamic[k]
    return col, pid, dyn


def _ground(h: _Hits, scene: Scene, c: np.ndarray, d: np.ndarray, tg: np.ndarray, inv_f: float, L: np.ndarray):
    """Fill the first ``len(d)`` hits (the ground, normal +z); returns the ground's surface sample (paint)."""
    ng = len(d)
    dn = np.sqrt(np.einsum("ij,ij->i", d, d))
    cosg = np.abs(d[:, 2]) / dn
    h.fp[:ng] = tg * dn * inv_f / np.maximum(cosg, 0.05) ** 0.75
    gx = c[0] + tg.astype(np.float64) * d[:, 0]
    gy = c[1] + tg.astype(np.float64) * d[:, 1]
    gs = scene.ground(gx, gy, h.fp[:ng])
    h.u[:ng], h.v[:ng] = gx, gy
    h.tex[:ng], h.tint[:ng], h.scale[:ng], h.pid[:ng] = gs.tex, gs.tint, gs.scale, gs.pid
    h.lam[:ng] = max(L[2], 0.0)
    return gs


def _boxes(h: _Hits, ng: int, boxes: BoxSet, c: np.ndarray, k: np.ndarray, d: np.ndarray, tb: np.ndarray,
           inv_f: float, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill the hits from ``ng`` on (boxes ``k``: local hit point, face, face coordinates in metres); returns the
    windows' coverage and colour."""
    tab = _box_table(boxes, c, L)[k]
    rel = tab[:, 0:3] + tb * d
    cy, sy = tab[:, 3], tab[:, 4]
    lx = cy * rel[:, 0] + sy * rel[:, 1]
    ly = -sy * rel[:, 0] + cy * rel[:, 1]
    lz = rel[:, 2]
    dx = cy * d[:, 0] + sy * d[:, 1]
    dy = -sy * d[:, 0] + cy * d[:, 1]
    hx, hy, hz_ = tab[:, 5], tab[:, 6], tab[:, 7]
    qx, qy, qz = np.abs(lx) / hx, np.abs(ly) / hy, np.abs(lz) / hz_
    axis = np.where((qx >= qy) & (qx >= qz), 0, np.where(qy >= qz, 1, 2))
    a0, a1 = axis == 0, axis == 1
    la = np.where(a0, lx, np.where(a1, ly, lz))
    sgn = np.where(la >= 0, 1.0, -1.0).astype(np.float32)
    nd = sgn * np.where(a0, dx, np.where(a1, dy, d[:, 2]))
    nl = sgn * np.where(a0, tab[:, 18], np.where(a1, tab[:, 19], tab[:, 20]))
    dn = np.sqrt(np.einsum("ij,ij->i", d, d))
    h.fp[ng:] = tb[:, 0] * dn * inv_f / np.maximum(np.abs(nd) / dn, 0.05) ** 0.75
    h.lam[ng:] = np.maximum(nl, 0.0)
    fu = np.where(a0, ly * sgn, np.where(a1, -lx * sgn, lx))
    fv = np.where(axis == 2, ly, -lz)
    h.u[ng:] = fu + tab[:, 12] + 7.3 * axis
    h.v[ng:] = fv + tab[:, 13]
    h.tex[ng:] = boxes.tex[k]
    h.tint[ng:] = tab[:, 8:11]
    h.scale[ng:] = tab[:, 11]
    h.pid[ng:] = boxes.pid[k]
    return _windows(tab[:, 14:18], boxes.key[k], axis, sgn, fu, lz + hz_, np.where(a0, hy, hx), h.fp[ng:])


def _texture_and_light(h: _Hits, scene: Scene, ng: int, gs, win) -> np.ndarray:
    """Shaded colour [n,3]: detail texture and low-frequency variation (both with the level of detail from the
    footprint), the ground's paint, the boxes' windows, then ambient + Lambert light."""
    n = len(h.u)
    per_texel = h.scale / textures.SIZE
    lod = np.log2(np.maximum(h.fp / per_texel, 1e-6))
    base = textures.sample(h.tex, h.u / per_texel, h.v / per_texel, lod)
    big = 9.0 * per_texel
    low = textures.sample(np.full(n, _NOISE), h.u / big + 57.0, h.v / big + 91.0, lod - np.log2(9.0))[:, :1]
    albedo = base * h.tint * (0.75 + 0.5 * low)
    if gs is not None:
        a = albedo[:ng]
        a += (gs.paint_rgb - a) * gs.paint[:, None]
    if win is not None:
        wcov, wcol = win
        a = albedo[ng:]
        a += (wcol - a) * wcov[:, None]
    lightv = scene.ambient + (1.0 - scene.ambient) * h.lam
    return np.clip(albedo * lightv[:, None], 0.0, 1.0)
