"""PLY round trip and back-projection, panoptic PNG round trip, colour visualisation, plots."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pvslam_core.outputs.panoptic_png import (
    MAX_ID,
    PanopticWriter,
    colorize,
    decode_ids,
    encode_ids,
    load_panoptic,
    load_panoptic_dir,
    save_panoptic,
)
from pvslam_core.outputs.plots import plot_error_over_time, plot_trajectory_top, top_view_axes
from pvslam_core.outputs.ply import (
    panoptic_point_cloud_from_keyframes,
    point_cloud_from_keyframes,
    read_ply,
    write_ply,
)
from pvslam_core.types import Category, PanopticSegmentation, Segment

CATS = [Category(1, "road", False, (128, 64, 128)), Category(2, "car", True, (0, 0, 142))]


# ---------------------------------------------------------------------------------------------------------------
# PLY
# ---------------------------------------------------------------------------------------------------------------
def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    n = 10_000
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    cols = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    extra = {"category_id": rng.integers(-1, 20, n).astype(np.int64), "conf": rng.random(n).astype(np.float32),
             "dynamic": rng.random(n) > 0.5}
    p = tmp_path / "c.ply"
    assert write_ply(p, pts, cols, extra) == n
    header = p.read_bytes()[:400].split(b"end_header")[0].decode()
    assert "binary_little_endian" in header and "property uchar red" in header and "property int category_id" in header
    pts2, cols2, extra2 = read_ply(p)
    np.testing.assert_array_equal(pts2, pts)
    np.testing.assert_array_equal(cols2, cols)
    np.testing.assert_array_equal(extra2["category_id"], extra["category_id"])
    np.testing.assert_array_equal(extra2["conf"], extra["conf"])
    np.testing.assert_array_equal(extra2["dynamic"], extra["dynamic"].astype(np.uint8))
    # File size = header + 4*3 + 3 + 4 + 4 + 1 bytes per vertex.
    assert os.path.getsize(p) == len(header) + len("end_header\n") + n * (12 + 3 + 4 + 4 + 1)


def test_ply_empty_and_no_colors(tmp_path):
    write_ply(tmp_path / "e.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    pts, cols, _ = read_ply(tmp_path / "e.ply")
    assert pts.shape == (0, 3) and cols.shape == (0, 3)
    write_ply(tmp_path / "n.ply", torch.ones(4, 3))
    pts, cols, extra = read_ply(tmp_path / "n.ply")
    assert cols is None and extra == {} and pts.shape == (4, 3)


def test_ply_bad_input(tmp_path):
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        write_ply(tmp_path / "b.ply", np.zeros((3, 2)))
    with pytest.raises(ValueError, match="colors"):
        write_ply(tmp_path / "b.ply", np.zeros((3, 3)), np.zeros((2, 3), np.uint8))
    assert not (tmp_path / "b.ply").exists()


def test_point_cloud_from_keyframes_known_geometry():
    # Keyframe 0 at the origin, keyframe 1 translated by (1, 0, 0) and yawed 90 degrees about the camera y axis.
    h, w = 6, 8
    intr = torch.tensor([4.0, 4.0, 3.5, 2.5])
    disps = torch.full((2, h, w), 0.5)  # depth 2 m everywhere
    disps[0, 0, 0] = 0.0  # invalid
    disps[1, 5, 7] = 1e-3  # 1000 m: far, dropped by max_depth
    q1 = Rotation.from_euler("y", 90, degrees=True).as_quat()
    poses = torch.tensor([[0, 0, 0, 0, 0, 0, 1.0], [1, 0, 0, *q1]], dtype=torch.float64)
    images = torch.zeros(2, 3, h, w, dtype=torch.uint8)
    images[1, 0] = 255
    images[0, 2, 1, 2] = 77
    pts, cols = point_cloud_from_keyframes(poses, disps, intr, images, max_depth=10.0)
    assert pts.dtype == np.float32 and cols.dtype == np.uint8
    assert len(pts) == 2 * h * w - 2
    # Keyframe 0 pixel (x=2, y=1): X_c = ((2-3.5)/4*2, (1-2.5)/4*2, 2) = (-0.75, -0.75, 2).
    k = np.nonzero(cols[:, 2] == 77)[0]
    np.testing.assert_allclose(pts[k[0]], [-0.75, -0.75, 2.0], atol=1e-6)
    # Keyframe 1 points: world = R_y(90) X_c + (1, 0, 0); the optical axis (z) maps to world +x.
    kf1 = pts[cols[:, 0] == 255]
    assert len(kf1) == h * w - 1
    np.testing.assert_allclose(kf1[:, 0], 1.0 + 2.0, atol=1e-5)  # z_c = 2 -> x_w = 1 + 2
    # stride and relative far-point filter
    pts2, _ = point_cloud_from_keyframes(poses, disps, intr, images, stride=2)
    assert len(pts2) == 2 * 3 * 4 - 1  # (0, 0) invalid; the far pixel (5, 7) is not on the stride-2 grid
    # Images at a higher resolution are resized.
    big = torch.nn.functional.interpolate(images.float(), scale_factor=2, mode="nearest").to(torch.uint8)
    pts3, cols3 = point_cloud_from_keyframes(poses, disps, intr, big, max_depth=10.0)
    np.testing.assert_array_equal(pts3, pts)
    np.testing.assert_array_equal(cols3, cols)


def test_panoptic_point_cloud(tmp_path):
    h, w = 4, 4
    ids = torch.zeros(h, w, dtype=torch.int64)
    ids[:2] = 1
    ids[2:, :2] = 7
    seg = PanopticSegmentation(ids, [Segment(1, 1, False), Segment(7, 2, True)])
    poses = torch.tensor([[0, 0, 0, 0, 0, 0, 1.0]], dtype=torch.float64)
    pts, cols, extra = panoptic_point_cloud_from_keyframes(poses, torch.ones(1, h, w), [2.0, 2.0, 1.5, 1.5], [seg], CATS)
    assert len(pts) == 12  # void dropped
    assert set(extra["category_id"].tolist()) == {1, 2}
    road = extra["category_id"] == 1
    np.testing.assert_array_equal(cols[road], np.tile([128, 64, 128], (road.sum(), 1)))
    write_ply(tmp_path / "p.ply", pts, cols, extra)
    _, _, e2 = read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(e2["segment_id"], extra["segment_id"])


# ---------------------------------------------------------------------------------------------------------------
# Panoptic PNG
# ---------------------------------------------------------------------------------------------------------------
def test_encode_decode_ids_full_range():
    rng = np.random.default_rng(0)
    ids = rng.integers(0, MAX_ID + 1, size=(37, 53), dtype=np.int64)
    ids[0, :4] = [0, 1, 255, 256]
    ids[1, :3] = [65535, 65536, MAX_ID]
    rgb = encode_ids(ids)
    assert rgb.dtype == np.uint8 and rgb.shape == (37, 53, 3)
    np.testing.assert_array_equal(rgb[0, 3], [0, 1, 0])
    np.testing.assert_array_equal(rgb[1, 2], [255, 255, 255])
    np.testing.assert_array_equal(decode_ids(rgb), ids)
    with pytest.raises(ValueError, match="ids must be in"):
        encode_ids(np.array([[MAX_ID + 1]]))
    with pytest.raises(ValueError):
        encode_ids(np.array([[-1]]))


def test_panoptic_png_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    ids = rng.choice([0, 1, 7, 300, 70_000, MAX_ID], size=(24, 32)).astype(np.int64)
    segs = [Segment(1, 1, False), Segment(7, 2, True, 0.9), Segment(300, 2, True), Segment(70_000, 2, True),
            Segment(MAX_ID, 1, False), Segment(12345, 2, True)]  # 12345 absent from the map
    seg = PanopticSegmentation(torch.from_numpy(ids), segs)
    info = save_panoptic(tmp_path / "000003.png", seg)
    assert {d["id"] for d in info} == {1, 7, 300, 70_000, MAX_ID}
    assert sum(d["area"] for d in info) == int((ids != 0).sum())
    # The PNG itself holds id = R + 256 G + 256^2 B in RGB order (check with an independent reader).
    from PIL import Image

    rgb = np.asarray(Image.open(tmp_path / "000003.png").convert("RGB")).astype(np.int64)
    np.testing.assert_array_equal(rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2], ids)
    assert all(set(d) == {"id", "category_id", "iscrowd", "bbox", "area"} for d in info)  # COCO keys only
    back = load_panoptic(tmp_path / "000003.png", info, CATS, scores={7: 0.9})  # scores: pvslam's own key
    np.testing.assert_array_equal(back.ids.numpy(), ids)
    assert back.segment(7).category_id == 2 and back.segment(7).isthing and back.segment(7).score == pytest.approx(0.9)
    assert not back.segment(1).isthing


def test_colorize_categories_and_instances():
    ids = torch.tensor([[0, 1, 1, 5], [6, 6, 5, 5]])
    seg = PanopticSegmentation(ids, [Segment(1, 1, False), Segment(5, 2, True), Segment(6, 2, True)])
    img = colorize(seg, CATS)
    assert img.dtype == np.uint8 and img.shape == (2, 4, 3)
    np.testing.assert_array_equal(img[0, 0], [0, 0, 0])  # void
    np.testing.assert_array_equal(img[0, 1], [128, 64, 128])  # stuff: exact category colour
    assert not np.array_equal(img[0, 3], img[1, 0])  # two cars: distinct shades
    assert np.abs(img[0, 3].astype(int) - [0, 0, 142]).max() <= 50  # ... of the car colour
    # Stable over time: the shade depends on the id only.
    seg2 = PanopticSegmentation(torch.tensor([[5]]), [Segment(5, 2, True)])
    np.testing.assert_array_equal(colorize(seg2, CATS)[0, 0], img[0, 3])


def test_panoptic_writer_run_dir(tmp_path):
    segs = {}
    with PanopticWriter(tmp_path, categories=CATS, vis=True, flush_every=2) as w:
        for t in (0, 2, 4):
            ids = torch.ones(6, 8, dtype=torch.int64)
            ids[2:4, t : t + 3] = 1000 + t
            segs[t] = PanopticSegmentation(ids, [Segment(1, 1, False), Segment(1000 + t, 2, True)])
            w.write(t, segs[t])
            if t == 2:  # flushed after the second frame: segments.json valid mid-run
                assert len(json.loads((tmp_path / "panoptic" / "segments.json").read_text())["annotations"]) == 2
    assert sorted(os.listdir(tmp_path / "panoptic")) == ["000000.png", "000002.png", "000004.png", "segments.json"]
    assert sorted(os.listdir(tmp_path / "panoptic_vis")) == ["000000.png", "000002.png", "000004.png"]
    meta = json.loads((tmp_path / "panoptic" / "segments.json").read_text())
    assert [c["name"] for c in meta["categories"]] == ["road", "car"]
    loaded = load_panoptic_dir(tmp_path / "panoptic")
    assert sorted(loaded) == [0, 2, 4]
    for t in loaded:
        np.testing.assert_array_equal(loaded[t].ids.numpy(), segs[t].ids.numpy())
        assert loaded[t].segment(1000 + t).isthing


# ---------------------------------------------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------------------------------------------
def _png_ok(path) -> bool:
    data = open(path, "rb").read()
    return data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 2000


def test_plots_produce_png(tmp_path):
    t = np.linspace(0, 2 * np.pi, 200)
    gt = np.stack([10 * np.cos(t), 0.1 * np.sin(5 * t), 6 * np.sin(t)], axis=1)  # KITTI-like: x-z plane
    est = gt + np.random.default_rng(0).normal(0, 0.2, gt.shape)
    err = np.linalg.norm(est - gt, axis=1)
    assert top_view_axes(gt) == (0, 2)
    axes = plot_trajectory_top(tmp_path / "plots" / "trajectory_top.png", est, gt, err)
    assert axes == (0, 2)
    assert _png_ok(tmp_path / "plots" / "trajectory_top.png")
    plot_trajectory_top(tmp_path / "no_gt.png", est, None, None)
    assert _png_ok(tmp_path / "no_gt.png")
    plot_error_over_time(tmp_path / "ate.png", 100 + 0.1 * np.arange(200), err)
    assert _png_ok(tmp_path / "ate.png")
    from PIL import Image

    im = Image.open(tmp_path / "plots" / "trajectory_top.png")
    assert im.size[0] > 200 and im.size[1] > 200
