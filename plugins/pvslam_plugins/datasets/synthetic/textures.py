"""Texture bank for the synthetic renderer: photographs shipped with scikit-image plus procedural noise.

Every texture is a square ``S x S`` RGB float32 image in ``[0, 1]`` with a mip pyramid (``cv2.pyrDown``), all
packed into one atlas image.  Textures repeat with mirrored tiling (``...cba|abc...|cba...``): no seams, and the
pyramid uses the same reflection so every level tiles seamlessly too.

Sampling is trilinear: bilinear (``cv2.remap`` over the atlas, one call per level for all pixels) inside the two
levels that bracket the requested level of detail (LOD), blended by its fractional part.  The LOD comes from the pixel footprint on the surface (see :mod:`.render`), which keeps far
surfaces from shimmering -- optical flow breaks on aliasing.

If a scikit-image picture cannot be loaded (a trimmed install), a seeded procedural noise texture takes its place,
so the generator never needs the network.
"""
from __future__ import annotations

import functools
import warnings
from typing import Callable

import cv2
import numpy as np

from . import texture_families

SIZE = 256  # texels per side
LEVELS = 8  # mip levels: 256, 128, ..., 2 texels a side

# name -> loader; grayscale pictures become RGB and are tinted per surface by the scene
_GRAY = ("brick", "grass", "gravel", "camera", "moon", "coins", "text", "page", "clock", "cell")
_RGB = ("rocket", "coffee", "chelsea", "astronaut", "hubble_deep_field", "immunohistochemistry", "retina",
        "colorwheel")
PROCEDURAL = ("noise", "fine_noise", "wood", "plaster")
# families only domain randomisation draws (:mod:`.texture_families`); appended, so every other index stays
EXTRA: tuple[str, ...] = tuple(texture_families.MAKERS)
NAMES: tuple[str, ...] = _GRAY + _RGB + PROCEDURAL + EXTRA
INDEX = {n: i for i, n in enumerate(NAMES)}


def _value_noise(size: int, seed: int, octaves: tuple[tuple[int, float], ...]) -> np.ndarray:
    """Tileable-enough fractal value noise in [0, 1] (sum of bicubic-upsampled random grids)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size, size), np.float32)
    total = 0.0
    for cells, amp in octaves:
        grid = rng.random((cells, cells)).astype(np.float32)
        out += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amp
    out /= total
    out -= out.min()
    return out / max(float(out.max()), 1e-6)


def _procedural(name: str, size: int, seed: int = 0) -> np.ndarray:
    if name == "fine_noise":
        g = _value_noise(size, 11 + seed, ((8, 0.3), (32, 0.4), (128, 0.6), (256, 0.5)))
    elif name == "wood":
        y = np.linspace(0, 1, size, dtype=np.float32)[:, None]
        n = _value_noise(size, 23 + seed, ((4, 1.0), (16, 0.5)))
        g = 0.5 + 0.5 * np.sin(2 * np.pi * (12 * y + 2.5 * n))
        g = 0.6 * g + 0.4 * _value_noise(size, 29 + seed, ((64, 1.0), (256, 0.6)))
    elif name == "plaster":
        g = 0.7 + 0.3 * _value_noise(size, 31 + seed, ((16, 0.5), (64, 0.5), (256, 0.8)))
    else:  # "noise" and fallback for missing pictures
        g = _value_noise(size, 7 + seed, ((4, 1.0), (16, 0.7), (64, 0.5), (256, 0.3)))
    return np.repeat(g[..., None], 3, axis=2)


def _load_picture(name: str) -> np.ndarray:
    import skimage.data as skdata

    loader: Callable[[], np.ndarray] = getattr(skdata, name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = np.asarray(loader())
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    img = img.astype(np.float32)
    if img.max() > 1.5:
        img /= 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return img


def _square(img: np.ndarray, size: int) -> np.ndarray:
    h, w = img.shape[:2]
    s = min(h, w)
    top, left = (h - s) // 2, (w - s) // 2
    crop = np.ascontiguousarray(img[top : top + s, left : left + s])
    interp = cv2.INTER_AREA if s > size else cv2.INTER_CUBIC
    return cv2.resize(crop, (size, size), interpolation=interp)


def _normalise(img: np.ndarray, gray: bool) -> np.ndarray:
    """Grayscale detail maps: mean 0.5, fixed contrast (the scene tints them); photos: kept, slightly flattened."""
    if gray:
        g = img.mean(axis=2, keepdims=True)
        g = (g - g.mean()) / max(float(g.std()), 1e-3)
        g = np.clip(0.55 + 0.2 * g, 0.05, 1.0)
        return np.repeat(g, 3, axis=2)
    return np.clip(0.1 + 0.85 * img, 0.0, 1.0)


def _pyramid(base: np.ndarray, levels: int) -> list[np.ndarray]:
    out = [base]
    for _ in range(1, levels):
        out.append(cv2.pyrDown(out[-1], borderType=cv2.BORDER_REFLECT))
    return out


@functools.lru_cache(maxsize=4)
def texture_atlas(size: int = SIZE, levels: int = LEVELS) -> "Atlas":
    """All textures and their mip levels packed into one float32 image (cached, read-only).

    Texture ``t`` occupies rows ``t * (size + 2) ...``; level ``k`` (``size >> k`` texels a side) starts at column
    ``cols[k]``; every level keeps a one-texel mirrored border so bilinear taps at the tile edge stay inside it.
    """
    if size >> (levels - 1) < 1:
        raise ValueError(f"{levels} levels do not fit a {size}-texel texture")
    cols = np.zeros(levels, np.int64)
    for k in range(1, levels):
        cols[k] = cols[k - 1] + (size >> (k - 1)) + 2
    width = int(cols[-1] + (size >> (levels - 1)) + 2)
    img = np.zeros((len(NAMES) * (size + 2), width, 3), np.float32)
    for t, name in enumerate(NAMES):
        if name in PROCEDURAL:
            base = _procedural(name, size)
        elif name in EXTRA:
            base = _normalise(texture_families.make(name, size), gray=True)
        else:
            try:
                base = _normalise(_square(_load_picture(name), size), gray=name in _GRAY)
            except Exception:  # missing picture in a trimmed install: deterministic noise instead
                base = _procedural("noise", size, seed=t)
        for k, lev in enumerate(_pyramid(base.astype(np.float32), levels)):
            n = size >> k
            pad = cv2.copyMakeBorder(lev, 1, 1, 1, 1, cv2.BORDER_REFLECT)
            r0 = t * (size + 2)
            img[r0 : r0 + n + 2, cols[k] : cols[k] + n + 2] = pad
    img.setflags(write=False)
    return Atlas(img=img, size=size, levels=levels, cols=cols)


class Atlas:
    def __init__(self, img: np.ndarray, size: int, levels: int, cols: np.ndarray):
        self.img, self.size, self.levels, self.cols = img, size, levels, cols


def sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray, lod: np.ndarray) -> np.ndarray:
    """Trilinear sample of texture ``tex`` (int [N]) at base-texel coordinates ``u, v`` (float [N]) and level of
    detail ``lod`` (float [N], 0 = full resolution); returns float32 ``[N, 3]``.  Texel centres at integers."""
    atlas = texture_atlas()
    n = len(tex)
    if n == 0:
        return np.zeros((0, 3), np.float32)
    S, L = atlas.size, atlas.levels
    lod = np.clip(np.asarray(lod, np.float32), 0.0, L - 1.0)
    l0 = lod.astype(np.int64)  # floor (lod >= 0)
    w1 = (lod - l0)[:, None]
    single = not np.any(w1 > 0)
    # reduce to one mirrored period (2S base texels at every level), then float32 is precise enough
    period = 2.0 * S
    ur = np.mod(np.asarray(u, np.float64) + 0.5, period).astype(np.float32)
    vr = np.mod(np.asarray(v, np.float64) + 0.5, period).astype(np.float32)
    row0 = (np.asarray(tex, np.int64) * (S + 2) + 0.5).astype(np.float32)
    ks = np.arange(L)
    sk_tab = (S >> ks).astype(np.float32)
    inv_tab = np.ldexp(np.float32(1.0), -ks).astype(np.float32)
    col_tab = (atlas.cols + 0.5).astype(np.float32)
    rows = -(-n // 1024)  # remap wants both map sides below 32767
    x = np.zeros(rows * 1024, np.float32)
    y = np.zeros(rows * 1024, np.float32)
    res = []
    for k in (l0, np.minimum(l0 + 1, L - 1)):
        inv, two_sk = inv_tab[k], 2.0 * sk_tab[k]
        mu, mv = ur * inv, vr * inv  # level-k coordinate + 0.5, in [0, 2 sk)
        # mirror into [0, sk]; -0.5 for the texel centre and +1 for the border: + 0.5
        np.add(np.minimum(mu, two_sk - mu), col_tab[k], out=x[:n])
        np.add(np.minimum(mv, two_sk - mv), row0, out=y[:n])
        out = cv2.remap(atlas.img, x.reshape(rows, 1024), y.reshape(rows, 1024), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        res.append(out.reshape(-1, 3)[:n])
        if single:
            return res[0]
    return res[0] + (res[1] - res[0]) * w1


def tex_id(name: str) -> int:
    if name not in INDEX:
        raise KeyError(f"unknown texture {name!r}; known: {', '.join(NAMES)}")
    return INDEX[name]
