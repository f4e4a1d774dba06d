"""The synthetic scenarios: scene + camera trajectory + timing, each a pure function of its parameters and seed.

* ``driving_loop`` (default): a forward-looking car camera (1.5 m high) drives counter-clockwise in the outer
  lane around a 96 x 56 m city block (rounded corners, smooth yaw, 8 m/s at 12 fps: about 444 frames a lap),
  1.1 laps by default so the last frames revisit the first ones; ``laps`` sets the length instead.
* ``moving_vehicles``: a straight four-lane street with two cross streets; the camera drives forward while a lead
  car, overtaking cars, oncoming cars and a bus, and crossing vehicles move independently.
* ``indoor_handheld``: an 8 x 6 x 2.8 m room with posters and furniture; a handheld camera loops around it
  with smooth random 6-DoF wobble and revisits its start.
* the benchmark scenarios of :mod:`.scenarios_indoor` (``handheld_fast``, ``indoor_textureless``),
  :mod:`.scenarios_street` (``busy_street``, ``forward_low_parallax``) and :mod:`.scenarios_city`
  (``driving_city``).

Seed 0 of the first three is what the published figures were measured on and never changes.  Other seeds of
``moving_vehicles`` and ``indoor_handheld`` also vary vehicle placement (collision-free) / wall textures and
furniture since a later content revision (:func:`revision`; the cache key includes it, so an older cached folder
is not reused).
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import numpy as np

from .layout import (Ids, StreetProfile, add_building, add_pole, add_tree, car_parts, populate_side, road_ground,
                     straight_street)
from .render import Camera
from .scenario_base import Scenario, count_frames, vehicles_collide
from .scene import (BoxBuilder, GroundSample, MovingObject, RoundedRect, Scene, camera_rotation, pose_matrices,
                    smooth_heading, smooth_noise, stuff_id)
from .textures import tex_id

SCENARIOS: dict[str, str] = {
    "driving_loop": "car camera driving 1.1 laps around a 96x56 m city block (buildings, parked cars, trees); "
                    "the end revisits the start",
    "driving_block": "the driving loop around a small 44x26 m block: 1.1 laps, about 210 frames (short loop "
                     "closure tests)",
    "moving_vehicles": "car camera on a straight four-lane street with overtaking, oncoming and crossing vehicles",
    "indoor_handheld": "handheld 6-DoF camera looping around a furnished room with posters; revisits its start",
    "handheld_fast": "handheld camera at 30 Hz in a furnished room: fast turns up to ~300 deg/s, some of them "
                     "near-pure rotations while standing still",
    "indoor_textureless": "handheld camera at 30 Hz in a texture-poor room: large plain walls, few posters",
    "busy_street": "car camera on a street full of large moving vehicles (buses, trucks, cars: crossing, oncoming, "
                   "overtaking, a lead vehicle) covering up to about a third of the image",
    "forward_low_parallax": "car camera at highway speed on a long straight road, structure mostly far away "
                            "(little parallax in the image centre, like KITTI 01)",
    "driving_city": "car camera driving a figure-eight through a grid of city blocks (left and right turns); "
                    "revisits the middle street and its start",
    "suburban_street": "car camera at 10 Hz on a narrow suburban street: kerbs raise the lawns and pavements, the "
                       "road's width changes and it rises over a crest (the near ground is not one plane, like "
                       "KITTI 06)",
}
DEFAULT_SCENARIO = "driving_loop"
# Content revision of a scenario's non-zero seeds (0 = as first published).  Part of the cache key and of
# meta.json when non-zero: a folder cached before the change is regenerated instead of being reused.
_REVISIONS = {"moving_vehicles": 2, "indoor_handheld": 1}


def revision(name: str, seed: int) -> int:
    """Content revision of ``(name, seed)``: 0 for every seed 0 and for scenarios never changed."""
    return _REVISIONS.get(name, 0) if int(seed) != 0 else 0


class UnknownScenarioError(ValueError):
    pass


def check_name(name: str) -> None:
    if name not in SCENARIOS:
        listing = "\n".join(f"  {k}: {v}" for k, v in SCENARIOS.items())
        raise UnknownScenarioError(f"unknown synthetic scenario {name!r}; available scenarios:\n{listing}")


def _builders() -> dict[str, Callable[..., Scenario]]:
    from .scenarios_city import driving_city
    from .scenarios_indoor import handheld_fast, indoor_textureless
    from .scenarios_street import busy_street, forward_low_parallax
    from .scenarios_suburb import suburban_street

    return {"driving_loop": _driving_loop, "driving_block": _driving_block, "moving_vehicles": _moving_vehicles, "indoor_handheld": _indoor_handheld,
            "handheld_fast": handheld_fast, "indoor_textureless": indoor_textureless, "busy_street": busy_street,
            "forward_low_parallax": forward_low_parallax, "driving_city": driving_city,
            "suburban_street": suburban_street}


def build(name: str, num_frames: Optional[int] = None, width: int = 320, height: int = 240, seed: int = 0,
          laps: Optional[float] = None, hfov_deg: Optional[float] = None, domain: Optional[str] = None) -> Scenario:
    """Build scenario ``name``.  ``num_frames`` None = the scenario's default length (``laps`` may set it);
    ``hfov_deg`` None = the default camera (:meth:`.render.Camera.default`).  The scene and the trajectory do not
    depend on the camera: another field of view sees the same sequence through another lens.  ``domain`` (see
    :mod:`.domain`) restyles the scene: other textures, thing sizes, light and camera; None = the plain scene."""
    check_name(name)
    if width < 16 or height < 16:
        raise ValueError(f"image size must be at least 16x16, got {width}x{height}")
    if num_frames is not None and num_frames < 1:
        raise ValueError(f"num_frames must be positive, got {num_frames}")
    sc = _builders()[name](num_frames, Camera.default(width, height, hfov_deg), seed, laps)
    sc.params = dict(scenario=name, num_frames=sc.num_frames, width=width, height=height, seed=seed, laps=laps)
    if hfov_deg is not None:
        sc.params["hfov_deg"] = float(hfov_deg)
    if revision(name, seed):
        sc.params["revision"] = revision(name, seed)
    if domain is not None:
        from .domain import randomise

        sc.scene = randomise(sc.scene, domain, name, seed)
        sc.params["domain"] = domain
    return sc


_count = count_frames


# ------------------------------------------------------------------------------------------------ driving loop
def _driving_loop(num_frames, cam, seed, laps, road: Optional[RoundedRect] = None,
                  name: str = "driving_loop") -> Scenario:
    rng = np.random.default_rng([seed, 1])
    road = road or RoundedRect(48.0, 28.0, 12.0)  # road centreline
    prof = StreetProfile()
    b = BoxBuilder()
    ids = Ids()
    a, bb, r = road.a, road.b, road.r
    # the four straights, counter-clockwise; the outward normal of each
    sides = [((-(a - r), -bb), (1.0, 0.0), (0.0, -1.0), 2 * (a - r)),
             ((a, -(bb - r)), (0.0, 1.0), (1.0, 0.0), 2 * (bb - r)),
             ((a - r, bb), (-1.0, 0.0), (0.0, 1.0), 2 * (a - r)),
             ((-a, bb - r), (0.0, -1.0), (-1.0, 0.0), 2 * (bb - r))]
    for start, e, n, length in sides:
        start, e, n = np.array(start), np.array(e), np.array(n)
        populate_side(b, rng, ids, start, e, n, length, prof)  # outer side
        inner = StreetProfile(margin=prof.margin + 4.0)
        populate_side(b, rng, ids, start, e, -n, length, inner, max_depth=11.0)  # block side
    # corners: a building behind a row of trees outside, a pole and trees inside each rounded corner
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (a - r), sy * (bb - r)
            diag = math.atan2(sy, sx)
            for ang in (0.25, 0.5, 0.75):
                phi = diag + (ang - 0.5) * 1.2
                rr = r + prof.facade + 1.0
                add_tree(b, rng, cx + rr * math.cos(phi), cy + rr * math.sin(phi))
            rr = r + prof.facade + 10.0
            add_building(b, rng, cx + rr * math.cos(diag), cy + rr * math.sin(diag), diag + math.pi / 2,
                         float(rng.uniform(14, 20)), 12.0, float(rng.uniform(8, 26)), key=int(rng.integers(1 << 30)))
            inner_r = r - prof.tree
            add_pole(b, cx + inner_r * sx * 0.7071, cy + inner_r * sy * 0.7071)
            for k in range(3):
                q = float(rng.uniform(2, 5))
                add_tree(b, rng, cx - sx * q * (k + 1) * 0.8, cy - sy * q * (3 - k) * 0.6)
    # a skyline ring of tall buildings further out: every place sees its own distant backdrop
    for start, e, n, length in sides:
        start, e, n = np.array(start), np.array(e), np.array(n)
        o = start + n * 45.0 - e * 40.0
        pos = 0.0
        while pos < length + 80.0:
            w = float(rng.uniform(12, 26))
            p = o + e * (pos + w / 2) + n * float(rng.uniform(0, 10))
            add_building(b, rng, float(p[0]), float(p[1]), math.atan2(e[1], e[0]), w, float(rng.uniform(12, 20)),
                         float(rng.uniform(15, 45)), key=int(rng.integers(1 << 30)))
            pos += w + float(rng.uniform(2, 8))
    ground = road_ground(road.signed_distance, road.along, half_width=6.0, sidewalk=3.0,
                         lane_lines=((0.0, True), (-3.9, False), (3.9, False)))
    scene = Scene(static=b.build(), ground=ground, sky=True)

    fps, speed = 12.0, 8.0
    lane = road.offset(2.0)  # right-hand traffic, counter-clockwise: outer lane
    per_lap = lane.perimeter / (speed / fps)
    n = _count(num_frames, laps, per_lap, 1.1)
    t = np.arange(n) / fps
    s = speed * t
    x, y, _ = lane.point(s)
    yaw = smooth_heading(lane.point, s, 3.0)
    pitch = np.deg2rad(-1.5) + smooth_noise(t, seed * 7 + 1, np.deg2rad(0.4), freqs=(0.3, 0.55, 0.9, 1.3))
    roll = smooth_noise(t, seed * 7 + 2, np.deg2rad(0.3), freqs=(0.25, 0.5, 0.85, 1.2))
    z = 1.5 + smooth_noise(t, seed * 7 + 3, 0.01, freqs=(0.7, 1.1, 1.7, 2.3))
    R = camera_rotation(yaw, pitch, roll)
    poses = pose_matrices(R, np.stack([x, y, z], axis=1))
    return Scenario(name, scene, poses, t, cam, depth_scale=256.0, loop_radius=3.0)


def _driving_block(num_frames, cam, seed, laps) -> Scenario:
    """The driving loop around a small block (44 x 26 m road centreline): a revisit after about 190 frames, short
    enough for end-to-end tests of loop closure."""
    return _driving_loop(num_frames, cam, seed, laps, road=RoundedRect(22.0, 13.0, 8.0), name="driving_block")


# ------------------------------------------------------------------------------------------------ moving vehicles
def _moving_vehicles(num_frames, cam, seed, laps) -> Scenario:
    rng = np.random.default_rng([seed, 2])
    fps, speed = 10.0, 8.0
    n = _count(num_frames, None, 200, 1.0)
    t = np.arange(n) / fps
    length = speed * t[-1] + 140.0
    x_start = -40.0
    # seed 0 is the published sequence; other seeds also move the cross streets and every vehicle (their own
    # stream, so the layout stream below is the same as before for every seed)
    vr = np.random.default_rng([seed, 22]) if seed != 0 else None
    crossings = (100.0, 150.0)
    if vr is not None:
        crossings = (100.0 + float(vr.uniform(-15, 10)), 150.0 + float(vr.uniform(-10, 15)))
    b = BoxBuilder()
    ids = Ids()
    ground = straight_street(b, rng, ids, x_start, length, crossings)
    t1 = (crossings[0] - 12.0) / speed  # crossing when the camera is 12 m before the intersection
    t2 = (crossings[1] - 14.0) / speed
    specs = [("car", 16.0, -1.75, 8.6, 0.0, 0.0),  # lead car, slowly pulling away
             ("car", -12.0, -5.25, 12.5, 0.0, 0.0),  # overtaking on the right
             ("car", -30.0, -5.25, 13.0, 0.0, 6.0),  # a second overtaker
             ("truck", 90.0, 1.75, -9.0, 0.0, 0.0),  # oncoming bus, close lane
             ("car", 150.0, 5.25, -10.0, 0.0, 0.0),  # oncoming car, far lane
             ("car", 230.0, 1.75, -9.0, 0.0, 0.0),
             ("car", crossings[0] + 1.75, -1.75, 0.0, -7.0, t1),
             ("truck", crossings[1] - 1.75, -1.75, 0.0, 6.0, t2)]
    parts = []  # in the published order: the layout stream draws sizes and colours as it always did
    for kind, *_ in specs:
        cat = "truck" if kind == "truck" else "car"
        pid = ids.new(cat)
        parts.append((cat, pid) + car_parts(rng, pid, dynamic=True, kind=kind))

    def place(spec) -> np.ndarray:
        _, x0, y0, vx, vy, t0 = spec
        return np.stack([x0 + vx * (t - t0), y0 + vy * (t - t0), np.full(n, math.atan2(vy, vx))], 1)

    def jitter(spec):
        kind, x0, y0, vx, vy, t0 = spec
        if vx != 0.0:  # along the street: another start and speed
            x0 += float(vr.uniform(-8.0, 8.0))
            vx *= float(vr.uniform(0.85, 1.15))
            if y0 == -1.75 and vx > 0:  # in the camera's lane: stays ahead, never driven into
                x0, vx = max(x0, 10.0), max(vx, 1.03 * speed)
        else:  # crossing: another moment and speed
            t0 += float(vr.uniform(-0.8, 0.8))
            vy *= float(vr.uniform(0.85, 1.15))
        return kind, x0, y0, vx, vy, t0

    paths = [place(s) for s in specs]
    sizes = [p[3] for p in parts]
    cam_xy = np.stack([speed * t, np.full(n, -1.75)], 1)
    for _ in range(20 if vr is not None else 0):  # jittered placements until no two vehicles overlap
        cand = [place(jitter(s)) for s in specs]
        if not vehicles_collide(cand, sizes, cam_xy):
            paths = cand
            break
    movers = [MovingObject(pid, cat, p, path, size) for (cat, pid, p, size), path in zip(parts, paths)]
    scene = Scene(static=b.build(), ground=ground, movers=movers, sky=True)
    yaw = smooth_noise(t, seed * 11 + 1, np.deg2rad(1.2), freqs=(0.05, 0.09, 0.15, 0.2))
    pitch = np.deg2rad(-1.0) + smooth_noise(t, seed * 11 + 2, np.deg2rad(0.4), freqs=(0.3, 0.55, 0.9, 1.3))
    roll = smooth_noise(t, seed * 11 + 3, np.deg2rad(0.3), freqs=(0.25, 0.5, 0.85, 1.2))
    R = camera_rotation(yaw, pitch, roll)
    pos = np.stack([speed * t, np.full(n, -1.75), np.full(n, 1.5)], axis=1)
    return Scenario("moving_vehicles", scene, pose_matrices(R, pos), t, cam, depth_scale=256.0, loop_radius=3.0)


# ------------------------------------------------------------------------------------------------ indoor
def _indoor_handheld(num_frames, cam, seed, laps) -> Scenario:
    rng = np.random.default_rng([seed, 3])
    A, B, Hh = 4.0, 3.0, 2.8  # half length, half width, height
    b = BoxBuilder()
    ids = Ids()
    wall = stuff_id("wall")
    wall_tints = [(0.86, 0.82, 0.74), (0.7, 0.78, 0.85), (0.85, 0.74, 0.7), (0.76, 0.84, 0.72)]
    wall_tex = ["plaster", "brick", "fine_noise", "wood"]
    mx = my = 1.0  # furniture layout mirrored in x / y
    if seed != 0:  # seed 0 is the published sequence; other seeds also vary the walls and the furniture layout
        vr = np.random.default_rng([seed, 33])
        wall_tex = [wall_tex[k] for k in vr.permutation(4)]
        wall_tints = [wall_tints[k] for k in vr.permutation(4)]
        mx, my = (float(v) for v in vr.choice([-1.0, 1.0], 2))
    th = 0.2
    walls = [((A + th / 2, 0.0), (th, 2 * B + 2 * th), 0), ((-A - th / 2, 0.0), (th, 2 * B + 2 * th), 1),
             ((0.0, B + th / 2), (2 * A, th), 2), ((0.0, -B - th / 2), (2 * A, th), 3)]
    for (cx, cy), (sx, sy), k in walls:
        b.add((cx, cy, Hh / 2), (sx, sy, Hh), tex=wall_tex[k],
              tint=wall_tints[k], scale=float(rng.uniform(1.5, 3.0)), pid=wall,
              off=(float(rng.uniform(0, 9)), float(rng.uniform(0, 9))))
    b.add((0.0, 0.0, Hh + 0.1), (2 * A + 0.4, 2 * B + 0.4, 0.2), tex="plaster", tint=(0.93, 0.93, 0.9), scale=3.0,
          pid=stuff_id("ceiling"))
    # posters: one picture tile each, flush on the walls
    pics = ["astronaut", "chelsea", "coffee", "rocket", "hubble_deep_field", "retina", "colorwheel", "clock",
            "coins", "camera", "immunohistochemistry", "text"]
    order = rng.permutation(len(pics))
    slots = [(A, y, 0) for y in (-1.8, 0.3, 2.0)] + [(-A, y, 0) for y in (-1.5, 1.2)] + \
            [(x, B, 1) for x in (-2.6, -0.4, 2.2)] + [(x, -B, 1) for x in (-2.2, 0.4, 2.8)]
    for (x, y, along_x), pi in zip(slots, order):
        w = float(rng.uniform(0.8, 1.4))
        h = float(rng.uniform(0.6, 1.0))
        z = float(rng.uniform(1.2, 1.8))
        depth = 0.03
        if along_x:
            cx, cy, size = x, y - np.sign(y) * depth / 2, (w, depth, h)
        else:
            cx, cy, size = x - np.sign(x) * depth / 2, y, (depth, w, h)
        b.add((cx, cy, z), size, tex=pics[pi], tint=(1.0, 1.0, 1.0), scale=w, pid=wall, off=(w / 2, h / 2))
    # furniture along the walls and a table in the middle (things)
    furn = [("table", (0.0, 0.0), (1.2, 0.8, 0.75), "wood", (0.62, 0.45, 0.3)),
            ("shelf", (A - 0.25, -0.8), (0.4, 1.6, 1.9), "text", (0.85, 0.8, 0.7)),
            ("sofa", (-A + 0.5, 0.0), (0.9, 2.0, 0.8), "fine_noise", (0.3, 0.4, 0.65)),
            ("cabinet", (1.5, B - 0.3), (1.4, 0.5, 1.1), "wood", (0.5, 0.35, 0.25)),
            ("desk", (-1.8, -B + 0.4), (1.5, 0.7, 0.76), "cell", (0.75, 0.75, 0.78)),
            ("box", (3.3, 2.3), (0.6, 0.6, 0.6), "page", (0.8, 0.7, 0.5)),
            ("plant", (-3.4, 2.4), (0.5, 0.5, 1.4), "grass", (0.35, 0.6, 0.3))]
    for name, (x, y), size, tex, tint in furn:
        jx, jy = rng.uniform(-0.1, 0.1, 2)
        b.add_on_ground(float(mx * x + (jx if name == "table" else 0)), float(my * y + jy * 0.5), size, tex=tex,
                        tint=tuple(float(c) for c in np.clip(np.array(tint) + rng.uniform(-0.05, 0.05, 3), 0, 1)),
                        scale=float(rng.uniform(0.8, 1.6)), pid=ids.new("furniture"),
                        off=(float(rng.uniform(0, 5)), float(rng.uniform(0, 5))), key=int(rng.integers(1 << 30)))
    floor_tex, rug_tex = tex_id("wood"), tex_id("immunohistochemistry")

    def ground(x, y, fp):
        rug = (np.abs(x) < 1.6) & (np.abs(y) < 1.1)
        n = len(x)
        tint = np.empty((n, 3), np.float32)
        tint[:] = (0.72, 0.56, 0.4)
        tint[rug] = (0.9, 0.85, 0.85)
        return GroundSample(pid=np.full(n, stuff_id("floor"), np.int64),
                            tex=np.where(rug, rug_tex, floor_tex).astype(np.int64), tint=tint,
                            scale=np.where(rug, 2.2, 1.6).astype(np.float32), paint=np.zeros(n, np.float32),
                            paint_rgb=np.zeros(3, np.float32))

    scene = Scene(static=b.build(), ground=ground, sky=False, light=(0.2, 0.3, 0.93), ambient=0.62)
    fps, lap_s = 15.0, 20.0
    n = _count(num_frames, laps, lap_s * fps, 1.1)
    t = np.arange(n) / fps
    th_ = 2 * math.pi * t / lap_s
    x = 2.3 * np.cos(th_) + smooth_noise(t, seed * 13 + 1, 0.08)
    y = 1.5 * np.sin(th_) + smooth_noise(t, seed * 13 + 2, 0.08)
    z = 1.45 + smooth_noise(t, seed * 13 + 3, 0.08)
    yaw = th_ + 2 * math.pi / 3 + smooth_noise(t, seed * 13 + 4, np.deg2rad(12), freqs=(0.05, 0.11, 0.19, 0.31))
    pitch = np.deg2rad(-12.0) + smooth_noise(t, seed * 13 + 5, np.deg2rad(7), freqs=(0.06, 0.13, 0.21, 0.37))
    roll = smooth_noise(t, seed * 13 + 6, np.deg2rad(4), freqs=(0.07, 0.15, 0.23, 0.33))
    R = camera_rotation(yaw, pitch, roll)
    poses = pose_matrices(R, np.stack([x, y, z], axis=1))
    return Scenario("indoor_handheld", scene, poses, t, cam, depth_scale=5000.0, loop_radius=0.75)


# ------------------------------------------------------------------------------------------------ ground truth
def revisit_pairs(poses: np.ndarray, radius: float, max_angle_deg: float = 20.0, min_gap: int = 50
                  ) -> list[tuple[int, int]]:
    """All ``(i, j)`` with ``i > j + min_gap``, camera centres within ``radius`` and optical axes within the angle."""
    c = poses[:, :3, 3]
    z = poses[:, :3, 2]
    cos_max = math.cos(math.radians(max_angle_deg))
    out: list[tuple[int, int]] = []
    n = len(poses)
    for i0 in range(0, n, 512):
        ci, zi = c[i0 : i0 + 512], z[i0 : i0 + 512]
        d = np.linalg.norm(ci[:, None] - c[None], axis=2)
        cs = zi @ z.T
        ii = np.arange(i0, i0 + len(ci))[:, None]
        jj = np.arange(n)[None]
        m = (ii > jj + min_gap) & (d <= radius) & (cs >= cos_max)
        a, bidx = np.nonzero(m)
        out.extend(zip((a + i0).tolist(), bidx.tolist()))
    return out

