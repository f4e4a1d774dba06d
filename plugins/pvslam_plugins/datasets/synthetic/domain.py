"""Domain randomisation of a built scenario (opt-in; ``build(..., domain=...)``): the same layout and trajectory
under other textures, thing sizes, lighting, exposure, camera noise and blur, and haze.

A domain is a split name (:data:`DOMAINS`).  ``"train"`` draws textures from the families of
:data:`TRAIN_FAMILIES` and thing sizes from ``SIZE_RANGE["train"]``; ``"heldout"`` only from
:data:`HELD_OUT_FAMILIES` and larger things, which no training frame ever shows: a segmenter trained on ``"train"``
frames is evaluated on ``"heldout"`` ones.  Everything is drawn from the scenario's seed (same seed and domain,
same sequence).  Static surfaces keep one appearance across views (textures, tints and the light are per scene; the
camera noise alone changes per frame), so the sequence stays usable for SLAM.

Without a domain nothing here runs and the generator's output is unchanged.
"""
from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass

import cv2
import numpy as np

from . import textures
from .scene import CATEGORIES, BoxSet, GroundSample, MovingObject, Scene

__all__ = ["DOMAINS", "TEXTURE_FAMILIES", "HELD_OUT_FAMILIES", "TRAIN_FAMILIES", "SIZE_RANGE", "family_textures",
           "randomise", "check_domain", "Look"]

DOMAINS = ("train", "heldout")

#: the texture bank grouped by source: scikit-image photographs, value noise, and the procedural families of
#: :mod:`.texture_families`
TEXTURE_FAMILIES: dict[str, tuple[str, ...]] = {
    "photo_gray": textures._GRAY,
    "photo_rgb": textures._RGB,
    "value_noise": textures.PROCEDURAL,
    "bricks": ("bricks", "tiles"),
    "stripes": ("stripes", "plaid"),
    "checker": ("checker", "dots"),
    "cellular": ("voronoi", "cracks"),
    "gabor": ("gabor", "ripples"),
}
#: the split: families only evaluation sees (the plain generator never uses them either)
HELD_OUT_FAMILIES = ("cellular", "gabor")
TRAIN_FAMILIES = tuple(f for f in TEXTURE_FAMILIES if f not in HELD_OUT_FAMILIES)

#: thing size factors (length and height; the width follows the length closely): held-out things are larger than
#: any in training, as a street from another renderer has buses and cars up to a third of the image
SIZE_RANGE = {"train": (0.8, 1.25), "heldout": (1.3, 1.7)}
_TINT_JITTER = 0.3  # per-channel tint factor in [1 - j, 1 + j]: other paints, other leaves
_THINGS = {c.id for c in CATEGORIES if c.isthing}


def family_textures(families) -> np.ndarray:
    """Texture ids of the families named."""
    return np.array([textures.tex_id(n) for f in families for n in TEXTURE_FAMILIES[f]], np.int64)


def check_domain(domain: str) -> str:
    """``domain`` when it names a split of :data:`DOMAINS` (ValueError otherwise)."""
    if domain not in DOMAINS:
        raise ValueError(f"unknown domain {domain!r}; known: {', '.join(DOMAINS)}")
    return domain


def _split_families(domain: str) -> tuple[str, ...]:
    return HELD_OUT_FAMILIES if check_domain(domain) == "heldout" else TRAIN_FAMILIES


def _rng(domain: str, scenario: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) % 2 ** 32, zlib.crc32(scenario.encode()), DOMAINS.index(domain) + 1])


def _tints(rng: np.random.Generator, tint: np.ndarray) -> np.ndarray:
    f = rng.uniform(1 - _TINT_JITTER, 1 + _TINT_JITTER, tint.shape)
    return np.clip(tint * f, 0.05, 1.0).astype(np.float32)


def _restyle(boxes: BoxSet, rng: np.random.Generator, pool: np.ndarray) -> BoxSet:
    """Each box: a texture from ``pool``, a jittered tint and texture scale."""
    n = len(boxes)
    return dataclasses.replace(boxes, tex=rng.choice(pool, n), tint=_tints(rng, boxes.tint),
                               scale=(boxes.scale * rng.uniform(0.6, 1.6, n)).astype(np.float32))


def _scale_static_things(boxes: BoxSet, rng: np.random.Generator, lo: float, hi: float) -> BoxSet:
    """Static things (parked cars, furniture) grown about their footprint's centre, standing on the same ground."""
    center, half = boxes.center.copy(), boxes.half.copy()
    for pid in np.unique(boxes.pid):
        if pid // 1000 not in _THINGS or pid % 1000 == 0:
            continue
        m = boxes.pid == pid
        s_h, s_v = rng.uniform(lo, hi, 2)
        g = center[m, :2].mean(axis=0)
        center[m, :2] = g + (center[m, :2] - g) * s_h
        half[m, :2] *= s_h
        center[m, 2] *= s_v
        half[m, 2] *= s_v
    return dataclasses.replace(boxes, center=center, half=half)


def _scale_mover(m: MovingObject, rng: np.random.Generator, lo: float, hi: float) -> MovingObject:
    s_l, s_v = rng.uniform(lo, hi, 2)
    s = np.array([s_l, s_l * rng.uniform(0.9, 1.1), s_v])
    parts = dataclasses.replace(m.parts, center=m.parts.center * s, half=m.parts.half * s)
    return dataclasses.replace(m, parts=parts, size=tuple(float(v) for v in np.asarray(m.size) * s))


def _ground(fn, lut: np.ndarray, tint_f: np.ndarray):
    """The scene's ground shader with its textures mapped through ``lut`` and its tints scaled per texture."""

    def ground(x: np.ndarray, y: np.ndarray, fp: np.ndarray) -> GroundSample:
        g = fn(x, y, fp)
        return dataclasses.replace(g, tex=lut[g.tex], tint=np.clip(g.tint * tint_f[g.tex], 0.05, 1.0)
                                   .astype(np.float32))

    return ground


@dataclass(frozen=True)
class Look:
    """A camera's rendition of the scene's light: exposure gain, gamma, white balance, haze over depth (metres;
    the sky takes the haze colour fully when there is haze), Gaussian blur (px) and per-frame Gaussian noise (on
    0..1 pixels, drawn from ``seed`` and the frame)."""

    gain: float
    gamma: float
    white: tuple[float, float, float]
    haze_per_m: float
    haze_rgb: tuple[float, float, float]
    blur_px: float
    noise: float
    seed: int

    @staticmethod
    def draw(rng: np.random.Generator) -> "Look":
        haze = float(rng.uniform(0.01, 0.06)) if rng.random() < 0.5 else 0.0
        return Look(gain=float(rng.uniform(0.6, 1.5)), gamma=float(rng.uniform(0.8, 1.25)),
                    white=tuple(float(v) for v in rng.uniform(0.85, 1.15, 3)), haze_per_m=haze,
                    haze_rgb=tuple(float(v) for v in np.clip(rng.uniform(0.6, 0.9) + rng.uniform(-0.04, 0.04, 3),
                                                             0, 1)),
                    blur_px=float(rng.uniform(0.0, 1.2)), noise=float(rng.uniform(0.0, 0.03)),
                    seed=int(rng.integers(2 ** 31)))

    def __call__(self, col: np.ndarray, depth: np.ndarray, frame: int) -> np.ndarray:
        """``col`` float32 [H, W, 3] in [0, 1] and z-depth [H, W] (0 = sky) -> the camera's image, in [0, 1]."""
        out = col * (np.asarray(self.white, np.float32) * self.gain)
        if self.haze_per_m > 0:
            t = np.where(depth > 0, np.exp(-self.haze_per_m * depth), 0.0).astype(np.float32)[..., None]
            out = out * t + np.asarray(self.haze_rgb, np.float32) * (1 - t)
        out = np.clip(out, 0.0, 1.0) ** np.float32(1.0 / self.gamma)
        if self.blur_px > 0.3:
            out = cv2.GaussianBlur(out, (0, 0), self.blur_px)
        if self.noise > 0:
            rng = np.random.default_rng([self.seed, int(frame)])
            out = out + rng.normal(0.0, self.noise, out.shape).astype(np.float32)
        return np.clip(out, 0.0, 1.0).astype(np.float32)


def randomise(scene: Scene, domain: str, scenario: str, seed: int) -> Scene:
    """``scene`` restyled for ``domain`` (a new :class:`Scene`; the layout and the movers' paths are kept)."""
    pool = family_textures(_split_families(domain))
    rng = _rng(domain, scenario, seed)
    lo, hi = SIZE_RANGE[domain]
    static = _scale_static_things(_restyle(scene.static, rng, pool), rng, lo, hi)
    movers = [_scale_mover(dataclasses.replace(m, parts=_restyle(m.parts, rng, pool)), rng, lo, hi)
              for m in scene.movers]
    lut = rng.choice(pool, len(textures.NAMES))
    tint_f = rng.uniform(1 - _TINT_JITTER, 1 + _TINT_JITTER, (len(textures.NAMES), 3)).astype(np.float32)
    elev, azim = np.radians(rng.uniform(20, 75)), rng.uniform(0, 2 * np.pi)
    light = (float(np.cos(elev) * np.cos(azim)), float(np.cos(elev) * np.sin(azim)), float(np.sin(elev)))
    return dataclasses.replace(scene, static=static, movers=movers, ground=_ground(scene.ground, lut, tint_f),
                               light=light, ambient=float(rng.uniform(0.3, 0.75)), look=Look.draw(rng))
