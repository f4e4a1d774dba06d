"""Indoor benchmark scenarios: a handheld camera with fast turns, and a texture-poor room.

* ``handheld_fast``: a furnished room (size, wall textures, posters and furniture layout drawn from the seed); a
  person walks an ellipse at 30 Hz holding the camera, looks around with fast turns (peak yaw rates 180-300 deg/s,
  one of them near 300), and stands still for some of the turns (near-pure rotations: the camera centre moves by
  hand tremor only, a few millimetres).
* ``indoor_textureless``: large plain walls (a plaster texture stretched to 60-100 m per tile: only faint
  low-frequency shading), a plain floor and ceiling, skirting boards, a door, two or three posters and a few
  plain pieces of furniture; a slow handheld walk at 30 Hz.

Both rooms use the z-up world of :mod:`.scene` (floor at z = 0) and ``depth_scale`` 5000 (TUM).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from .layout import Ids
from .render import Camera
from .scenario_base import Scenario, count_frames, integrate, turn_profile, window
from .scene import BoxBuilder, GroundSample, Scene, camera_rotation, pose_matrices, smooth_noise, stuff_id
from .textures import tex_id

PICTURES = ("astronaut", "chelsea", "coffee", "rocket", "hubble_deep_field", "retina", "colorwheel", "clock",
            "coins", "camera", "immunohistochemistry", "text")
WALL_TEXTURES = ("plaster", "brick", "fine_noise", "wood", "cell", "page", "noise")
WALL_TINTS = ((0.86, 0.82, 0.74), (0.7, 0.78, 0.85), (0.85, 0.74, 0.7), (0.76, 0.84, 0.72), (0.9, 0.88, 0.8),
              (0.78, 0.74, 0.82))


# ------------------------------------------------------------------------------------------------ room parts
def add_room_shell(b: BoxBuilder, A: float, B: float, H: float, walls, ceiling) -> None:
    """Four walls (``walls[k] = (tex, tint, scale, off)``: +x, -x, +y, -y) around ``|x| <= A, |y| <= B`` and a
    ceiling slab ``(tex, tint, scale)`` at height ``H``."""
    th = 0.2
    boxes = [((A + th / 2, 0.0), (th, 2 * B + 2 * th)), ((-A - th / 2, 0.0), (th, 2 * B + 2 * th)),
             ((0.0, B + th / 2), (2 * A, th)), ((0.0, -B - th / 2), (2 * A, th))]
    for ((cx, cy), (sx, sy)), (tex, tint, scale, off) in zip(boxes, walls):
        b.add((cx, cy, H / 2), (sx, sy, H), tex=tex, tint=tint, scale=scale, pid=stuff_id("wall"), off=off)
    tex, tint, scale = ceiling
    b.add((0.0, 0.0, H + 0.1), (2 * A + 0.4, 2 * B + 0.4, 0.2), tex=tex, tint=tint, scale=scale,
          pid=stuff_id("ceiling"))


def add_flush(b: BoxBuilder, A: float, B: float, wall: int, u: float, z: float, w: float, h: float, *, tex: str,
              tint, scale: float, depth: float = 0.03, off=None) -> None:
    """A flat rectangle (poster, door, board) ``w x h`` centred at ``u`` along wall ``wall`` (0: +x, 1: -x, 2: +y,
    3: -y) and height ``z``, standing ``depth`` out of the wall (labelled wall: it is part of it)."""
    off = (w / 2, h / 2) if off is None else off
    if wall < 2:
        sgn = 1.0 if wall == 0 else -1.0
        b.add((sgn * (A - depth / 2), u, z), (depth, w, h), tex=tex, tint=tint, scale=scale, pid=stuff_id("wall"),
              off=off)
    else:
        sgn = 1.0 if wall == 2 else -1.0
        b.add((u, sgn * (B - depth / 2), z), (w, depth, h), tex=tex, tint=tint, scale=scale, pid=stuff_id("wall"),
              off=off)


def add_posters(b: BoxBuilder, rng: np.random.Generator, A: float, B: float, count: int) -> None:
    """``count`` posters (one picture each) at random free places on the walls."""
    slots = [(w, u) for w, half in ((0, B), (1, B), (2, A), (3, A))
             for u in np.arange(-half + 1.0, half - 0.9, 1.7)]
    pick = rng.choice(len(slots), size=min(count, len(slots)), replace=False)
    pics = rng.permutation(len(PICTURES))
    for k, si in enumerate(pick):
        wall, u = slots[int(si)]
        w, h = float(rng.uniform(0.8, 1.3)), float(rng.uniform(0.6, 1.0))  # slots 1.7 m apart: never overlap
        add_flush(b, A, B, wall, float(u) + float(rng.uniform(-0.1, 0.1)), float(rng.uniform(1.2, 1.8)), w, h,
                  tex=PICTURES[int(pics[k % len(pics)])], tint=(1.0, 1.0, 1.0), scale=w)


def add_furniture(b: BoxBuilder, rng: np.random.Generator, ids: Ids, A: float, B: float, items, plain: bool) -> None:
    """Furniture ``(name, (x, y) as fractions of the half sizes, size, tex, tint)``, mirrored by the seed; ``plain``
    stretches the textures (texture-poor rooms)."""
    mx, my = (float(v) for v in rng.choice([-1.0, 1.0], 2))
    for name, (fx, fy), size, tex, tint in items:
        x = mx * fx * A + (size[0] / 2 + 0.05 if abs(fx) == 1 else 0.0) * -np.sign(mx * fx)
        y = my * fy * B + (size[1] / 2 + 0.05 if abs(fy) == 1 else 0.0) * -np.sign(my * fy)
        scale = float(rng.uniform(15.0, 25.0)) if plain else float(rng.uniform(0.8, 1.6))
        tint = tuple(float(c) for c in np.clip(np.array(tint) + rng.uniform(-0.05, 0.05, 3), 0, 1))
        b.add_on_ground(float(x), float(y), size, tex=tex, tint=tint, scale=scale, pid=ids.new("furniture"),
                        off=(float(rng.uniform(0, 5)), float(rng.uniform(0, 5))), key=int(rng.integers(1 << 30)))


def floor_shader(tex: str, tint, scale: float, rug: Optional[tuple] = None):
    """The floor (stuff ``floor``): one texture, optionally a rug ``(half x, half y, tex, tint, scale)``."""
    t_floor = tex_id(tex)

    def ground(x, y, fp):
        n = len(x)
        tints = np.empty((n, 3), np.float32)
        tints[:] = tint
        texs = np.full(n, t_floor, np.int64)
        scales = np.full(n, scale, np.float32)
        if rug is not None:
            hx, hy, rtex, rtint, rscale = rug
            m = (np.abs(x) < hx) & (np.abs(y) < hy)
            tints[m] = rtint
            texs[m] = tex_id(rtex)
            scales[m] = rscale
        return GroundSample(pid=np.full(n, stuff_id("floor"), np.int64), tex=texs, tint=tints, scale=scales,
                            paint=np.zeros(n, np.float32), paint_rgb=np.zeros(3, np.float32))

    return ground


FURNITURE = [("table", (0.0, 0.0), (1.2, 0.8, 0.75), "wood", (0.62, 0.45, 0.3)),
             ("shelf", (1.0, -0.27), (0.4, 1.6, 1.9), "text", (0.85, 0.8, 0.7)),
             ("sofa", (-1.0, 0.0), (0.9, 2.0, 0.8), "fine_noise", (0.3, 0.4, 0.65)),
             ("cabinet", (0.38, 1.0), (1.4, 0.5, 1.1), "wood", (0.5, 0.35, 0.25)),
             ("desk", (-0.45, -1.0), (1.5, 0.7, 0.76), "cell", (0.75, 0.75, 0.78)),
             ("box", (0.82, 0.77), (0.6, 0.6, 0.6), "page", (0.8, 0.7, 0.5)),
             ("plant", (-0.85, 0.8), (0.5, 0.5, 1.4), "grass", (0.35, 0.6, 0.3))]


def _handheld_poses(x, y, z, yaw, pitch, roll) -> np.ndarray:
    return pose_matrices(camera_rotation(yaw, pitch, roll), np.stack([x, y, z], axis=1))


# ------------------------------------------------------------------------------------------------ handheld_fast
def handheld_fast(num_frames, cam: Camera, seed: int, laps) -> Scenario:
    rng = np.random.default_rng([seed, 4])
    A, B, H = float(rng.uniform(3.6, 4.4)), float(rng.uniform(2.7, 3.3)), 2.8
    b = BoxBuilder()
    ids = Ids()
    tex = rng.choice(len(WALL_TEXTURES), 4, replace=False)
    tints = rng.permutation(len(WALL_TINTS))
    walls = [(WALL_TEXTURES[int(tex[k])], WALL_TINTS[int(tints[k])], float(rng.uniform(1.5, 3.0)),
              (float(rng.uniform(0, 9)), float(rng.uniform(0, 9)))) for k in range(4)]
    add_room_shell(b, A, B, H, walls, ("plaster", (0.93, 0.93, 0.9), 3.0))
    add_posters(b, rng, A, B, int(rng.integers(7, 11)))
    add_furniture(b, rng, ids, A, B, FURNITURE, plain=False)
    rug = (float(rng.uniform(1.2, 1.8)), float(rng.uniform(0.9, 1.3)), "immunohistochemistry", (0.9, 0.85, 0.85), 2.2)
    scene = Scene(static=b.build(), ground=floor_shader("wood", (0.72, 0.56, 0.4), 1.6, rug), sky=False,
                  light=(0.2, 0.3, 0.93), ambient=0.62)

    fps = 30.0
    n = count_frames(num_frames, None, 360, 1.0)
    t = np.arange(n) / fps
    T = max(float(t[-1]), 12.0)
    # drawn before the turns, whose number depends on the length: a shorter sequence is a prefix of a longer one
    walk_speed = float(rng.uniform(0.55, 0.75))
    direction = float(rng.choice([-1.0, 1.0]))
    th0 = float(rng.uniform(0, 2 * math.pi))
    # turns: the first after 2.5 s (time to initialise), then every 1.6-2.4 s, alternating sides; every other one
    # while standing still (a near-pure rotation)
    starts, amps, durs = [], [], []
    t0, sign = 2.5 + float(rng.uniform(0, 0.5)), float(rng.choice([-1.0, 1.0]))
    while t0 < T:
        amp = math.radians(float(rng.uniform(60, 140)))
        rate = math.radians(295.0 if not starts else float(rng.uniform(180, 300)))  # the first reaches ~300 deg/s
        starts.append(t0)
        amps.append(sign * amp)
        durs.append(1.875 * amp / rate)
        t0 += durs[-1] + float(rng.uniform(1.3, 2.1))
        sign = -sign
    stand = np.zeros(n)
    for k in range(1, len(starts), 2):
        stand = np.maximum(stand, window(t, starts[k] + durs[k] / 2, durs[k] / 2 + 0.3, 0.4))
    tau = integrate(t, 1.0 - stand)  # walking time: stands still while standing
    a_, b_ = 0.55 * A, 0.5 * B
    th = th0 + direction * walk_speed * tau / math.sqrt((a_ ** 2 + b_ ** 2) / 2)
    s = seed * 17
    # sway follows the walk (frozen while standing); hand tremor (1-2 mm) does not
    tremor = lambda k, amp: smooth_noise(t, s + k, amp, freqs=(0.9, 1.7, 2.9, 4.1))  # noqa: E731
    x = a_ * np.cos(th) + smooth_noise(tau, s + 1, 0.05) + tremor(2, 0.0015)
    y = b_ * np.sin(th) + smooth_noise(tau, s + 3, 0.05) + tremor(4, 0.0015)
    z = 1.5 + smooth_noise(tau, s + 5, 0.06) + tremor(6, 0.001)
    yaw = th + direction * (math.pi / 2 + 0.35) + turn_profile(t, starts, amps, durs) \
        + smooth_noise(t, s + 7, np.deg2rad(8), freqs=(0.07, 0.13, 0.23, 0.41))
    pitch = np.deg2rad(-8.0) + smooth_noise(t, s + 8, np.deg2rad(6), freqs=(0.1, 0.23, 0.37, 0.6))
    roll = smooth_noise(t, s + 9, np.deg2rad(4), freqs=(0.08, 0.19, 0.31, 0.5))
    poses = _handheld_poses(x, y, z, yaw, pitch, roll)
    return Scenario("handheld_fast", scene, poses, t, cam, depth_scale=5000.0, loop_radius=0.75)


# ------------------------------------------------------------------------------------------------ textureless
def indoor_textureless(num_frames, cam: Camera, seed: int, laps) -> Scenario:
    rng = np.random.default_rng([seed, 5])
    A, B, H = float(rng.uniform(3.5, 4.5)), float(rng.uniform(2.6, 3.2)), 2.7
    b = BoxBuilder()
    ids = Ids()
    # plain walls: plaster stretched to 60-100 m per tile leaves only faint, low-frequency shading
    base = np.array(WALL_TINTS[int(rng.integers(len(WALL_TINTS)))])
    walls = [("plaster", tuple(float(c) for c in np.clip(base + rng.uniform(-0.03, 0.03, 3), 0, 1)),
              float(rng.uniform(60, 100)), (float(rng.uniform(0, 50)), float(rng.uniform(0, 50)))) for _ in range(4)]
    add_room_shell(b, A, B, H, walls, ("plaster", (0.95, 0.95, 0.93), 80.0))
    for wall in range(4):  # skirting boards: edges, but only along one direction
        half = B if wall < 2 else A
        add_flush(b, A, B, wall, 0.0, 0.05, 2 * half, 0.1, tex="plaster", tint=(0.55, 0.52, 0.48), scale=30.0,
                  depth=0.02)
    door_wall = int(rng.integers(4))
    half = B if door_wall < 2 else A
    add_flush(b, A, B, door_wall, float(rng.uniform(-half + 0.8, half - 0.8)), 1.03, 0.9, 2.05, tex="wood",
              tint=(0.55, 0.42, 0.3), scale=12.0, depth=0.04)
    # a window (a bright pane in a dark frame) on another wall: strong edges, no texture
    win_wall = int((door_wall + rng.integers(1, 4)) % 4)
    half = B if win_wall < 2 else A
    u, w = float(rng.uniform(-half + 1.2, half - 1.2)), float(rng.uniform(1.0, 1.6))
    add_flush(b, A, B, win_wall, u, 1.5, w + 0.16, 1.36, tex="plaster", tint=(0.3, 0.3, 0.32), scale=30.0, depth=0.035)
    add_flush(b, A, B, win_wall, u, 1.5, w, 1.2, tex="plaster", tint=(0.82, 0.9, 1.0), scale=30.0, depth=0.045)
    add_posters(b, rng, A, B, int(rng.integers(2, 5)))
    items = [("table", (0.0, 0.0), (1.2, 0.8, 0.75), "wood", (0.62, 0.5, 0.38)),
             ("sofa", (-1.0, 0.0), (0.9, 2.0, 0.8), "plaster", (0.45, 0.5, 0.6)),
             ("cabinet", (0.4, 1.0), (1.4, 0.5, 1.1), "plaster", (0.85, 0.85, 0.82))]
    add_furniture(b, rng, ids, A, B, items, plain=True)
    floor_tint = tuple(float(c) for c in rng.uniform(0.6, 0.75, 3))
    scene = Scene(static=b.build(), ground=floor_shader("plaster", floor_tint, 60.0), sky=False,
                  light=(0.2, 0.3, 0.93), ambient=0.62)

    fps, lap_s = 30.0, 24.0
    n = count_frames(num_frames, laps, lap_s * fps, 300 / (lap_s * fps))
    t = np.arange(n) / fps
    direction = float(rng.choice([-1.0, 1.0]))
    th = float(rng.uniform(0, 2 * math.pi)) + direction * 2 * math.pi * t / lap_s
    s = seed * 19
    x = 0.5 * A * np.cos(th) + smooth_noise(t, s + 1, 0.08)
    y = 0.45 * B * np.sin(th) + smooth_noise(t, s + 2, 0.08)
    z = 1.45 + smooth_noise(t, s + 3, 0.08)
    yaw = th + direction * (math.pi / 2 + 0.5) + smooth_noise(t, s + 4, np.deg2rad(12),
                                                              freqs=(0.05, 0.11, 0.19, 0.31))
    pitch = np.deg2rad(-10.0) + smooth_noise(t, s + 5, np.deg2rad(6), freqs=(0.06, 0.13, 0.21, 0.37))
    roll = smooth_noise(t, s + 6, np.deg2rad(3), freqs=(0.07, 0.15, 0.23, 0.33))
    poses = _handheld_poses(x, y, z, yaw, pitch, roll)
    return Scenario("indoor_textureless", scene, poses, t, cam, depth_scale=5000.0, loop_radius=0.75)
