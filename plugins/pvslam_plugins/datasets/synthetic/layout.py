"""Building blocks for the scenarios: buildings, cars, trees, poles, street sides and road-like ground shaders.

All randomness comes from the ``numpy.random.Generator`` passed in, so a scenario is a pure function of its seed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .scene import BoxBuilder, BoxSet, GroundSample, stuff_id, thing_id
from .textures import tex_id

FACADE_TINTS = np.array([
    [0.86, 0.78, 0.62], [0.78, 0.45, 0.36], [0.66, 0.66, 0.70], [0.52, 0.60, 0.72], [0.92, 0.82, 0.48],
    [0.93, 0.92, 0.88], [0.58, 0.72, 0.56], [0.80, 0.55, 0.40], [0.70, 0.60, 0.75], [0.55, 0.50, 0.45],
], np.float32)
DETAIL_TEX = ("brick", "plaster", "gravel", "fine_noise", "noise", "moon", "coins", "cell", "camera", "page", "text")
MURAL_TEX = ("rocket", "coffee", "chelsea", "astronaut", "hubble_deep_field", "immunohistochemistry", "retina",
             "colorwheel", "clock")
CAR_TINTS = np.array([
    [0.75, 0.1, 0.1], [0.1, 0.2, 0.65], [0.9, 0.9, 0.92], [0.15, 0.15, 0.17], [0.55, 0.57, 0.6],
    [0.85, 0.65, 0.1], [0.1, 0.45, 0.25], [0.5, 0.1, 0.4],
], np.float32)
PAINT = np.array([0.93, 0.93, 0.86], np.float32)


class Ids:
    """Stable instance numbers per thing category, in creation order."""

    def __init__(self) -> None:
        self.next: dict[str, int] = {}

    def new(self, category: str) -> int:
        k = self.next.get(category, 0) + 1
        self.next[category] = k
        return thing_id(category, k)


def _jitter(rng: np.random.Generator, c: np.ndarray, amount: float = 0.06) -> tuple[float, float, float]:
    return tuple(float(x) for x in np.clip(c + rng.uniform(-amount, amount, 3), 0.05, 1.0))


def add_building(b: BoxBuilder, rng: np.random.Generator, x: float, y: float, yaw: float, w: float, d: float,
                 h: float, key: int) -> None:
    """A building with its own texture, tint, texture offset and window pattern (distinct places look distinct)."""
    r = rng.random()
    if r < 0.22:
        tex, scale = MURAL_TEX[int(rng.integers(len(MURAL_TEX)))], float(rng.uniform(7.0, 14.0))
        tint = _jitter(rng, np.array([0.9, 0.9, 0.9], np.float32), 0.08)
    else:
        tex, scale = DETAIL_TEX[int(rng.integers(len(DETAIL_TEX)))], float(rng.uniform(2.5, 6.0))
        tint = _jitter(rng, FACADE_TINTS[int(rng.integers(len(FACADE_TINTS)))])
    win = (0.0, 0.0, 0.0, 0.0)
    if rng.random() < 0.8:
        win = (float(rng.uniform(2.0, 3.6)), float(rng.uniform(3.0, 3.7)), float(rng.uniform(0.35, 0.65)),
               float(rng.uniform(0.4, 0.62)))
    off = (float(rng.uniform(0, 50)), float(rng.uniform(0, 50)))
    b.add_on_ground(x, y, (w, d, h), yaw=yaw, tex=tex, tint=tint, scale=scale, off=off, win=win,
                    pid=stuff_id("building"), key=key)


def car_parts(rng: np.random.Generator, pid: int, dynamic: bool, kind: str = "car") -> tuple[BoxSet, tuple]:
    """Boxes of a vehicle in its own frame (x forward, centred at the origin on the ground) and its extents."""
    p = BoxBuilder()
    col = _jitter(rng, CAR_TINTS[int(rng.integers(len(CAR_TINTS)))], 0.05)
    key = int(rng.integers(1 << 30))
    if kind == "car":
        L, W, H = float(rng.uniform(3.9, 4.8)), float(rng.uniform(1.7, 1.9)), float(rng.uniform(1.4, 1.6))
        p.add((0.0, 0.0, 0.6), (L, W, 0.9), tex="fine_noise", tint=col, scale=2.0, pid=pid, dynamic=dynamic,
              key=key, off=(float(rng.uniform(0, 9)), 0.0))
        p.add((-0.15 * L, 0.0, 1.05 + (H - 1.05) / 2), (0.55 * L, W * 0.9, H - 1.05), tex="noise",
              tint=(0.22, 0.25, 0.3), scale=1.5, pid=pid, dynamic=dynamic, key=key)
    else:  # truck / bus: a long box carrying an advertising picture
        L, W, H = float(rng.uniform(8.0, 11.0)), 2.5, float(rng.uniform(3.0, 3.4))
        mural = ("rocket", "coffee", "chelsea", "astronaut", "immunohistochemistry")[int(rng.integers(5))]
        p.add((0.0, 0.0, 0.3 + (H - 0.3) / 2), (L, W, H - 0.3), tex=mural, tint=(0.95, 0.95, 0.95),
              scale=float(L * 0.6), pid=pid, dynamic=dynamic, key=key, win=(1.6, 2.2, 0.6, 0.3))
    return p.build(), (L, W, H)


def add_static_vehicle(b: BoxBuilder, rng: np.random.Generator, pid: int, x: float, y: float, yaw: float) -> None:
    parts, _ = car_parts(rng, pid, dynamic=False)
    c, s = math.cos(yaw), math.sin(yaw)
    for k in range(len(parts)):
        px, py, pz = parts.center[k]
        b.rows.append(dict(center=(x + c * px - s * py, y + s * px + c * py, pz), half=list(parts.half[k]),
                           yaw=yaw, tex=int(parts.tex[k]), tint=tuple(parts.tint[k]), scale=float(parts.scale[k]),
                           off=tuple(parts.off[k]), win=tuple(parts.win[k]), pid=pid, dynamic=False,
                           key=int(parts.key[k])))


def add_tree(b: BoxBuilder, rng: np.random.Generator, x: float, y: float) -> None:
    h = float(rng.uniform(2.2, 3.0))
    b.add_on_ground(x, y, (0.35, 0.35, h + 0.3), tex="wood", tint=(0.45, 0.33, 0.22), scale=1.5,
                    pid=stuff_id("vegetation"))
    cw, ch = float(rng.uniform(2.2, 3.2)), float(rng.uniform(2.0, 3.0))
    b.add((x, y, h + ch / 2), (cw, cw, ch), yaw=float(rng.uniform(0, math.pi)), tex="grass",
          tint=_jitter(rng, np.array([0.36, 0.58, 0.28], np.float32), 0.07), scale=float(rng.uniform(1.5, 2.5)),
          off=(float(rng.uniform(0, 20)), float(rng.uniform(0, 20))), pid=stuff_id("vegetation"))


def add_pole(b: BoxBuilder, x: float, y: float, h: float = 5.5) -> None:
    b.add_on_ground(x, y, (0.18, 0.18, h), tex="fine_noise", tint=(0.55, 0.56, 0.58), scale=1.0,
                    pid=stuff_id("pole"))


@dataclass
class StreetProfile:
    """Lateral layout of a street side (distances from the road centreline)."""

    parking: float = 4.9  # parked-car centre line
    tree: float = 7.6  # tree / pole line on the sidewalk
    facade: float = 9.6  # where buildings start
    margin: float = 3.0  # keep the segment ends free


def populate_side(b: BoxBuilder, rng: np.random.Generator, ids: Ids, a: np.ndarray, e: np.ndarray, nrm: np.ndarray,
                  length: float, prof: StreetProfile, keep_out: tuple[tuple[float, float], ...] = (),
                  max_depth: float = 14.0) -> None:
    """Buildings (with gaps), parked cars, trees and poles along one side of a straight street segment.

    ``a`` start point, ``e`` unit direction, ``nrm`` unit normal pointing away from the road, ``keep_out``
    intervals of arc length left free (intersections).
    """
    yaw = math.atan2(e[1], e[0])

    def free(s0: float, s1: float) -> bool:
        return s0 >= prof.margin and s1 <= length - prof.margin and all(s1 <= k0 or s0 >= k1 for k0, k1 in keep_out)

    def at(s: float, lat: float) -> np.ndarray:
        return a + e * s + nrm * lat

    s = prof.margin + float(rng.uniform(0, 4))
    while s < length - prof.margin:
        w = float(rng.uniform(8.0, 20.0))
        if free(s, s + w):
            d = float(rng.uniform(8.0, max_depth))
            h = float(rng.choice([rng.uniform(5, 9), rng.uniform(9, 16), rng.uniform(16, 28)], p=[0.3, 0.45, 0.25]))
            p = at(s + w / 2, prof.facade + d / 2)
            add_building(b, rng, float(p[0]), float(p[1]), yaw, w, d, h, key=int(rng.integers(1 << 30)))
            s += w
        else:
            s += 2.0
            continue
        s += float(rng.uniform(1.5, 9.0)) if rng.random() < 0.75 else float(rng.uniform(10.0, 16.0))
    s = prof.margin + float(rng.uniform(0, 6))
    while s < length - prof.margin - 5:
        if free(s, s + 5.0) and rng.random() < 0.6:
            p = at(s + 2.5, prof.parking)
            fwd = yaw if rng.random() < 0.8 else yaw + math.pi
            add_static_vehicle(b, rng, ids.new("car"), float(p[0]), float(p[1]), fwd)
        s += 5.6 + float(rng.uniform(0.3, 3.0))
    s = prof.margin + float(rng.uniform(0, 8))
    while s < length - prof.margin:
        if free(s - 1.5, s + 1.5):
            p = at(s, prof.tree)
            if rng.random() < 0.65:
                add_tree(b, rng, float(p[0]), float(p[1]))
            else:
                q = at(s, prof.tree - 1.2)
                add_pole(b, float(q[0]), float(q[1]))
        s += float(rng.uniform(8.0, 17.0))


def aa_band(dist: np.ndarray, width: float, fp: np.ndarray) -> np.ndarray:
    """Anti-aliased coverage of a band ``|dist| < width / 2`` for a pixel footprint ``fp``."""
    return np.clip((width / 2.0 - np.abs(dist)) / np.maximum(fp, 1e-4) + 0.5, 0.0, 1.0)


def dashes(along: np.ndarray, period: float, duty: float, fp: np.ndarray) -> np.ndarray:
    f = np.mod(along / period, 1.0)
    return np.clip((duty / 2.0 - np.abs(f - 0.5)) * period / np.maximum(fp, 1e-4) + 0.5, 0.0, 1.0)


def road_ground(lateral: Callable[[np.ndarray, np.ndarray], np.ndarray],
                along: Callable[[np.ndarray, np.ndarray], np.ndarray], half_width: float, sidewalk: float,
                lane_lines: tuple[tuple[float, bool], ...], inner_tex: str = "grass",
                outer_tex: str = "gravel", extra_road: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None):
    """A ground shader for a road given by signed lateral distance (positive = outer side) and along-coordinate.

    ``lane_lines``: (lateral offset, dashed) of painted lines.  Beyond the sidewalk: terrain, textured
    ``inner_tex`` on the negative side and ``outer_tex`` on the positive side.
    """
    road_t, walk_t, in_t, out_t = tex_id("gravel"), tex_id("brick"), tex_id(inner_tex), tex_id(outer_tex)

    def fn(x: np.ndarray, y: np.ndarray, fp: np.ndarray) -> GroundSample:
        d = lateral(x, y)
        ad = np.abs(d)
        road = ad < half_width
        if extra_road is not None:
            road |= extra_road(x, y)
        walk = ~road & (ad < half_width + sidewalk)
        n = len(x)
        pid = np.where(road, stuff_id("road"), np.where(walk, stuff_id("sidewalk"), stuff_id("terrain")))
        tex = np.where(road, road_t, np.where(walk, walk_t, np.where(d < 0, in_t, out_t)))
        tint = np.empty((n, 3), np.float32)
        tint[:] = np.where(d[:, None] < 0, np.array([0.42, 0.6, 0.3], np.float32),
                           np.array([0.62, 0.56, 0.48], np.float32))
        tint[walk] = (0.74, 0.71, 0.67)
        tint[road] = (0.36, 0.36, 0.38)
        scale = np.where(road, 3.0, np.where(walk, 2.5, 4.0)).astype(np.float32)
        paint = np.zeros(n, np.float32)
        if road.any():
            al = along(x, y)
            for off, dashed in lane_lines:
                cov = aa_band(d - off, 0.15, fp)
                if dashed:
                    cov = cov * dashes(al, 6.0, 0.5, fp)
                paint = np.maximum(paint, cov)
            paint *= road & (ad < half_width)
        return GroundSample(pid=pid.astype(np.int64), tex=tex.astype(np.int64), tint=tint, scale=scale,
                            paint=paint.astype(np.float32), paint_rgb=PAINT)

    return fn


def straight_street(b: BoxBuilder, rng: np.random.Generator, ids: Ids, x_start: float, length: float,
                    crossings: tuple[float, ...]):
    """A straight street along +x (from ``x_start``, ``length`` m) with cross streets at the x positions
    ``crossings``: both sides populated, buildings lining each cross street, asphalt over the intersections.
    Returns the ground function (:func:`road_ground`).  Shared by the moving-vehicles and busy-street scenarios;
    the random draws happen in a fixed order, so a scenario's sequences do not depend on who calls this."""
    prof = StreetProfile(parking=8.6, tree=11.2, facade=13.2, margin=0.0)
    keep = tuple((c - x_start - 9.0, c - x_start + 9.0) for c in crossings)
    for sgn in (1.0, -1.0):
        populate_side(b, rng, ids, np.array([x_start, 0.0]), np.array([1.0, 0.0]), np.array([0.0, sgn]),
                      length, prof, keep_out=keep)
    for c in crossings:  # buildings lining the cross streets
        for sx in (-1.0, 1.0):
            for sgn in (1.0, -1.0):
                side = StreetProfile(parking=4.9, tree=7.6, facade=9.6, margin=0.0)
                populate_side(b, rng, ids, np.array([c, sgn * 20.0]), np.array([0.0, sgn]), np.array([sx, 0.0]),
                              60.0, side)
    cross = np.array(crossings)
    return road_ground(lambda x, y: y, lambda x, y: x, half_width=7.5, sidewalk=4.5,
                       lane_lines=((0.0, False), (-3.5, True), (3.5, True)), inner_tex="gravel",
                       extra_road=lambda x, y: np.min(np.abs(x[:, None] - cross[None]), axis=1) < 6.0)
