"""Scene description for the synthetic generator: categories, boxes, moving objects, ground and camera paths.

World frame: **z up**, ground plane ``z = 0``, metres.  Everything above the ground is a box oriented about the
vertical axis (``yaw``), with a per-box material (texture, tint, texture scale and offset in metres, optional
procedural windows).  Texture coordinates are box-local metres, so texture is attached to the surface: a static
box looks the same from every view, and a moving box carries its texture with it.

A :class:`Scene` is static boxes + :class:`MovingObject` s (several boxes in an object frame, with a world pose
``(x, y, yaw)`` per frame) + a ground shader (a function of the ground point: which stuff class, texture, tint
and painted markings) + an optional sky at infinity.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from pvslam_core.types import Category

from .textures import tex_id

# --------------------------------------------------------------------------------------------------- categories
CATEGORIES: tuple[Category, ...] = (
    Category(1, "road", False, (128, 64, 128)),
    Category(2, "sidewalk", False, (244, 35, 232)),
    Category(3, "building", False, (70, 70, 70)),
    Category(4, "vegetation", False, (107, 142, 35)),
    Category(5, "terrain", False, (152, 251, 152)),
    Category(6, "sky", False, (70, 130, 180)),
    Category(7, "pole", False, (153, 153, 153)),
    Category(8, "wall", False, (102, 102, 156)),
    Category(9, "floor", False, (190, 153, 153)),
    Category(10, "ceiling", False, (180, 165, 180)),
    Category(11, "car", True, (0, 0, 142)),
    Category(12, "truck", True, (0, 0, 70)),
    Category(13, "furniture", True, (220, 220, 0)),
)
CAT = {c.name: c.id for c in CATEGORIES}
CAT_BY_ID = {c.id: c for c in CATEGORIES}


def stuff_id(name: str) -> int:
    """Panoptic id of a stuff class: ``category_id * 1000``."""
    return CAT[name] * 1000


def thing_id(name: str, instance: int) -> int:
    """Panoptic id of a thing instance: ``category_id * 1000 + instance`` (instance 1..999)."""
    if not 1 <= instance <= 999:
        raise ValueError(f"instance number must be in 1..999, got {instance}")
    return CAT[name] * 1000 + instance


# --------------------------------------------------------------------------------------------------- boxes
@dataclass
class BoxSet:
    """Boxes oriented about z: ``center`` [B,3], ``half`` sizes [B,3], ``yaw`` [B] plus material and labels."""

    center: np.ndarray  # float64 [B, 3]
    half: np.ndarray  # float64 [B, 3]
    yaw: np.ndarray  # float64 [B]
    tex: np.ndarray  # int64 [B]
    tint: np.ndarray  # float32 [B, 3]
    scale: np.ndarray  # float32 [B] metres per texture tile
    off: np.ndarray  # float32 [B, 2] texture offset in metres
    win: np.ndarray  # float32 [B, 4] window spacing (u, v) in metres and open fraction (u, v); spacing 0 = none
    pid: np.ndarray  # int64 [B] panoptic id
    dynamic: np.ndarray  # bool [B]
    key: np.ndarray  # int64 [B] per-box random key (window variation)

    def __len__(self) -> int:
        return int(self.center.shape[0])

    @staticmethod
    def concat(sets: list["BoxSet"]) -> "BoxSet":
        sets = [s for s in sets if len(s)]
        if not sets:
            return BoxBuilder().build()
        return BoxSet(**{f: np.concatenate([getattr(s, f) for s in sets]) for f in BoxSet.__dataclass_fields__})


class BoxBuilder:
    """Collects boxes one by one (``add``) and freezes them into a :class:`BoxSet`."""

    def __init__(self) -> None:
        self.rows: list[dict] = []

    def add(self, center, size, *, yaw: float = 0.0, tex: str = "noise", tint=(0.6, 0.6, 0.6), scale: float = 4.0,
            off=(0.0, 0.0), win=(0.0, 0.0, 0.0, 0.0), pid: int, dynamic: bool = False, key: int = 0) -> None:
        """``center`` is the box centre; ``size`` full extents (length along its x, width, height)."""
        self.rows.append(dict(center=center, half=[s / 2.0 for s in size], yaw=yaw, tex=tex_id(tex), tint=tint,
                              scale=scale, off=off, win=win, pid=pid, dynamic=dynamic, key=key))

    def add_on_ground(self, x: float, y: float, size, **kw) -> None:
        self.add((x, y, size[2] / 2.0), size, **kw)

    def build(self) -> BoxSet:
        r = self.rows
        return BoxSet(
            center=np.array([x["center"] for x in r], np.float64).reshape(-1, 3),
            half=np.array([x["half"] for x in r], np.float64).reshape(-1, 3),
            yaw=np.array([x["yaw"] for x in r], np.float64).reshape(-1),
            tex=np.array([x["tex"] for x in r], np.int64).reshape(-1),
            tint=np.array([x["tint"] for x in r], np.float32).reshape(-1, 3),
            scale=np.array([x["scale"] for x in r], np.float32).reshape(-1),
            off=np.array([x["off"] for x in r], np.float32).reshape(-1, 2),
            win=np.array([x["win"] for x in r], np.float32).reshape(-1, 4),
            pid=np.array([x["pid"] for x in r], np.int64).reshape(-1),
            dynamic=np.array([x["dynamic"] for x in r], bool).reshape(-1),
            key=np.array([x["key"] for x in r], np.int64).reshape(-1),
        )


@dataclass
class MovingObject:
    """Rigid boxes in an object frame moved by a per-frame world pose ``(x, y, yaw)`` (object on the ground)."""

    pid: int
    name: str
    parts: BoxSet  # centres/yaws in the object frame
    poses: np.ndarray  # float64 [N, 3]: x, y, yaw per frame
    size: tuple[float, float, float]  # bounding extents (length, width, height), for objects.json

    def at(self, i: int) -> BoxSet:
        x, y, yaw = self.poses[i]
        c, s = math.cos(yaw), math.sin(yaw)
        p = self.parts
        cen = p.center.copy()
        cen[:, 0] = x + c * p.center[:, 0] - s * p.center[:, 1]
        cen[:, 1] = y + s * p.center[:, 0] + c * p.center[:, 1]
        return BoxSet(center=cen, half=p.half, yaw=p.yaw + yaw, tex=p.tex, tint=p.tint, scale=p.scale, off=p.off,
                      win=p.win, pid=p.pid, dynamic=p.dynamic, key=p.key)

    def pose7(self, i: int) -> list[float]:
        """Object-to-world pose ``[tx, ty, tz, qx, qy, qz, qw]`` (rotation about z) of frame ``i``."""
        x, y, yaw = (float(v) for v in self.poses[i])
        return [x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)]


@dataclass
class GroundSample:
    """What the ground shader says about ground points: label, texture, tint and painted overlay."""

    pid: np.ndarray  # int64 [N]
    tex: np.ndarray  # int64 [N]
    tint: np.ndarray  # float32 [N, 3]
    scale: np.ndarray  # float32 [N] metres per tile
    paint: np.ndarray  # float32 [N] coverage of markings in [0, 1]
    paint_rgb: np.ndarray  # float32 [3]


GroundFn = Callable[[np.ndarray, np.ndarray, np.ndarray], GroundSample]


@dataclass(frozen=True)
class Relief:
    """A gentle rise of the ground along world x: a raised cosine ``height`` m high and ``2 * half_length`` m long,
    centred at ``x = centre`` (slopes of a few per cent: a crest a car drives over)."""

    height: float
    centre: float
    half_length: float

    def z(self, x: np.ndarray) -> np.ndarray:
        u = np.clip((np.asarray(x, np.float64) - self.centre) / self.half_length, -1.0, 1.0)
        return 0.5 * self.height * (1.0 + np.cos(np.pi * u))

    def slope(self, x: np.ndarray) -> np.ndarray:
        u = (np.asarray(x, np.float64) - self.centre) / self.half_length
        inside = np.abs(u) < 1.0
        return np.where(inside, -0.5 * self.height * np.pi / self.half_length * np.sin(np.pi * u), 0.0)


@dataclass
class Scene:
    static: BoxSet
    ground: GroundFn
    movers: list[MovingObject] = field(default_factory=list)
    sky: bool = True
    light: tuple[float, float, float] = (0.35, -0.5, 0.79)  # direction towards the sun (world, z up)
    ambient: float = 0.5
    look: Optional[Callable[[np.ndarray, np.ndarray, int], np.ndarray]] = None  # camera rendition (domain.Look)
    # the ground's height along world x (``relief.z(x)``, its slope ``relief.slope(x)``); None: the plane z = 0
    relief: Optional[Relief] = None

    def boxes_at(self, i: int) -> BoxSet:
        if not self.movers:
            return self.static
        return BoxSet.concat([self.static] + [m.at(i) for m in self.movers])

    def moving_ids(self) -> list[int]:
        return sorted({m.pid for m in self.movers})


# --------------------------------------------------------------------------------------------------- paths
class RoundedRect:
    """A rectangle ``|x| <= a, |y| <= b`` with corners rounded by radius ``r``, traversed counter-clockwise.

    Arc length ``s`` starts at ``(0, -b)`` heading +x.  ``offset(o)`` is the parallel curve at distance ``o``
    outwards (again a rounded rectangle).
    """

    def __init__(self, a: float, b: float, r: float):
        if not (0 < r <= min(a, b)):
            raise ValueError(f"corner radius {r} must be in (0, min(a, b)]")
        self.a, self.b, self.r = float(a), float(b), float(r)
        ax, by = a - r, b - r
        hp = math.pi / 2
        # (kind, start point or arc centre, heading or start angle, length)
        self.segments = [
            ("line", (0.0, -b), 0.0, ax),
            ("arc", (ax, -by), -hp, hp * r),
            ("line", (a, -by), hp, 2 * by),
            ("arc", (ax, by), 0.0, hp * r),
            ("line", (ax, b), math.pi, 2 * ax),
            ("arc", (-ax, by), hp, hp * r),
            ("line", (-a, by), 3 * hp, 2 * by),
            ("arc", (-ax, -by), math.pi, hp * r),
            ("line", (-ax, -b), 0.0, ax),
        ]
        self.perimeter = sum(s[3] for s in self.segments)

    def offset(self, o: float) -> "RoundedRect":
        return RoundedRect(self.a + o, self.b + o, self.r + o)

    def point(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position ``(x, y)`` and heading (radians) at arc length ``s`` (any real; wraps around)."""
        s = np.mod(np.asarray(s, np.float64), self.perimeter)
        x, y, h = np.zeros_like(s), np.zeros_like(s), np.zeros_like(s)
        s0 = 0.0
        for kind, p, ang, length in self.segments:
            m = (s >= s0) & (s < s0 + length + 1e-12)
            ds = s[m] - s0
            if kind == "line":
                x[m] = p[0] + ds * math.cos(ang)
                y[m] = p[1] + ds * math.sin(ang)
                h[m] = ang
            else:
                phi = ang + ds / self.r
                x[m] = p[0] + self.r * np.cos(phi)
                y[m] = p[1] + self.r * np.sin(phi)
                h[m] = phi + math.pi / 2
            s0 += length
        return x, y, h

    def signed_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Signed distance to the curve (positive outside)."""
        qx = np.abs(x) - (self.a - self.r)
        qy = np.abs(y) - (self.b - self.r)
        outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
        return outside + np.minimum(np.maximum(qx, qy), 0.0) - self.r

    def along(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """A coordinate along the curve near it (metres; piecewise: resets between straights and arcs)."""
        qx = np.abs(x) - (self.a - self.r)
        qy = np.abs(y) - (self.b - self.r)
        arc = (qx > 0) & (qy > 0)
        return np.where(arc, self.r * np.arctan2(qy, qx), np.where(qx > qy, y, x))


def smooth_heading(fn: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]], s: np.ndarray,
                   window: float) -> np.ndarray:
    """Heading at ``s`` averaged over ``s +- window`` (tangent vectors averaged, so it is continuous)."""
    offs = np.linspace(-window, window, 9)
    wts = np.exp(-0.5 * (offs / (window / 2.0 + 1e-9)) ** 2)
    cx = np.zeros_like(s, dtype=np.float64)
    cy = np.zeros_like(s, dtype=np.float64)
    for o, w in zip(offs, wts):
        _, _, h = fn(s + o)
        cx += w * np.cos(h)
        cy += w * np.sin(h)
    return np.arctan2(cy, cx)


# --------------------------------------------------------------------------------------------------- cameras
def look_rotation(forward: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world rotation [N,3,3] (columns: camera x right, y down, z forward) for world forward vectors."""
    f = np.asarray(forward, np.float64)
    f = f / np.linalg.norm(f, axis=-1, keepdims=True)
    upv = np.broadcast_to(np.asarray(up, np.float64), f.shape)
    right = np.cross(f, upv)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(f, right)
    return np.stack([right, down, f], axis=-1)


def rot_axis(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrices [N,3,3] about unit ``axis`` [N,3] by ``angle`` [N]."""
    axis = np.asarray(axis, np.float64)
    angle = np.asarray(angle, np.float64)[..., None, None]
    k = np.zeros(axis.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2] = -axis[..., 2], axis[..., 1]
    k[..., 1, 0], k[..., 1, 2] = axis[..., 2], -axis[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -axis[..., 1], axis[..., 0]
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def camera_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``R_wc`` [N,3,3] of a camera with heading ``yaw`` (about world z, 0 = +x), ``pitch`` (positive looks
    up) and ``roll`` (about the optical axis), world z up."""
    yaw, pitch, roll = (np.asarray(v, np.float64) for v in (yaw, pitch, roll))
    fwd = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=-1)
    r = look_rotation(fwd)
    return r @ rot_axis(np.broadcast_to([0.0, 0.0, 1.0], fwd.shape), roll)


def smooth_noise(t: np.ndarray, seed: int, amp: float, freqs=(0.07, 0.13, 0.23, 0.41)) -> np.ndarray:
    """Deterministic smooth wobble: a sum of sinusoids with seeded phases, peak about ``amp``."""
    rng = np.random.default_rng(seed)
    out = np.zeros_like(np.asarray(t, np.float64))
    for f in freqs:
        out += np.sin(2 * math.pi * f * t + rng.uniform(0, 2 * math.pi)) / len(freqs)
    return amp * out * 1.6


def pose_matrices(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[N,4,4] from rotations [N,3,3] and translations [N,3]."""
    T = np.zeros((R.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def hash01(*ints: np.ndarray) -> np.ndarray:
    """Deterministic per-integer-tuple pseudo-random value in [0, 1)."""
    h = np.zeros(np.broadcast(*ints).shape, np.uint64)
    for k, v in zip((0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D, 0x27D4EB2F), ints):
        h = (h ^ (np.asarray(v).astype(np.int64).astype(np.uint64) * np.uint64(k))) & np.uint64(0xFFFFFFFF)
        h = (h * np.uint64(0x2C1B3C6D) + np.uint64(0x297A2D39)) & np.uint64(0xFFFFFFFF)
        h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(1 << 24)

