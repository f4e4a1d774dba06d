"""A suburban street whose ground is not one plane: raised lawns and pavements beside a narrow road, and a crest.

* ``suburban_street``: a straight two-lane road along +x at 10 fps, 8-11 m/s (slowing down and speeding up by up to
  about a third), the camera 1.65 m above the road (a KITTI-like car camera).  Kerbs lift the lawn on the left and the
  pavement (then a front lawn) on the right by 0.10-0.20 m; the road's half width changes from one kerb piece to the
  next (2.8-4.6 m: bays, narrowings, driveways left open), so the share of the near ground that is road changes as the
  car drives.  Part-way along, the road rises over a crest 0.2-0.6 m high and 40-80 m long (:class:`~.scene.Relief`,
  slopes up to 0.5-2.7 deg) and the car pitches with it; the lawns follow it in 1 m steps, houses, trees and posts
  stand at z = 0 (a crest's top hides their first few decimetres).  Houses are set back behind the lawns, a few cars
  are parked in the bays. Nothing moves.

Why: the near ground of a real street is not one plane, across the road (kerbs) or along it (crests), where a road
plane searched on it would read the raised surfaces and the rising road as a faster motion; the generator's other
streets are one plane.
"""
from __future__ import annotations

import numpy as np

from .layout import Ids, add_building, add_pole, add_static_vehicle, add_tree, road_ground
from .render import Camera
from .scenario_base import Scenario, count_frames
from .scene import BoxBuilder, Relief, Scene, camera_rotation, pose_matrices, smooth_noise, stuff_id

LANE = -1.4  # the camera's lane centre (right-hand traffic along +x; the centre line is y = 0)
LAWN = (0.36, 0.56, 0.28)
PAVING = (0.70, 0.68, 0.64)


def _kerb_pieces(rng: np.random.Generator, x0: float, x1: float) -> list[tuple[float, float, float]]:
    """``(start, end, kerb distance from the centre line)`` of one side's kerb pieces: 8-30 m long, the road's
    half width 2.8-4.6 m, and now and then a 3-6 m gap (a driveway or a lane's mouth)."""
    out, x = [], x0
    while x < x1:
        length = float(rng.uniform(8.0, 30.0))
        out.append((x, x + length, float(rng.uniform(2.8, 4.6))))
        x += length + (float(rng.uniform(3.0, 6.0)) if rng.random() < 0.25 else 0.0)
    return out


SINK = 0.1  # m: how far a slab on a crest reaches below the ground


def _steps(relief: Relief, xa: float, xb: float) -> list[tuple[float, float, float]]:
    """``(start, end, ground height)`` of a slab's pieces: one piece on flat ground, 1 m steps on a crest."""
    if xb <= relief.centre - relief.half_length or xa >= relief.centre + relief.half_length:
        return [(xa, xb, 0.0)]
    cuts = np.unique(np.concatenate([[xa, xb], np.arange(np.ceil(xa), xb, 1.0)]))
    return [(float(a), float(b), float(relief.z((a + b) / 2))) for a, b in zip(cuts[:-1], cuts[1:]) if b - a > 1e-6]


def _slab(b: BoxBuilder, rng: np.random.Generator, relief: Relief, xa: float, xb: float, y_in: float,
          width: float, side: float, height: float, tex: str, tint, pid: int) -> None:
    """A raised slab (lawn or pavement) from ``xa`` to ``xb``, from ``y_in`` outwards (``side`` +1 left, -1 right)."""
    tint = tuple(float(c) for c in np.clip(np.asarray(tint) + rng.uniform(-0.05, 0.05, 3), 0, 1))
    sc, off = float(rng.uniform(1.5, 3.0)), (float(rng.uniform(0, 30)), float(rng.uniform(0, 30)))
    for a, b_, z in _steps(relief, xa, xb):
        # on a crest each 1 m step stands on the ground below its middle (and reaches 0.1 m into it)
        b.add(((a + b_) / 2, side * (y_in + width / 2), z + (height - SINK) / 2), (b_ - a, width, height + SINK),
              tex=tex, tint=tint, scale=sc, off=(off[0] + a - xa, off[1]), pid=pid)


def suburban_street(num_frames, cam: Camera, seed: int, laps) -> Scenario:
    rng = np.random.default_rng([seed, 11])
    fps, n_default = 10.0, 120
    n = count_frames(num_frames, None, n_default, 1.0)
    speed = float(rng.uniform(8.0, 11.0))
    # the car slows down and speeds up again (by up to about a third), so its path is no constant-velocity line
    t_all = np.arange(max(n, n_default)) / fps
    v = speed * (1.0 + smooth_noise(t_all, seed * 31 + 6, 0.3, freqs=(0.04, 0.07, 0.11, 0.16)))
    x_all = np.concatenate([[0.0], np.cumsum(v[:-1]) / fps])
    road_end = float(x_all[-1])
    x0, x1 = -40.0, road_end + 120.0
    b, ids = BoxBuilder(), Ids()
    # a crest the car drives over part-way along the street (slopes up to 0.5-2.7 deg)
    relief = Relief(float(rng.uniform(0.2, 0.6)), float(rng.uniform(0.3, 0.6)) * road_end, float(rng.uniform(20, 40)))
    lawn, walk = stuff_id("terrain"), stuff_id("sidewalk")
    for side in (1.0, -1.0):
        for xa, xb, kerb in _kerb_pieces(rng, x0, x1):
            h = float(rng.uniform(0.10, 0.20))
            if side > 0:  # the left: a lawn from the kerb to the houses
                _slab(b, rng, relief, xa, xb, kerb, float(rng.uniform(6.0, 12.0)), side, h, "grass", LAWN, lawn)
                continue
            pave = float(rng.uniform(1.8, 3.5))  # the right: a pavement, then a front lawn at the same height
            _slab(b, rng, relief, xa, xb, kerb, pave, side, h, "brick", PAVING, walk)
            _slab(b, rng, relief, xa, xb, kerb + pave, float(rng.uniform(3.0, 8.0)), side, h, "grass", LAWN, lawn)
            if kerb > 4.4 and rng.random() < 0.5 and xb - xa > 7.0:  # a car parked in this piece's bay
                xc = float(rng.uniform(xa + 3.0, xb - 3.0))
                add_static_vehicle(b, rng, ids.new("car"), xc, -(kerb - 1.0), 0.0)
    for side in (1.0, -1.0):  # trees and lamp posts on the lawns, houses behind them
        x = x0 + float(rng.uniform(0, 10))
        while x < x1:
            y = side * float(rng.uniform(6.0, 9.0))
            if rng.random() < 0.7:
                add_tree(b, rng, x, y)
            else:
                add_pole(b, x, y)
            x += float(rng.uniform(7.0, 18.0))
        x = x0 + float(rng.uniform(0, 15))
        while x < x1:
            w = float(rng.uniform(8.0, 16.0))
            add_building(b, rng, x + w / 2, side * float(rng.uniform(14.0, 22.0)) + side * 5.0, 0.0, w,
                         float(rng.uniform(8.0, 12.0)), float(rng.uniform(5.0, 9.0)), key=int(rng.integers(1 << 30)))
            x += w + float(rng.uniform(4.0, 14.0))
    # the ground itself: asphalt wherever no slab covers it (the road, its bays and the driveways)
    ground = road_ground(lambda x, y: y, lambda x, y: x, half_width=40.0, sidewalk=0.0, lane_lines=((0.0, True),))
    scene = Scene(static=b.build(), ground=ground, sky=True, relief=relief)

    t, x = t_all[:n], x_all[:n]
    s = seed * 31
    sway = smooth_noise(t, s + 1, 0.15, freqs=(0.03, 0.07, 0.11, 0.17))
    yaw = smooth_noise(t, s + 2, np.deg2rad(0.8), freqs=(0.03, 0.07, 0.11, 0.17))
    pitch = np.deg2rad(-0.6) + smooth_noise(t, s + 3, np.deg2rad(0.5), freqs=(0.1, 0.25, 0.5, 0.9))
    roll = smooth_noise(t, s + 4, np.deg2rad(0.4), freqs=(0.15, 0.35, 0.7, 1.1))
    heave = smooth_noise(t, s + 5, 0.015, freqs=(0.5, 0.9, 1.4, 2.1))
    pos = np.stack([x, LANE + sway, 1.65 + heave + relief.z(x)], 1)
    pitch = pitch + np.arctan(relief.slope(x))  # the car pitches with the road
    poses = pose_matrices(camera_rotation(yaw, pitch, roll), pos)
    return Scenario("suburban_street", scene, poses, t, cam, depth_scale=256.0, loop_radius=3.0)
