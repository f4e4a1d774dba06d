"""The suburban street's ground is not one plane: kerbs raise the lawns and pavements, a crest raises the road, the
car drives over it; and the renderer finds a ray's first hit on such a relief."""
from __future__ import annotations

import numpy as np

from pvslam_plugins.datasets.synthetic import scenarios
from pvslam_plugins.datasets.synthetic.render import _ground_hits, render
from pvslam_plugins.datasets.synthetic.scene import Relief, stuff_id

W, H = 160, 120


def _world_points(sc, i):
    cam, T = sc.camera, sc.poses[i]
    out = render(sc.scene, i, T, cam)
    v, u = np.nonzero(out.depth > 0)
    z = out.depth[v, u].astype(np.float64)
    Xc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    return Xc @ T[:3, :3].T + T[:3, 3], out.panoptic[v, u]


def test_a_ray_meets_the_relief_first_and_the_plane_beyond_it():
    relief = Relief(height=0.5, centre=30.0, half_length=20.0)
    c = np.array([0.0, 0.0, 1.65])
    # rays straight ahead, from steeply down to slightly up (the rising road ahead meets some of those too)
    pitch = np.deg2rad(np.linspace(-30.0, 1.0, 200))
    dw = np.stack([np.cos(pitch), np.zeros_like(pitch), np.sin(pitch)], 1).astype(np.float32)[None]
    t = _ground_hits(c, dw, relief)[0].astype(np.float64)
    # brute force: the first sample of a fine march whose height is at or below the ground
    ts = np.linspace(0.0, 400.0, 400001)
    for k in range(0, 200, 7):
        d = dw[0, k].astype(np.float64)
        h = c[2] + ts * d[2] - relief.z(c[0] + ts * d[0])
        first = np.nonzero(h <= 0)[0]
        if len(first) == 0:
            assert not np.isfinite(t[k])
            continue
        assert abs(t[k] - ts[first[0]]) < 2e-3 * max(1.0, ts[first[0]])
        x = c[0] + t[k] * d[0]
        assert abs(c[2] + t[k] * d[2] - relief.z(x)) < 1e-3  # on the ground: the relief's or the plane's
    hit = np.isfinite(t)
    x = c[0] + t[hit] * dw[0, hit, 0]
    assert (np.abs(x - 30.0) < 20.0).any() and (x > 50.0).any()  # some on the crest, some beyond it
    assert not np.isfinite(t[-1])  # 1 deg up clears a 0.5 m crest from 1.65 m


def test_kerbs_and_a_crest_lift_the_ground_off_one_plane():
    sc = scenarios.build("suburban_street", width=W, height=H, seed=3)
    relief = sc.scene.relief
    assert 0.2 <= relief.height <= 0.6
    x_cam = sc.poses[:, 0, 3]
    assert x_cam[0] < relief.centre - relief.half_length < relief.centre < x_cam[-1]  # the car drives over it
    # the camera stays 1.65 m above the road (+- its heave) and pitches with the slope
    assert np.allclose(sc.poses[:, 2, 3] - relief.z(x_cam), 1.65, atol=0.03)
    pitch = np.arcsin(sc.poses[:, 2, 2])  # of the optical axis
    slope = np.arctan(relief.slope(x_cam))
    gain = np.polyfit(slope, pitch, 1)[0]  # the slope's share of the pitch (besides the car's own sway)
    assert 0.6 < gain < 1.4 and np.corrcoef(pitch, slope)[0, 1] > 0.6
    lifts = []
    for i in (0, int(np.argmin(np.abs(x_cam - (relief.centre - relief.half_length / 2)))), len(x_cam) // 2):
        X, pid = _world_points(sc, i)
        road = pid == stuff_id("road")
        raised = (pid == stuff_id("terrain")) | (pid == stuff_id("sidewalk"))
        assert road.sum() > 0.1 * W * H and raised.sum() > 0.02 * W * H
        assert np.abs(X[road, 2] - relief.z(X[road, 0])).max() < 0.02  # the road is the relief
        lift = X[raised, 2] - relief.z(X[raised, 0])  # the lawns' and pavements' tops above it
        assert np.median(lift) > 0.08
        lifts.append(np.median(lift))
    assert max(lifts) < 0.25


def test_the_road_changes_width_along_the_street():
    sc = scenarios.build("suburban_street", num_frames=2, width=W, height=H, seed=4)
    boxes = sc.scene.static
    walk = (boxes.pid == stuff_id("sidewalk")) & (boxes.center[:, 0] > 0) & (boxes.center[:, 0] < 100)
    kerbs = np.round(-(boxes.center[walk, 1] + boxes.half[walk, 1]), 2)  # the pavement's inner edge, right side
    assert len(np.unique(kerbs)) >= 4 and kerbs.min() >= 2.8 and kerbs.max() <= 4.6
