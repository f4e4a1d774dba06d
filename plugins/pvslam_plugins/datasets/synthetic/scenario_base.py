"""What every scenario builder returns (:class:`Scenario`) and the trajectory helpers the newer scenarios share.

Kept apart from :mod:`.scenarios` so the scenario modules (:mod:`.scenarios_indoor`, :mod:`.scenarios_street`,
:mod:`.scenarios_city`) can import it without an import cycle.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .render import Camera
from .scene import Scene


@dataclass
class Scenario:
    name: str
    scene: Scene
    poses: np.ndarray  # float64 [N, 4, 4] T_wc
    timestamps: np.ndarray  # float64 [N] seconds
    camera: Camera
    depth_scale: float  # depth PNG value = metres * depth_scale
    loop_radius: float  # revisit criterion: camera centres within this many metres ...
    loop_angle_deg: float = 20.0  # ... and optical axes within this angle
    loop_min_gap: int = 50  # ... and i > j + loop_min_gap
    params: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])


MAX_FRAMES = 1_000_000  # the longest sequence generated: a scenario holds a pose per frame in memory


def count_frames(num_frames: Optional[int], laps: Optional[float], per_lap: float, default_laps: float) -> int:
    """``num_frames`` if given, else ``laps`` (or ``default_laps``) times the frames of one lap (at most
    ``MAX_FRAMES``: ValueError naming the key otherwise)."""
    if num_frames is not None:
        n, what = float(num_frames), f"num_frames = {num_frames}"
    else:
        laps = default_laps if laps is None else laps
        n, what = laps * per_lap, f"laps = {laps} ({laps * per_lap:.0f} frames)"
    if not n <= MAX_FRAMES:  # (NaN too)
        raise ValueError(f"{what}: at most {MAX_FRAMES} frames can be generated")
    return int(num_frames) if num_frames is not None else max(1, int(round(n)))


def smootherstep(x: np.ndarray) -> np.ndarray:
    """``6x^5 - 15x^4 + 10x^3`` on [0, 1] (0 outside below, 1 above): zero velocity and acceleration at both ends,
    peak slope 1.875."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def turn_profile(t: np.ndarray, starts, amplitudes, durations) -> np.ndarray:
    """Sum of smooth turns: turn ``k`` adds ``amplitudes[k]`` (radians) between ``starts[k]`` and
    ``starts[k] + durations[k]`` (seconds); its peak rate is ``1.875 * amplitude / duration``."""
    out = np.zeros_like(np.asarray(t, np.float64))
    for t0, a, d in zip(starts, amplitudes, durations):
        out += a * smootherstep((t - t0) / d)
    return out


def window(t: np.ndarray, centre: float, half: float, ramp: float) -> np.ndarray:
    """1 inside ``|t - centre| <= half``, 0 beyond ``half + ramp``, smooth in between."""
    d = np.abs(np.asarray(t, np.float64) - centre)
    return 1.0 - smootherstep((d - half) / ramp)


def integrate(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cumulative trapezoid integral of ``v`` over ``t`` (starts at 0)."""
    if len(t) < 2:
        return np.zeros_like(np.asarray(t, np.float64))
    inc = 0.5 * (v[1:] + v[:-1]) * np.diff(t)
    return np.concatenate([[0.0], np.cumsum(inc)])


def vehicles_collide(paths, sizes, cam_xy: np.ndarray, margin: float = 0.5) -> bool:
    """Whether any two vehicles, or a vehicle and the camera car (5 x 2 m at ``cam_xy`` [N, 2]), overlap at any frame.

    ``paths`` [V] arrays [N, 3] of ``(x, y, yaw)`` with the yaw along an axis; ``sizes`` [V] ``(length, width, _)``.
    """
    if not paths:
        return False
    P = np.stack(paths)  # [V, N, 3]
    L = np.array([s[0] for s in sizes])[:, None] / 2 + margin
    W = np.array([s[1] for s in sizes])[:, None] / 2 + margin
    along = np.abs(np.cos(P[..., 2])) > 0.5
    hx, hy = np.where(along, L, W), np.where(along, W, L)  # [V, N] half extents
    box = np.stack([P[..., 0] - hx, P[..., 0] + hx, P[..., 1] - hy, P[..., 1] + hy], -1)  # [V, N, 4]
    cam = np.stack([cam_xy[:, 0] - 2.5, cam_xy[:, 0] + 2.5, cam_xy[:, 1] - 1.0, cam_xy[:, 1] + 1.0], -1)[None]
    box = np.concatenate([box, cam], 0)  # [V + 1, N, 4]
    a, b = box[:, None], box[None]
    ov = (a[..., 0] < b[..., 1]) & (b[..., 0] < a[..., 1]) & (a[..., 2] < b[..., 3]) & (b[..., 2] < a[..., 3])
    ov[np.arange(len(box)), np.arange(len(box))] = False
    return bool(ov.any())


class PolylinePath:
    """A closed polyline with circular fillets of radius ``r`` at its corners, parametrised by arc length.

    ``points`` [K, 2] are the corners in driving order (closed: the last connects to the first); the path starts at
    the middle of the first segment so that it never starts inside a turn.  ``point(s)`` returns ``x, y, heading``
    for any real ``s`` (wraps around), like :class:`~.scene.RoundedRect`.
    """

    def __init__(self, points, r: float):
        p = np.asarray(points, np.float64)
        k = len(p)
        if k < 3:
            raise ValueError(f"a closed path needs at least 3 corners, got {k}")
        segs = []  # (kind, a, b, length): lines (start xy, heading) and arcs (centre xy, start angle, signed radius)
        # fillet tangent points per corner
        tang = []
        for i in range(k):
            a, b, c = p[i - 1], p[i], p[(i + 1) % k]
            d0 = (b - a) / np.linalg.norm(b - a)
            d1 = (c - b) / np.linalg.norm(c - b)
            turn = math.atan2(d0[0] * d1[1] - d0[1] * d1[0], float(d0 @ d1))  # signed, left positive
            cut = r * math.tan(abs(turn) / 2.0)
            if cut > 0.5 * min(np.linalg.norm(b - a), np.linalg.norm(c - b)) + 1e-9:
                raise ValueError(f"corner {i} of the path is too tight for a fillet of radius {r}")
            tang.append((b - d0 * cut, b + d1 * cut, d0, d1, turn))
        # start at the middle of the first segment (points 0 and 1)
        order = list(range(1, k + 1))
        start = 0.5 * (tang[0][1] + tang[1][0])
        cur = start
        for idx in order:
            t_in, t_out, d0, d1, turn = tang[idx % k]
            seg_len = float(np.linalg.norm(t_in - cur))
            segs.append(("line", cur.copy(), math.atan2(d0[1], d0[0]), seg_len))
            if abs(turn) > 1e-9:
                left = np.array([-d0[1], d0[0]])
                sgn = 1.0 if turn > 0 else -1.0
                centre = t_in + sgn * r * left
                ang0 = math.atan2(t_in[1] - centre[1], t_in[0] - centre[0])
                segs.append(("arc", centre, ang0, sgn * r, abs(turn) * r))
            cur = t_out
        # close: from the last fillet's exit back to the start point
        segs.append(("line", cur.copy(), math.atan2(*(start - cur)[::-1]), float(np.linalg.norm(start - cur))))
        self.segments = segs
        self.r = float(r)
        self.perimeter = float(sum(s[-1] for s in segs))

    def point(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = np.mod(np.asarray(s, np.float64), self.perimeter)
        x, y, h = np.zeros_like(s), np.zeros_like(s), np.zeros_like(s)
        s0 = 0.0
        for seg in self.segments:
            length = seg[-1]
            m = (s >= s0) & (s < s0 + length + 1e-12)
            ds = s[m] - s0
            if seg[0] == "line":
                _, p0, hd, _ = seg
                x[m] = p0[0] + ds * math.cos(hd)
                y[m] = p0[1] + ds * math.sin(hd)
                h[m] = hd
            else:
                _, c, ang0, sr, _ = seg
                phi = ang0 + ds / sr  # counter-clockwise for a left turn (sr > 0)
                x[m] = c[0] + abs(sr) * np.cos(phi)
                y[m] = c[1] + abs(sr) * np.sin(phi)
                h[m] = phi + math.copysign(math.pi / 2, sr)
            s0 += length
        return x, y, h

    def offset_point(self, s: np.ndarray, right: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The point ``right`` metres to the right of the path (a lane), with the path's heading."""
        x, y, h = self.point(s)
        return x + right * np.sin(h), y - right * np.cos(h), h
