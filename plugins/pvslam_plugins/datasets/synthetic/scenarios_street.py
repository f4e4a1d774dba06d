"""Street benchmark scenarios: a street full of large moving vehicles, and a fast forward drive with little parallax.

* ``busy_street``: a four-lane street with three cross streets (positions from the seed); the camera drives at
  6.5-7.5 m/s, 10 fps, while a lead vehicle (bus or car) drives ahead in its lane and later pulls away, buses and
  cars overtake on the right, oncoming traffic fills both opposite lanes and buses/trucks/cars cross at the
  intersections a few metres ahead.  Every vehicle is drawn from the seed; crossing vehicles are timed so they never
  drive through the camera or another vehicle.  Moving vehicles cover up to about a third of the image.
* ``forward_low_parallax``: a straight four-lane highway (concrete median and side barriers, lamp posts, signs,
  a few tree clusters), 18-24 m/s at 10 fps; everything else -- buildings, hills -- is 40-250 m away or further,
  so the centre of the image moves very little (KITTI 01-like).  Depths beyond 256 m are written as 0.

World streets run along +x; the camera drives on the right (``y = -1.75``).  A shorter sequence (``num_frames``)
is a prefix of the default one: the world is built for at least the default length.
"""
from __future__ import annotations

import math

import numpy as np

from .layout import (Ids, StreetProfile, add_building, add_pole, add_tree, car_parts, populate_side, road_ground,
                     straight_street)
from .render import Camera
from .scenario_base import Scenario, count_frames
from .scene import BoxBuilder, MovingObject, Scene, camera_rotation, pose_matrices, smooth_noise, stuff_id

LANE = -1.75  # the camera's lane (centre line y = 0, right-hand traffic along +x)


# ------------------------------------------------------------------------------------------------ busy street
class _Traffic:
    """Moving vehicles defined on the time grid ``t``; keeps their footprints for the crossing-conflict check."""

    def __init__(self, rng: np.random.Generator, ids: Ids, t: np.ndarray):
        self.rng, self.ids, self.t = rng, ids, t
        self.movers: list[MovingObject] = []
        # footprints of the along-street vehicles: (x(t), y, half length, half width)
        self.along: list[tuple[np.ndarray, float, float, float]] = []
        self.crossing: list[tuple[float, np.ndarray, float, float]] = []  # (x, y(t), half length, half width)

    def parts(self, kind: str):
        cat = "truck" if kind == "truck" else "car"
        pid = self.ids.new(cat)
        parts, size = car_parts(self.rng, pid, dynamic=True, kind=kind)
        return cat, pid, parts, size

    def add_along(self, kind: str, x: np.ndarray, y: float, rear: bool = False) -> None:
        """A vehicle along the street at ``x(t)`` (its centre, or with ``rear`` its rear end), lane ``y``."""
        cat, pid, parts, size = self.parts(kind)
        if rear:
            x = x + size[0] / 2
        heading = 0.0 if np.mean(np.diff(x)) >= 0 else math.pi
        self.movers.append(MovingObject(pid, cat, parts, np.stack([x, np.full_like(x, y), np.full_like(x, heading)],
                                                                   1), size))
        self.along.append((x, y, size[0] / 2, size[1] / 2))

    def add_crossing(self, kind: str, xc: float, vy: float, cam_x: np.ndarray, tries) -> bool:
        """A vehicle crossing the street at ``x = xc`` with speed ``vy``, its centre on the camera's lane at the
        first of the times ``tries`` at which it collides with nothing; False (not added) if none fits."""
        cat, pid, parts, size = self.parts(kind)
        hl, hw, margin = size[0] / 2, size[1] / 2, 1.0  # footprints overlap (plus a margin) = a collision
        for tp in tries:
            y = LANE + vy * (self.t - tp)
            clash = (np.abs(cam_x - xc) < 2.5 + hw + margin) & (np.abs(y - LANE) < hl + 1.0 + margin)  # the camera car
            for x, ya, h, w in self.along:
                clash = clash | ((np.abs(x - xc) < h + hw + margin) & (np.abs(y - ya) < hl + w + margin))
            for xo, yo, h, w in self.crossing:
                if abs(xo - xc) < w + hw + margin:
                    clash = clash | (np.abs(y - yo) < hl + h + margin)
            if not bool(clash.any()):
                self.crossing.append((xc, y, hl, hw))
                heading = math.pi / 2 if vy > 0 else -math.pi / 2
                self.movers.append(MovingObject(pid, cat, parts, np.stack(
                    [np.full_like(self.t, xc), y, np.full_like(self.t, heading)], 1), size))
                return True
        return False


def busy_street(num_frames, cam: Camera, seed: int, laps) -> Scenario:
    rng = np.random.default_rng([seed, 6])  # layout
    vr = np.random.default_rng([seed, 61])  # traffic
    fps, n_default = 10.0, 300
    n = count_frames(num_frames, None, n_default, 1.0)
    speed = float(rng.uniform(6.5, 7.5))
    t_all = np.arange(max(n, n_default)) / fps  # the world and the traffic are built for at least the default
    T = float(t_all[-1])
    length = speed * T + 160.0
    x_start = -40.0
    c1 = float(rng.uniform(50, 70))
    crossings = (c1, c1 + float(rng.uniform(55, 70)), c1 + float(rng.uniform(125, 145)))
    b = BoxBuilder()
    ids = Ids()
    ground = straight_street(b, rng, ids, x_start, length, crossings)

    t = t_all
    cam_x = speed * t
    traffic = _Traffic(vr, ids, t)
    # the lead vehicle: its rear 12-18 m ahead in the camera's lane, breathing +-3 m, pulling away after 0.4-0.65
    # of the drive's duration
    d0, t_leave = float(vr.uniform(12, 18)), float(vr.uniform(0.4, 0.65)) * T
    gap = d0 + 3.0 * np.sin(2 * math.pi * t / float(vr.uniform(8, 14)) + float(vr.uniform(0, 2 * math.pi)))
    gap = gap + 0.5 * 1.5 * np.maximum(t - t_leave, 0.0) ** 2
    traffic.add_along("truck" if vr.random() < 0.5 else "car", cam_x + gap, LANE, rear=True)
    # overtaking on the right: one lane speed (no vehicle drives into another), a bus or truck first
    v_r = speed + float(vr.uniform(2.5, 4.0))
    x0 = -float(vr.uniform(12, 25))
    for k in range(int(vr.integers(3, 5))):
        kind = "truck" if k == 0 or vr.random() < 0.4 else "car"
        traffic.add_along(kind, x0 + v_r * t, -5.25)
        x0 -= float(vr.uniform(25, 45))
    # oncoming traffic in both opposite lanes
    for lane, lo, hi in ((1.75, 8.0, 10.0), (5.25, 7.0, 9.0)):
        v_o = -float(vr.uniform(lo, hi))
        x0 = float(vr.uniform(25, 50))
        while x0 < length + (-v_o) * T:
            traffic.add_along("truck" if vr.random() < 0.4 else "car", x0 + v_o * t, lane)
            x0 += float(vr.uniform(25, 60))
    # crossing traffic: each vehicle on the camera's lane when the camera is 13-22 m before the crossing
    for c in crossings:
        for _ in range(int(vr.integers(1, 3))):
            vy = float(vr.choice([-1.0, 1.0])) * float(vr.uniform(6.0, 8.0))
            xc = c + (1.75 if vy > 0 else -1.75)
            tries = (xc - np.array([float(vr.uniform(13, 22))] + list(np.linspace(13, 40, 12)))) / speed
            traffic.add_crossing("truck" if vr.random() < 0.6 else "car", xc, vy, cam_x, tries)
    movers = [MovingObject(m.pid, m.name, m.parts, m.poses[:n], m.size) for m in traffic.movers]
    scene = Scene(static=b.build(), ground=ground, movers=movers, sky=True)

    tn = t[:n]
    s = seed * 23
    yaw = smooth_noise(tn, s + 1, np.deg2rad(1.2), freqs=(0.05, 0.09, 0.15, 0.2))
    pitch = np.deg2rad(-1.0) + smooth_noise(tn, s + 2, np.deg2rad(0.4), freqs=(0.3, 0.55, 0.9, 1.3))
    roll = smooth_noise(tn, s + 3, np.deg2rad(0.3), freqs=(0.25, 0.5, 0.85, 1.2))
    pos = np.stack([cam_x[:n], LANE + smooth_noise(tn, s + 4, 0.15, freqs=(0.03, 0.07, 0.11, 0.17)),
                    1.5 + smooth_noise(tn, s + 5, 0.01, freqs=(0.7, 1.1, 1.7, 2.3))], axis=1)
    poses = pose_matrices(camera_rotation(yaw, pitch, roll), pos)
    return Scenario("busy_street", scene, poses, tn, cam, depth_scale=256.0, loop_radius=3.0)


# ------------------------------------------------------------------------------------------------ low parallax
def forward_low_parallax(num_frames, cam: Camera, seed: int, laps) -> Scenario:
    rng = np.random.default_rng([seed, 7])
    fps, n_default = 10.0, 300
    n = count_frames(num_frames, None, n_default, 1.0)
    speed = float(rng.uniform(18.0, 24.0))
    T = (max(n, n_default) - 1) / fps
    road_end = speed * T
    x0, x1 = -60.0, road_end + 260.0
    b = BoxBuilder()
    # concrete median and right barrier ("wall"), in 40 m pieces with their own texture offsets
    for y, h in ((0.0, 0.8), (-9.3, 0.75)):
        for xa in np.arange(x0, x1, 40.0):
            b.add_on_ground(float(xa + 20.0), y, (40.0, 0.35, h), tex="fine_noise", tint=(0.62, 0.62, 0.6),
                            scale=2.0, off=(float(rng.uniform(0, 30)), 0.0), pid=stuff_id("wall"))
    # lamp posts and signs on the right; tree clusters on either side
    xa = x0 + float(rng.uniform(0, 30))
    while xa < x1:
        add_pole(b, float(xa), -10.3, h=float(rng.uniform(7.0, 9.0)))
        if rng.random() < 0.25:  # a sign board on two posts
            w = float(rng.uniform(2.5, 4.0))
            for dx in (-w / 3, w / 3):
                add_pole(b, float(xa + 8.0 + dx), -11.5, h=2.2)
            b.add((float(xa + 8.0), -11.5, 3.0), (w, 0.1, 1.8), tex="text", tint=(0.3, 0.5, 0.35), scale=w,
                  pid=stuff_id("pole"), off=(w / 2, 0.9))
        xa += float(rng.uniform(40, 70))
    xa = x0 + float(rng.uniform(0, 40))
    while xa < x1:
        side = float(rng.choice([-1.0, 1.0]))
        yc = side * float(rng.uniform(14, 30))
        for _ in range(int(rng.integers(3, 7))):
            add_tree(b, rng, float(xa + rng.uniform(-10, 10)), float(yc + side * rng.uniform(0, 8)))
        xa += float(rng.uniform(60, 110))
    # buildings 40-200 m to the sides, hills 150-250 m to the sides and beyond the end of the road
    for side in (-1.0, 1.0):
        xa = x0 + float(rng.uniform(0, 40))
        while xa < x1:
            w = float(rng.uniform(15, 60))
            add_building(b, rng, float(xa + w / 2), side * float(rng.uniform(40, 200)), 0.0, w,
                         float(rng.uniform(10, 30)), float(rng.uniform(8, 35)), key=int(rng.integers(1 << 30)))
            xa += w + float(rng.uniform(30, 110))
        xa = x0 - 100.0
        while xa < x1 + 100.0:
            w = float(rng.uniform(80, 200))
            _hill(b, rng, float(xa + w / 2), side * float(rng.uniform(150, 250)), w)
            xa += w * float(rng.uniform(0.6, 1.0))
    for yc in np.arange(-240.0, 241.0, 80.0):
        _hill(b, rng, float(road_end + rng.uniform(150, 240)), float(yc + rng.uniform(-20, 20)),
              float(rng.uniform(90, 140)))
    ground = road_ground(lambda x, y: y, lambda x, y: x, half_width=7.5, sidewalk=2.5,
                         lane_lines=((-7.0, False), (-3.5, True), (3.5, True), (7.0, False)), inner_tex="grass",
                         outer_tex="grass")
    scene = Scene(static=b.build(), ground=ground, sky=True)

    t = np.arange(n) / fps
    s = seed * 29
    sway = smooth_noise(t, s + 1, 0.2, freqs=(0.02, 0.05, 0.08, 0.13))
    yaw = smooth_noise(t, s + 2, np.deg2rad(0.5), freqs=(0.03, 0.07, 0.11, 0.17))
    pitch = np.deg2rad(-0.5) + smooth_noise(t, s + 3, np.deg2rad(0.3), freqs=(0.3, 0.55, 0.9, 1.3))
    roll = smooth_noise(t, s + 4, np.deg2rad(0.3), freqs=(0.25, 0.5, 0.85, 1.2))
    pos = np.stack([speed * t, LANE + sway, 1.65 + smooth_noise(t, s + 5, 0.01, freqs=(0.7, 1.1, 1.7, 2.3))], 1)
    poses = pose_matrices(camera_rotation(yaw, pitch, roll), pos)
    return Scenario("forward_low_parallax", scene, poses, t, cam, depth_scale=256.0, loop_radius=3.0)


def _hill(b: BoxBuilder, rng: np.random.Generator, x: float, y: float, w: float) -> None:
    """A distant hill: a wide, low, grassy or rocky box (terrain)."""
    tex = "grass" if rng.random() < 0.6 else "gravel"
    tint = (0.4, 0.55, 0.32) if tex == "grass" else (0.6, 0.55, 0.48)
    tint = tuple(float(c) for c in np.clip(np.array(tint) + rng.uniform(-0.06, 0.06, 3), 0, 1))
    b.add_on_ground(x, y, (w, float(rng.uniform(40, 90)), float(rng.uniform(15, 55))),
                    yaw=float(rng.uniform(-0.3, 0.3)), tex=tex, tint=tint, scale=float(rng.uniform(20, 40)),
                    off=(float(rng.uniform(0, 50)), float(rng.uniform(0, 50))), pid=stuff_id("terrain"))
