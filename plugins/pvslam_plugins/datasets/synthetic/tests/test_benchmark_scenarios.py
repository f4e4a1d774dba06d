"""The benchmark scenarios do what their names promise (fast turns and near-pure rotations, little texture, large
moving vehicles that collide with nothing, little parallax in the image centre, a city route that revisits), every
scenario changes with its seed, a shorter sequence is a prefix of the default one, and seed 0 of the published
scenarios is unchanged (golden values)."""
from __future__ import annotations

import hashlib
import json
import math

import cv2
import numpy as np
import pytest

from pvslam_plugins.datasets.synthetic import generator, scenarios
from pvslam_plugins.datasets.synthetic.render import render
from pvslam_plugins.datasets.synthetic.scene import stuff_id

NEW = ("handheld_fast", "indoor_textureless", "busy_street", "forward_low_parallax", "driving_city")


def _rates(sc):
    """Rotation rate (deg/s) and speed (m/s) between consecutive frames."""
    dt = np.diff(sc.timestamps)
    R = sc.poses[:, :3, :3]
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    v = np.linalg.norm(np.diff(sc.poses[:, :3, 3], axis=0), axis=1)
    return ang / dt, v / dt


# -------------------------------------------------------------------------------------------- seed 0 is frozen
# Computed at 96x72 before the benchmark scenarios were added: (frames, poses digest, [(frame, panoptic digest,
# mean rgb, depth sum)]).  Integer labels must match exactly; colour and depth within float round-off.
GOLDEN = {
    "driving_loop": (488, "1d7fe722582dbad8", [(0, "1ebc20df581241f2", 61.6719, 190877.047),
                                               (244, "ee6f7acdbd5c0445", 59.7801, 186450.105),
                                               (487, "5401e3aadde1fe31", 63.2694, 152704.684)]),
    "moving_vehicles": (200, "458f4e9e49ff254e", [(0, "87a25daf6e7fdef5", 85.2947, 109090.492),
                                                  (100, "b07253dd0dafff3b", 75.7781, 121789.79),
                                                  (199, "6722982a0b3f3a66", 87.8464, 90209.65)]),
    "indoor_handheld": (330, "8fd286612cff6d2e", [(0, "32b12d7a7628e56e", 61.3375, 21532.532),
                                                  (165, "a452ad8ed52eca19", 69.0434, 24312.603),
                                                  (329, "34e9a9cd355149d0", 68.0352, 26800.529)]),
}


@pytest.mark.parametrize("name", list(GOLDEN))
def test_seed_zero_of_the_published_scenarios_is_unchanged(name):
    n, pose_digest, frames = GOLDEN[name]
    sc = scenarios.build(name, width=96, height=72, seed=0)
    assert sc.num_frames == n
    assert hashlib.sha1(np.round(sc.poses, 9).tobytes()).hexdigest()[:16] == pose_digest
    for i, pan, rgb, depth in frames:
        out = render(sc.scene, i, sc.poses[i], sc.camera)
        assert hashlib.sha1(out.panoptic.astype(np.int64).tobytes()).hexdigest()[:16] == pan, (name, i)
        assert float(out.rgb.mean()) == pytest.approx(rgb, abs=2e-3)
        assert float(out.depth.astype(np.float64).sum()) == pytest.approx(depth, rel=1e-6)
    assert "revision" not in sc.params and scenarios.revision(name, 0) == 0


# -------------------------------------------------------------------------------------------- seeds
@pytest.mark.parametrize("name", list(scenarios.SCENARIOS))
def test_every_scenario_changes_with_its_seed(name):
    a, b = (scenarios.build(name, num_frames=30, width=64, height=48, seed=s) for s in (1, 2))
    assert np.abs(a.poses - b.poses).max() > 0.005  # trajectory (moving_vehicles: only its rotation jitters)
    sa, sb = a.scene.static, b.scene.static
    assert len(sa) != len(sb) or not np.allclose(sa.center, sb.center) or not np.array_equal(sa.tex, sb.tex)
    ra, rb = (render(s.scene, 0, s.poses[0], s.camera).rgb.astype(float) for s in (a, b))
    assert np.abs(ra - rb).mean() > 3.0  # the first image looks different
    if a.scene.movers:  # vehicle placement
        pa = np.concatenate([m.poses[0] for m in a.scene.movers])
        pb = np.concatenate([m.poses[0] for m in b.scene.movers])
        assert len(pa) != len(pb) or np.abs(pa - pb).max() > 1.0


@pytest.mark.parametrize("name", ["handheld_fast", "busy_street", "forward_low_parallax", "suburban_street"])
def test_a_shorter_sequence_is_a_prefix_of_the_default_one(name):
    full = scenarios.build(name, width=64, height=48, seed=4)
    short = scenarios.build(name, num_frames=20, width=64, height=48, seed=4)
    np.testing.assert_array_equal(short.poses, full.poses[:20])
    a, b = (render(s.scene, 15, s.poses[15], s.camera) for s in (short, full))
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.panoptic, b.panoptic)


def test_revised_seeds_get_their_own_cache_key(tmp_path):
    assert scenarios.revision("moving_vehicles", 3) == 2 and scenarios.revision("driving_loop", 3) == 0
    assert "revision" not in generator._params("moving_vehicles", None, 320, 240, 0, None)
    assert generator._params("indoor_handheld", None, 320, 240, 2, None)["revision"] == 1
    root = generator.generate("moving_vehicles", tmp_path / "mv", num_frames=2, width=32, height=24, seed=3,
                              progress=False)
    assert json.loads((root / "meta.json").read_text())["revision"] == 2
    assert generator.generate("moving_vehicles", root, num_frames=2, width=32, height=24, seed=3) == root


# -------------------------------------------------------------------------------------------- handheld_fast
def test_handheld_fast_turns_fast_and_sometimes_only_rotates():
    sc = scenarios.build("handheld_fast", width=80, height=60, seed=3)
    assert sc.num_frames == 360 and 1.0 / np.diff(sc.timestamps)[0] == pytest.approx(30.0)
    rate, speed = _rates(sc)
    assert 250.0 < rate.max() < 340.0
    fast = rate > 150.0
    turns = int(np.sum(fast[1:] & ~fast[:-1]) + fast[0])
    assert turns >= 3
    pure = (rate > 100.0) & (speed < 0.05)  # near-pure rotations: > 100 deg/s, < 5 cm/s (< 1.7 mm a frame)
    assert pure.sum() >= 5
    assert speed.max() > 0.5  # it also walks
    for i in range(0, sc.num_frames, 40):  # never inside the furniture or a wall
        d = render(sc.scene, i, sc.poses[i], sc.camera).depth
        assert (d > 0).all() and d.min() > 0.4


# -------------------------------------------------------------------------------------------- textureless
def _gradient(name, seed):
    sc = scenarios.build(name, width=160, height=120, seed=seed)
    g = []
    for i in np.linspace(0, sc.num_frames - 1, 6).round().astype(int):
        img = cv2.cvtColor(render(sc.scene, int(i), sc.poses[i], sc.camera).rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        mag = np.hypot(cv2.Sobel(img, cv2.CV_32F, 1, 0), cv2.Sobel(img, cv2.CV_32F, 0, 1))
        g.append((np.median(mag), mag.mean()))
    return np.array(g)  # [frames, (median, mean)] Sobel magnitude


def test_indoor_textureless_has_little_texture_but_some_structure():
    plain, textured = _gradient("indoor_textureless", 3), _gradient("indoor_handheld", 3)
    # the typical pixel: about one 8-bit level per pixel (quantised shading) against strong texture
    assert np.median(plain[:, 0]) < 0.35 * np.median(textured[:, 0])
    assert plain[:, 1].min() > 10.0  # edges, posters, furniture, a door: never a blank screen


# -------------------------------------------------------------------------------------------- busy street
def _footprints(sc, i):
    """Axis-aligned footprints [x0, x1, y0, y1] of the moving vehicles at frame i (they drive along the axes)."""
    out = []
    for m in sc.scene.movers:
        x, y, yaw = m.poses[i]
        L, Wd, _ = m.size
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        assert min(c, s) < 1e-9  # axis-aligned
        hx, hy = (L / 2, Wd / 2) if c > s else (Wd / 2, L / 2)
        out.append((x - hx, x + hx, y - hy, y + hy))
    return np.array(out)


def _collisions(sc, step=1):
    """Frames where two vehicles, or a vehicle and the camera car (5 x 2 m), overlap."""
    bad = []
    for i in range(0, sc.num_frames, step):
        f = _footprints(sc, i)
        cx, cy = sc.poses[i, 0, 3], sc.poses[i, 1, 3]
        hit_cam = (f[:, 0] < cx + 2.5) & (f[:, 1] > cx - 2.5) & (f[:, 2] < cy + 1.0) & (f[:, 3] > cy - 1.0)
        ov = ((f[:, None, 0] < f[None, :, 1]) & (f[None, :, 0] < f[:, None, 1]) & (f[:, None, 2] < f[None, :, 3])
              & (f[None, :, 2] < f[:, None, 3]))
        np.fill_diagonal(ov, False)
        if hit_cam.any() or ov.any():
            bad.append(i)
    return bad


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_moving_vehicles_with_other_seeds_collide_with_nothing(seed):
    sc = scenarios.build("moving_vehicles", width=32, height=24, seed=seed)
    assert _collisions(sc) == []


def test_busy_street_has_large_moving_vehicles_that_hit_nothing():
    sc = scenarios.build("busy_street", width=80, height=60, seed=0)
    heading = np.array([m.poses[0, 2] for m in sc.scene.movers])
    assert np.sum(np.abs(np.abs(heading) - math.pi / 2) < 1e-6) >= 2  # crossing
    assert np.sum(np.abs(np.abs(heading) - math.pi) < 1e-6) >= 3  # oncoming
    assert sum(m.name == "truck" for m in sc.scene.movers) >= 4  # buses and trucks
    assert _collisions(sc) == []
    cover = np.array([render(sc.scene, i, sc.poses[i], sc.camera).dynamic.mean() for i in range(0, sc.num_frames, 3)])
    assert 0.25 < cover.max() < 0.5
    assert np.mean(cover > 0.1) > 0.2


# -------------------------------------------------------------------------------------------- low parallax
def test_forward_low_parallax_moves_little_in_the_image_centre():
    sc = scenarios.build("forward_low_parallax", num_frames=2, width=160, height=120, seed=3)
    cam = sc.camera
    step = np.linalg.norm(sc.poses[1, :3, 3] - sc.poses[0, :3, 3])
    assert 1.8 <= step <= 2.4  # 18-24 m/s at 10 fps
    d = render(sc.scene, 0, sc.poses[0], cam).depth.astype(np.float64)
    v, u = np.nonzero(d > 0)
    z = d[v, u]
    Xc0 = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    X = Xc0 @ sc.poses[0, :3, :3].T + sc.poses[0, :3, 3]
    Xc = (X - sc.poses[1, :3, 3]) @ sc.poses[1, :3, :3]
    flow = np.hypot(cam.fx * Xc[:, 0] / Xc[:, 2] + cam.cx - u, cam.fy * Xc[:, 1] / Xc[:, 2] + cam.cy - v)
    centre = (np.abs(u - cam.cx) < cam.width / 6) & (np.abs(v - cam.cy) < cam.height / 10)
    bottom = v > 0.8 * cam.height
    assert np.median(z[centre]) > 40.0
    assert np.median(flow[centre]) < 0.1 * np.median(flow[bottom])
    assert np.median(flow[centre]) < 1.0  # px at 160x120


# -------------------------------------------------------------------------------------------- city
def test_driving_city_turns_both_ways_stays_on_the_road_and_revisits():
    sc = scenarios.build("driving_city", width=64, height=48, seed=3)
    lap = sc.num_frames / 1.05
    yaw = np.unwrap(np.arctan2(sc.poses[:, 1, 2], sc.poses[:, 0, 2]))
    yaw_rate = np.degrees(np.diff(yaw)) / np.diff(sc.timestamps)
    assert yaw_rate.max() > 20 and yaw_rate.min() < -20  # left and right turns
    assert abs(np.degrees(yaw[int(round(lap))] - yaw[0])) < 5  # a figure-eight: no net turn over one lap
    g = sc.scene.ground(sc.poses[:, 0, 3], sc.poses[:, 1, 3], np.full(sc.num_frames, 0.01))
    assert (g.pid == stuff_id("road")).all()
    pairs = np.array(scenarios.revisit_pairs(sc.poses, sc.loop_radius, sc.loop_angle_deg, sc.loop_min_gap))
    gap = pairs[:, 0] - pairs[:, 1]
    assert ((gap > 0.3 * lap) & (gap < 0.7 * lap)).any()  # the middle street, driven twice
    assert ((pairs[:, 1] < 20) & (pairs[:, 0] > lap - 5)).any()  # the end revisits the start


def test_driving_block_revisits_within_a_short_sequence():
    """The small block: the start is revisited after about 190 frames (end-to-end loop-closure tests use it)."""
    sc = scenarios.build("driving_block", width=64, height=48, seed=0)
    assert 200 <= sc.num_frames <= 260
    pairs = np.array(scenarios.revisit_pairs(sc.poses, sc.loop_radius, sc.loop_angle_deg, sc.loop_min_gap))
    assert ((pairs[:, 1] < 10) & (pairs[:, 0] > 180)).any()
    assert pairs[:, 0].min() > 150  # nothing is a revisit before the lap is done
    g = sc.scene.ground(sc.poses[:, 0, 3], sc.poses[:, 1, 3], np.full(sc.num_frames, 0.01))
    assert (g.pid == stuff_id("road")).all()
