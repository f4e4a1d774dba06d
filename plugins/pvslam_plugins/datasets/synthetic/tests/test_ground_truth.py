"""The ground truth of the synthetic scenarios is exact: depth reprojected with the GT poses lands on the same
surface (same depth, same colour, same panoptic id) in the next frame; moving objects follow their recorded poses;
the dynamic mask is exactly the moving instances; the driving loop revisits its start."""
from __future__ import annotations

import numpy as np
import pytest

from pvslam_plugins.datasets.synthetic import scenarios
from pvslam_plugins.datasets.synthetic.render import render, render_points
from pvslam_plugins.datasets.synthetic.scene import CAT_BY_ID

W, H = 160, 120


def _unproject(depth, cam, T):
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    Xc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
    return u, v, Xc @ T[:3, :3].T + T[:3, 3]


def _project(Xw, cam, T):
    Xc = (Xw - T[:3, 3]) @ T[:3, :3]
    z = Xc[:, 2]
    return cam.fx * Xc[:, 0] / z + cam.cx, cam.fy * Xc[:, 1] / z + cam.cy, z


def _reproject_check(sc, i, j, min_consistent=0.7, min_inside=0.3):
    cam = sc.camera
    a = render(sc.scene, i, sc.poses[i], cam)
    static = (a.depth > 0) & ~a.dynamic
    u, v, Xw = _unproject(np.where(static, a.depth, 0), cam, sc.poses[i])
    pu, pv, z = _project(Xw, cam, sc.poses[j])
    inside = (z > 0.1) & (pu >= 0) & (pu <= cam.width - 1) & (pv >= 0) & (pv <= cam.height - 1)
    assert inside.sum() > min_inside * len(u)
    u, v, pu, pv, z = u[inside], v[inside], pu[inside], pv[inside], z[inside]
    col, depth, pid, dyn = render_points(sc.scene, j, sc.poses[j], cam, pu, pv)
    rel = np.abs(depth - z) / z
    same = rel < 1e-4  # the others are occluded in frame j (or the surface left the view)
    assert same.mean() > min_consistent, f"only {same.mean():.2%} of the reprojected points are consistent"
    assert np.median(rel) < 1e-5
    # same surface point: same panoptic id, (nearly) the same colour
    assert np.array_equal(pid[same], a.panoptic[v[same], u[same]])
    dc = np.abs(col[same] - a.color[v[same], u[same]]).mean(axis=1)
    assert np.median(dc) < 0.02 and np.mean(dc < 0.08) > 0.9
    # against the rendered image of frame j (nearest pixel): depths agree on most points
    b = render(sc.scene, j, sc.poses[j], cam)
    ni, nj = np.round(pv[same]).astype(int), np.round(pu[same]).astype(int)
    agree = np.abs(b.depth[ni, nj] - z[same]) < 0.05 * z[same] + 0.02
    assert agree.mean() > 0.85
    return same.mean()


@pytest.mark.parametrize("name", list(scenarios.SCENARIOS))
def test_reprojection_with_gt_poses_is_exact(name):
    sc = scenarios.build(name, num_frames=12, width=W, height=H, seed=3)
    # at highway speed (2 m a frame) most of the near road leaves the view in one frame
    min_inside = 0.15 if name == "forward_low_parallax" else 0.3
    for i, j in ((0, 1), (5, 6), (4, 10)):
        _reproject_check(sc, i, j, min_consistent=0.6 if j - i > 1 else 0.75, min_inside=min_inside)


@pytest.mark.parametrize("name", ["moving_vehicles", "busy_street"])
def test_moving_objects_follow_their_recorded_poses(name):
    sc = scenarios.build(name, num_frames=80, width=W, height=H, seed=0)
    cam = sc.camera
    movers = {m.pid: m for m in sc.scene.movers}
    checked = 0
    for i in (20, 45, 70):
        a = render(sc.scene, i, sc.poses[i], cam)
        if a.dynamic.sum() < 50:
            continue
        u, v, Xw = _unproject(np.where(a.dynamic, a.depth, 0), cam, sc.poses[i])
        ids = a.panoptic[v, u]
        Xn = np.empty_like(Xw)
        for pid in np.unique(ids):
            m = movers[int(pid)]
            sel = ids == pid
            (x0, y0, w0), (x1, y1, w1) = m.poses[i], m.poses[i + 1]
            dxy = Xw[sel, :2] - [x0, y0]
            ang = w1 - w0
            rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
            Xn[sel, :2] = dxy @ rot.T + [x1, y1]
            Xn[sel, 2] = Xw[sel, 2]
        pu, pv, z = _project(Xn, cam, sc.poses[i + 1])
        ok = (z > 0.1) & (pu >= 0) & (pu <= cam.width - 1) & (pv >= 0) & (pv <= cam.height - 1)
        col, depth, pid, dyn = render_points(sc.scene, i + 1, sc.poses[i + 1], cam, pu[ok], pv[ok])
        same = np.abs(depth - z[ok]) / z[ok] < 1e-4
        assert same.mean() > 0.7
        assert np.array_equal(pid[same], ids[ok][same]) and dyn[same].all()
        checked += 1
    assert checked >= 2


@pytest.mark.parametrize("name", ["moving_vehicles", "busy_street"])
def test_dynamic_mask_is_exactly_the_moving_instances(name):
    sc = scenarios.build(name, num_frames=120, width=W, height=H, seed=1)
    moving = sc.scene.moving_ids()
    assert len(moving) >= 5
    seen = 0
    for i in (0, 30, 60, 90, 119):
        out = render(sc.scene, i, sc.poses[i], sc.camera)
        np.testing.assert_array_equal(out.dynamic, np.isin(out.panoptic, moving))
        seen += int(out.dynamic.any())
        # parked cars are things too, but static
        things = out.panoptic // 1000 == 11
        assert (things & ~out.dynamic).any() or i > 100
    assert seen >= 3


def test_moving_vehicles_cover_large_parts_of_the_image_at_times():
    sc = scenarios.build("moving_vehicles", width=80, height=60)
    cover = [render(sc.scene, i, sc.poses[i], sc.camera).dynamic.mean() for i in range(0, sc.num_frames, 4)]
    assert max(cover) > 0.15


def test_instance_ids_are_stable_over_frames():
    sc = scenarios.build("driving_loop", num_frames=30, width=W, height=H, seed=0)
    ids = [set(np.unique(render(sc.scene, i, sc.poses[i], sc.camera).panoptic).tolist()) for i in (0, 3, 6)]
    cars = [{x for x in s if x // 1000 == 11} for s in ids]
    assert cars[0] and cars[0] & cars[1]  # the same parked car keeps its id
    for s in ids:
        for x in s:
            cat = x // 1000
            assert cat in CAT_BY_ID
            if not CAT_BY_ID[cat].isthing:
                assert x % 1000 == 0


def test_driving_loop_revisits_its_start():
    sc = scenarios.build("driving_loop")  # default length: 1.1 laps
    n = sc.num_frames
    assert 420 <= n <= 560
    pairs = scenarios.revisit_pairs(sc.poses, sc.loop_radius, sc.loop_angle_deg, sc.loop_min_gap)
    assert len(pairs) > 50
    assert all(i > j + 50 for i, j in pairs)
    assert any(j == 0 for _, j in pairs)  # the first frame is revisited
    assert max(i for i, _ in pairs) == n - 1  # ... and the last frame revisits an early one
    assert min(j for i, j in pairs if i == n - 1) < 60
    # a closed loop: after exactly one lap the camera is back at the start
    c = sc.poses[:, :3, 3]
    d = np.linalg.norm(c[400:] - c[0], axis=1)
    assert d.min() < 0.5
    # smooth yaw: no jumps between frames
    f = sc.poses[:, :3, 2]
    ang = np.degrees(np.arccos(np.clip(np.sum(f[1:] * f[:-1], axis=1), -1, 1)))
    assert ang.max() < 4.0


def test_laps_sets_the_length():
    one = scenarios.build("driving_loop", laps=1.0).num_frames
    assert scenarios.build("driving_loop", laps=6.8).num_frames == pytest.approx(6.8 * one, abs=2)


def test_indoor_revisits_and_moves_in_6dof():
    sc = scenarios.build("indoor_handheld")
    pairs = scenarios.revisit_pairs(sc.poses, sc.loop_radius, sc.loop_angle_deg, sc.loop_min_gap)
    assert any(j < 10 for _, j in pairs)
    c = sc.poses[:, :3, 3]
    assert np.ptp(c[:, 2]) > 0.05  # height changes
    assert np.all(np.abs(c[:, 0]) < 3.2) and np.all(np.abs(c[:, 1]) < 2.2)  # stays inside the free space
