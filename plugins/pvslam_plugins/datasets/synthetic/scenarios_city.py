"""``driving_city``: a car camera drives a figure-eight through a grid of city blocks.

Three north-south streets (``x = -W, 0, W``) cross two east-west streets (``y = -h, h``), with 30 m stubs beyond
the grid; the block sizes (``W`` 44-56 m, ``2h`` 36-46 m), the buildings, parked cars, trees and the skyline come
from the seed.  The route (right-hand traffic, 2 m right of the centre line, 10 fps) loops
counter-clockwise around the east block (left turns), then clockwise around the west block (right turns): the
middle street is driven twice in the same direction and the end returns to the start.  The car drives 8 m/s on
the straights and slows to 5.5 m/s through the turns (braking and accelerating over ~6 m), so a right turn (8 m
radius) peaks at ~40 deg/s.  ``laps`` sets the length (default 1.05 laps, the last frames revisit the first ones).
"""
from __future__ import annotations

import math

import numpy as np

from .layout import Ids, StreetProfile, add_building, populate_side, road_ground
from .render import Camera
from .scenario_base import PolylinePath, Scenario, count_frames
from .scene import BoxBuilder, Scene, camera_rotation, pose_matrices, smooth_heading, smooth_noise

HALF_WIDTH, SIDEWALK, STUB = 6.0, 3.0, 30.0


def grid_ground(xs: np.ndarray, ys: np.ndarray, x_ext: float, y_ext: float):
    """Ground shader of a street grid: north-south streets at ``xs`` (for ``|y| <= y_ext``) and east-west streets at
    ``ys`` (for ``|x| <= x_ext``); lane markings along each street, none inside the intersections."""
    big = 1e6

    def nearest(x, y):
        dv = np.where(np.abs(y)[:, None] <= y_ext, x[:, None] - xs[None], big)  # [N, len(xs)] signed
        dh = np.where(np.abs(x)[:, None] <= x_ext, y[:, None] - ys[None], big)
        iv = np.argmin(np.abs(dv), axis=1)
        ih = np.argmin(np.abs(dh), axis=1)
        v = np.take_along_axis(dv, iv[:, None], 1)[:, 0]
        h = np.take_along_axis(dh, ih[:, None], 1)[:, 0]
        return v, h

    def lateral(x, y):
        v, h = nearest(x, y)
        return np.where(np.abs(v) <= np.abs(h), v, h)

    def along(x, y):
        v, h = nearest(x, y)
        return np.where(np.abs(v) <= np.abs(h), y, x)

    base = road_ground(lateral, along, half_width=HALF_WIDTH, sidewalk=SIDEWALK,
                       lane_lines=((0.0, True), (-3.9, False), (3.9, False)), inner_tex="grass", outer_tex="gravel")

    def fn(x, y, fp):
        g = base(x, y, fp)
        v, h = nearest(x, y)
        crossing = (np.abs(v) < HALF_WIDTH) & (np.abs(h) < HALF_WIDTH)
        g.paint[crossing] = 0.0
        return g

    return fn


def _drive(route: PolylinePath, lane, straight: float, turn: float, step: float = 0.05):
    """Timing of a drive along ``lane``: ``straight`` m/s, ``turn`` m/s on the fillets, smooth over ~6 m.

    Returns ``(s_of_t, lap_seconds)``: the path parameter at any times (laps repeat) and the time of one lap.
    """
    s = np.arange(0.0, route.perimeter + step / 2, step)
    x, y, h = route.point(s)
    curved = np.abs(np.diff(np.unwrap(h), append=h[-1])) > 1e-9  # on a fillet
    k = int(round(3.0 / step))
    ker = np.exp(-0.5 * (np.arange(-3 * k, 3 * k + 1) / k) ** 2)
    ker /= ker.sum()
    slow = np.convolve(np.concatenate([curved[-3 * k:], curved, curved[:3 * k]]).astype(float), ker, "valid")
    v = straight - (straight - turn) * np.clip(slow / 0.5, 0.0, 1.0)  # full turn speed once half the window curves
    lx, ly, _ = lane(s)
    dl = np.hypot(np.diff(lx), np.diff(ly))  # lane metres per step of s
    t_s = np.concatenate([[0.0], np.cumsum(dl / (0.5 * (v[1:] + v[:-1])))])
    lap = float(t_s[-1])

    def s_of_t(t):
        t = np.asarray(t, np.float64)
        q, r = np.divmod(t, lap)
        return q * route.perimeter + np.interp(r, t_s, s)

    return s_of_t, lap


def driving_city(num_frames, cam: Camera, seed: int, laps) -> Scenario:
    rng = np.random.default_rng([seed, 8])
    W, h = float(rng.uniform(44, 56)), float(rng.uniform(18, 23))
    xs, ys = np.array([-W, 0.0, W]), np.array([-h, h])
    x_ext, y_ext = W + STUB, h + STUB
    b = BoxBuilder()
    ids = Ids()
    prof = StreetProfile(margin=HALF_WIDTH + SIDEWALK + 1.0)
    # every street segment between intersections (and the stubs), both sides; inner blocks get shallower buildings
    inner_depth = min(11.0, max(4.0, min(W, 2 * h) / 2 - prof.facade))
    segments = []
    for x in xs:  # north-south
        stops = [-y_ext, -h, h, y_ext]
        for a0, a1 in zip(stops[:-1], stops[1:]):
            segments.append((np.array([x, a0]), np.array([0.0, 1.0]), a1 - a0, -h < 0.5 * (a0 + a1) < h))
    for y in ys:  # east-west
        stops = [-x_ext, -W, 0.0, W, x_ext]
        for a0, a1 in zip(stops[:-1], stops[1:]):
            segments.append((np.array([a0, y]), np.array([1.0, 0.0]), a1 - a0, -W < 0.5 * (a0 + a1) < W))
    for start, e, length, in_grid in segments:
        nrm = np.array([e[1], -e[0]])
        for side in (1.0, -1.0):
            mid = start + e * length / 2 + side * nrm * 10.0
            inside = in_grid and abs(mid[0]) < W and abs(mid[1]) < h  # this side faces an inner block
            populate_side(b, rng, ids, start, e, side * nrm, length, prof,
                          max_depth=inner_depth if inside else 14.0)
    # a skyline ring of tall buildings around the grid: every place sees its own distant backdrop
    for (ox, oy), (ex, ey), span in (((-x_ext - 40, -y_ext - 45), (1, 0), 2 * x_ext + 80),
                                     ((x_ext + 45, -y_ext - 40), (0, 1), 2 * y_ext + 80),
                                     ((x_ext + 40, y_ext + 45), (-1, 0), 2 * x_ext + 80),
                                     ((-x_ext - 45, y_ext + 40), (0, -1), 2 * y_ext + 80)):
        pos = 0.0
        while pos < span:
            w = float(rng.uniform(12, 26))
            nx, ny = ey, -ex  # outwards
            d = float(rng.uniform(0, 12))
            add_building(b, rng, ox + ex * (pos + w / 2) + nx * d, oy + ey * (pos + w / 2) + ny * d,
                         math.atan2(ey, ex), w, float(rng.uniform(12, 20)), float(rng.uniform(15, 45)),
                         key=int(rng.integers(1 << 30)))
            pos += w + float(rng.uniform(2, 8))
    scene = Scene(static=b.build(), ground=grid_ground(xs, ys, x_ext, y_ext), sky=True)

    route = PolylinePath([(0.0, -h), (W, -h), (W, h), (0.0, h), (0.0, -h), (-W, -h), (-W, h), (0.0, h)], r=10.0)

    def lane(s):
        return route.offset_point(s, 2.0)

    fps = 10.0
    s_of_t, lap_s = _drive(route, lane, straight=8.0, turn=5.5)
    n = count_frames(num_frames, laps, lap_s * fps, 1.05)
    t = np.arange(n) / fps
    s = s_of_t(t)
    x, y, _ = lane(s)
    yaw = smooth_heading(lane, s, 3.0)
    k = seed * 31
    pitch = np.deg2rad(-1.5) + smooth_noise(t, k + 1, np.deg2rad(0.4), freqs=(0.3, 0.55, 0.9, 1.3))
    roll = smooth_noise(t, k + 2, np.deg2rad(0.3), freqs=(0.25, 0.5, 0.85, 1.2))
    z = 1.5 + smooth_noise(t, k + 3, 0.01, freqs=(0.7, 1.1, 1.7, 2.3))
    poses = pose_matrices(camera_rotation(yaw, pitch, roll), np.stack([x, y, z], axis=1))
    return Scenario("driving_city", scene, poses, t, cam, depth_scale=256.0, loop_radius=3.0)
