"""Procedural texture families the plain generator never uses: bricks and tiles, stripes and plaid, checkers and
dots, cellular (Voronoi cells and cracks), Gabor-like oriented noise.  Only domain randomisation (:mod:`.domain`)
draws them.

Each maker returns a grayscale ``size x size`` float32 image in ``[0, 1]`` that the texture bank normalises like its
grayscale photographs (the scene tints it per surface).  Textures repeat with mirrored tiling, so none needs to be
periodic itself.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["MAKERS", "make"]


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    return x, y


def _noise(size: int, rng: np.random.Generator, cells: int) -> np.ndarray:
    g = rng.random((cells, cells)).astype(np.float32)
    return cv2.resize(g, (size, size), interpolation=cv2.INTER_CUBIC)


def _cell_value(rng: np.random.Generator, *ij: np.ndarray) -> np.ndarray:
    """A random value in [0, 1) per integer cell index tuple (a seeded table lookup)."""
    table = rng.random(4096).astype(np.float32)
    h = np.zeros(ij[0].shape, np.int64)
    for k, v in zip((73856093, 19349663, 83492791), ij):
        h ^= v.astype(np.int64) * k
    return table[np.abs(h) % table.size]


def _bricks(size: int, rng: np.random.Generator, rows: int, cols: int, stagger: float) -> np.ndarray:
    x, y = _grid(size)
    r = np.floor(y * rows)
    xs = x * cols + stagger * (r % 2)
    c = np.floor(xs)
    fy, fx = y * rows - r, xs - c
    mortar_v, mortar_u = 0.08, 0.08 * cols / rows
    joint = (np.minimum(fy, 1 - fy) < mortar_v / 2) | (np.minimum(fx, 1 - fx) < mortar_u / 2)
    face = 0.3 + 0.45 * _cell_value(rng, r, c) + 0.15 * _noise(size, rng, 64)
    return np.where(joint, 0.85, face)


def _stripes(size: int, rng: np.random.Generator, plaid: bool) -> np.ndarray:
    x, y = _grid(size)
    warp = 0.04 * _noise(size, rng, 8)
    g = 0.5 + 0.5 * np.tanh(3.0 * np.sin(2 * np.pi * 9 * (x + warp)))
    if plaid:
        g = 0.55 * g + 0.45 * (0.5 + 0.5 * np.tanh(3.0 * np.sin(2 * np.pi * 5 * (y + warp))))
    return g + 0.1 * _noise(size, rng, 128)


def _checker(size: int, rng: np.random.Generator, dots: bool) -> np.ndarray:
    x, y = _grid(size)
    n = 8
    i, j = np.floor(x * n), np.floor(y * n)
    if dots:
        d = np.hypot(x * n - i - 0.5, y * n - j - 0.5)
        g = np.where(d < 0.3, 0.2 + 0.2 * _cell_value(rng, i, j), 0.8)
    else:
        g = np.where((i + j) % 2 == 0, 0.25, 0.8)
    return g + 0.1 * _noise(size, rng, 64)


def _cellular(size: int, rng: np.random.Generator, cracks: bool) -> np.ndarray:
    pts = rng.random((48, 2)).astype(np.float32)
    x, y = _grid(size)
    d = np.hypot(x[..., None] - pts[:, 0], y[..., None] - pts[:, 1])  # [S, S, P]
    part = np.partition(d, 1, axis=2)
    if cracks:
        edge = part[..., 1] - part[..., 0]
        return np.clip(0.3 + 8.0 * edge, 0.0, 0.85) + 0.1 * _noise(size, rng, 64)
    shade = rng.random(len(pts)).astype(np.float32)
    return 0.25 + 0.55 * shade[np.argmin(d, axis=2)] + 0.1 * _noise(size, rng, 128)


def _gabor(size: int, rng: np.random.Generator, orientations: int) -> np.ndarray:
    white = rng.standard_normal((size, size)).astype(np.float32)
    out = np.zeros((size, size), np.float32)
    for _ in range(orientations):
        theta, lam = float(rng.uniform(0, np.pi)), float(rng.uniform(6.0, 14.0))
        k = cv2.getGaborKernel((31, 31), 0.5 * lam, theta, lam, 0.6, 0, ktype=cv2.CV_32F)
        out += cv2.filter2D(white, -1, k, borderType=cv2.BORDER_REFLECT)
    return out


MAKERS = {
    "bricks": lambda s, rng: _bricks(s, rng, 8, 4, 0.5),
    "tiles": lambda s, rng: _bricks(s, rng, 6, 6, 0.0),
    "stripes": lambda s, rng: _stripes(s, rng, False),
    "plaid": lambda s, rng: _stripes(s, rng, True),
    "checker": lambda s, rng: _checker(s, rng, False),
    "dots": lambda s, rng: _checker(s, rng, True),
    "voronoi": lambda s, rng: _cellular(s, rng, False),
    "cracks": lambda s, rng: _cellular(s, rng, True),
    "gabor": lambda s, rng: _gabor(s, rng, 1),
    "ripples": lambda s, rng: _gabor(s, rng, 3),
}


def make(name: str, size: int) -> np.ndarray:
    """Texture ``name`` of :data:`MAKERS` as ``float32 [size, size, 3]`` (gray, unnormalised), seeded by its name."""
    rng = np.random.default_rng(sum(ord(ch) * 31 ** k for k, ch in enumerate(name)) % (2 ** 32))
    g = MAKERS[name](size, rng).astype(np.float32)
    return np.repeat(g[..., None], 3, axis=2)
