"""The written folder: it reads back exactly what was rendered, its files alone are geometrically consistent
(depth + calib + groundtruth.txt reproject onto the next frame's depth and colour), generation is deterministic,
cached and atomic, and the ``synthetic`` reader plugin yields proper Frames."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pvslam_plugins.datasets.synthetic import generator, scenarios, writer
from pvslam_plugins.datasets.synthetic.render import render
from pvslam_plugins.datasets.synthetic.reader import SyntheticSequence

W, H = 160, 120


@pytest.fixture(scope="module")
def moving_seq(tmp_path_factory):
    root = tmp_path_factory.mktemp("syn") / "mv"
    return generator.generate("moving_vehicles", root, num_frames=12, width=W, height=H, seed=5, progress=False)


def test_layout_and_metadata(moving_seq):
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "calib.txt", "panoptic.json", "loops.json",
                 "objects.json", "meta.json"):
        assert (moving_seq / name).is_file(), name
    for sub in ("rgb", "depth", "panoptic", "dynamic"):
        assert len(list((moving_seq / sub).glob("*.png"))) == 12
    meta = json.loads((moving_seq / "meta.json").read_text())
    assert meta["scenario"] == "moving_vehicles" and meta["seed"] == 5 and meta["width"] == W
    assert meta["version"] == writer.GENERATOR_VERSION
    objs = json.loads((moving_seq / "objects.json").read_text())
    assert len(objs["frames"]) == 12 and {str(o["id"]) for o in objs["objects"]} == set(objs["frames"][0]["poses"])
    assert set(meta["moving_ids"]) == {o["id"] for o in objs["objects"]}
    assert not list(moving_seq.parent.glob(".*tmp*"))  # no temporary folder left behind


def test_folder_reads_back_exactly(moving_seq):
    sc = scenarios.build("moving_vehicles", num_frames=12, width=W, height=H, seed=5)
    seq = SyntheticSequence(moving_seq)
    assert len(seq) == 12
    assert (seq.intrinsics.fx, seq.intrinsics.cx, seq.intrinsics.cy) == (sc.camera.fx, sc.camera.cx, sc.camera.cy)
    np.testing.assert_allclose(seq.timestamps, sc.timestamps, atol=1e-6)
    for i in (0, 7, 11):
        out = render(sc.scene, i, sc.poses[i], sc.camera)
        a = seq.arrays(i)
        np.testing.assert_array_equal(a["rgb"], out.rgb)
        q = writer.quantize_depth(out.depth, sc.depth_scale)
        np.testing.assert_array_equal(a["depth"], q.astype(np.float32) / np.float32(sc.depth_scale))
        np.testing.assert_array_equal(a["panoptic"], out.panoptic)
        np.testing.assert_array_equal(a["dynamic"], out.dynamic)
        R = Rotation.from_quat(a["pose"][3:]).as_matrix()
        np.testing.assert_allclose(R, sc.poses[i][:3, :3], atol=1e-8)
        np.testing.assert_allclose(a["pose"][:3], sc.poses[i][:3, 3], atol=1e-8)
        ids = {s.id for s in seq.segments(i)}
        assert ids == set(np.unique(out.panoptic).tolist()) - {0}


def _T(pose7):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(pose7[3:]).as_matrix()
    T[:3, 3] = pose7[:3]
    return T


def _file_consistency(seq: SyntheticSequence, i: int, j: int, shift=(0.0, 0.0, 0.0)):
    """Fraction of static pixels of frame i whose depth, reprojected with the files' poses and calibration, matches
    frame j's depth (inverse depth interpolated bilinearly, exact on planes) and colour, and the median colour
    error of the depth matches."""
    K = seq.intrinsics
    a, b = seq.arrays(i), seq.arrays(j)
    Ti, Tj = _T(a["pose"]), _T(b["pose"])
    Tj[:3, 3] += shift
    ok = (a["depth"] > 0) & ~a["dynamic"]
    v, u = np.nonzero(ok)
    z = a["depth"][v, u].astype(np.float64)
    Xc = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], 1)
    Xj = (Xc @ Ti[:3, :3].T + Ti[:3, 3] - Tj[:3, 3]) @ Tj[:3, :3]
    zj = Xj[:, 2]
    pu, pv = K.fx * Xj[:, 0] / zj + K.cx, K.fy * Xj[:, 1] / zj + K.cy
    x0, y0 = np.floor(pu).astype(int), np.floor(pv).astype(int)
    m = (zj > 0.1) & (x0 >= 0) & (y0 >= 0) & (x0 < K.width - 1) & (y0 < K.height - 1)
    pu, pv, zj, x0, y0, src = pu[m], pv[m], zj[m], x0[m], y0[m], (v[m], u[m])
    fx, fy = (pu - x0)[:, None], (pv - y0)[:, None]
    dj = b["depth"]
    corners = [(y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1)]
    dep = np.stack([dj[c] for c in corners], 1)
    pan = np.stack([b["panoptic"][c] for c in corners], 1)
    plane = (dep > 0).all(1) & (pan == pan[:, :1]).all(1)
    inv = 1.0 / np.where(dep > 0, dep, 1.0)
    wts = np.concatenate([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    inv_i = (inv * wts).sum(1)
    match = plane & (np.abs(inv_i * zj - 1.0) < 3e-3)
    rgb = np.stack([b["rgb"][c].astype(np.float64) for c in corners], 1)
    col = (rgb * wts[..., None]).sum(1)
    err = np.abs(col - a["rgb"][src].astype(np.float64)).mean(1)
    both = match & (err < 12.0)  # same depth and the same colour (8-bit levels)
    return both.sum() / max(plane.sum(), 1), float(np.median(err[match])) if match.any() else 255.0


@pytest.mark.parametrize("name", ["driving_loop", "indoor_handheld", "handheld_fast", "indoor_textureless",
                                  "busy_street", "forward_low_parallax", "driving_city", "suburban_street"])
def test_files_alone_are_geometrically_consistent(tmp_path, name):
    root = generator.generate(name, tmp_path / name, num_frames=4, width=320, height=240, seed=2, progress=False)
    seq = SyntheticSequence(root)
    for i, j in ((0, 1), (1, 3)):
        frac, colour_err = _file_consistency(seq, i, j)
        assert frac > 0.9, (i, j, frac)
        assert colour_err < 6.0, (i, j, colour_err)  # 8-bit levels
    # negative control: a 12 cm error in a pose is caught
    frac, _ = _file_consistency(seq, 0, 1, shift=(0.1, 0.05, 0.05))
    assert frac < 0.5


def test_moving_sequence_files_are_consistent_on_static_pixels(moving_seq):
    seq = SyntheticSequence(moving_seq)
    frac, colour_err = _file_consistency(seq, 2, 3)
    assert frac > 0.85 and colour_err < 6.0


def test_determinism_by_seed():
    a = scenarios.build("driving_loop", num_frames=3, width=64, height=48, seed=7)
    b = scenarios.build("driving_loop", num_frames=3, width=64, height=48, seed=7)
    c = scenarios.build("driving_loop", num_frames=3, width=64, height=48, seed=8)
    np.testing.assert_array_equal(a.poses, b.poses)
    ra, rb, rc = (render(s.scene, 2, s.poses[2], s.camera) for s in (a, b, c))
    np.testing.assert_array_equal(ra.rgb, rb.rgb)
    np.testing.assert_array_equal(ra.panoptic, rb.panoptic)
    np.testing.assert_array_equal(ra.depth, rb.depth)
    assert not np.array_equal(ra.rgb, rc.rgb)


def test_unknown_scenario_lists_the_scenarios(tmp_path):
    with pytest.raises(ValueError) as e:
        generator.generate("no_such_scene", tmp_path / "x")
    for name in generator.SCENARIOS:
        assert name in str(e.value)
    from pydantic import ValidationError

    from pvslam_plugins.datasets.synthetic.config import SyntheticConfig

    with pytest.raises(ValidationError) as e2:
        SyntheticConfig(scenario="no_such_scene")
    assert "driving_loop" in str(e2.value)


def test_cache_is_reused_and_writing_is_atomic(tmp_path, monkeypatch):
    monkeypatch.setenv("PVSLAM_CACHE", str(tmp_path / "cache"))
    p1 = generator.generate("indoor_handheld", None, num_frames=3, width=48, height=32, progress=False)
    assert p1.parent.parent == tmp_path / "cache" and generator.is_complete(p1)
    stamp = (p1 / "meta.json").stat().st_mtime_ns
    p2 = generator.ensure_cached("indoor_handheld", num_frames=3, width=48, height=32, progress=False)
    assert p2 == p1 and (p1 / "meta.json").stat().st_mtime_ns == stamp
    assert generator.cache_path("indoor_handheld", num_frames=4, width=48, height=32) != p1
    # an existing folder with other content is never overwritten
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x.txt").write_text("keep")
    with pytest.raises(FileExistsError):
        generator.generate("indoor_handheld", tmp_path / "busy", num_frames=3, width=48, height=32)
    # a crash while writing leaves neither the folder nor a temporary one
    calls = {"n": 0}
    real = writer.render

    def crashing(*args, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("boom")
        return real(*args, **kw)

    monkeypatch.setattr(writer, "render", crashing)
    with pytest.raises(RuntimeError):
        generator.generate("indoor_handheld", tmp_path / "out", num_frames=3, width=48, height=32, progress=False)
    assert not (tmp_path / "out").exists()
    assert not [p for p in tmp_path.iterdir() if "tmp" in p.name]


def test_reader_plugin_yields_frames(moving_seq, tmp_path, monkeypatch):
    import pvslam_plugins.datasets.synthetic as plugin
    from pvslam_core.registry import build_registry

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    reg = build_registry(extra_modules=(plugin,))
    spec = reg.get("dataset", "synthetic")
    assert spec.extras["generate"] is generator.generate and "driving_loop" in spec.extras["scenarios"]
    reader = spec.factory(spec.config_model(path=str(moving_seq), gt_maps=["depth", "panoptic", "dynamic"]), None)
    info = reader.info()
    assert info.num_frames == 12 and info.has_gt_pose and info.has_gt_depth and info.has_gt_panoptic
    assert (info.intrinsics.fx, info.intrinsics.cx, info.intrinsics.width) == (0.85 * W, (W - 1) / 2, W)
    cats = {c.name: c for c in info.categories}
    assert cats["car"].isthing and not cats["road"].isthing and cats["car"].id == 11
    frames = list(reader)
    assert [f.index for f in frames] == list(range(12))
    f = frames[4]
    assert f.image.shape == (3, H, W) and f.gt_pose.shape == (7,) and f.gt_depth.shape == (H, W)
    assert f.gt_dynamic.dtype.__str__() == "torch.bool" and f.gt_panoptic.ids.shape == (H, W)
    assert f.intrinsics == info.intrinsics
    # common options go through the base class: stride and resize
    r2 = spec.factory(spec.config_model(path=str(moving_seq), stride=2, resize=(80, 64)), None)
    assert r2.info().num_frames == 6 and r2.info().intrinsics.width == 80
    assert next(iter(r2)).image.shape == (3, 64, 80)
    # without a path the reader generates into the cache
    monkeypatch.setenv("PVSLAM_CACHE", str(tmp_path / "c"))
    r3 = spec.factory(spec.config_model(scenario="indoor_handheld", num_frames=3, width=48, height=32,
                                        progress=False), None)
    assert r3.info().num_frames == 3 and r3.info().name == "synthetic-indoor_handheld"


def test_loop_pairs_reach_the_reader(tmp_path):
    root = generator.generate("driving_loop", tmp_path / "dl", num_frames=None, laps=1.05, width=32, height=24,
                              progress=False)
    seq = SyntheticSequence(root)
    pairs = seq.loop_pairs
    assert pairs.dtype == np.int64 and pairs.shape[1] == 2 and len(pairs) and (pairs[:, 0] > pairs[:, 1] + 50).all()
    from pvslam_plugins.datasets.synthetic.config import SyntheticConfig
    from pvslam_plugins.datasets.synthetic.reader import SyntheticReader

    info = SyntheticReader(SyntheticConfig(path=str(root), crop_multiple=1)).info()
    assert len(info.loop_pairs) and set(map(tuple, info.loop_pairs.tolist())) == set(map(tuple, pairs.tolist()))



def test_invalid_calibration_names_the_file(tmp_path):
    """A hand-written minimal folder (no generator): the calibration is read before any image."""
    from pvslam_core.datasets.base import DatasetError

    root = tmp_path / "seq"
    root.mkdir()
    (root / "meta.json").write_text(json.dumps({"width": 32, "height": 24}))
    (root / "rgb.txt").write_text("0.0 rgb/000000.png\n0.1 rgb/000001.png\n")
    (root / "depth.txt").write_text("0.0 depth/000000.png\n0.1 depth/000001.png\n")
    (root / "groundtruth.txt").write_text("0.0 0 0 0 0 0 0 1\n0.1 0.1 0 0 0 0 0 1\n")
    (root / "calib.txt").write_text("27.2 27.2 nan 11.5\n")
    with pytest.raises(DatasetError) as err:
        SyntheticSequence(root)
    assert str(root / "calib.txt") in str(err.value) and "cx=nan" in str(err.value)


def test_a_long_sequences_segments_are_held_as_arrays_not_dicts(moving_seq, tmp_path):
    """The reader keeps every frame's ground-truth segment list for the whole run: as one int64 array (a few bytes a
    segment), not as panoptic.json's dict per segment (a 10 000-frame loop held ~23 MB that way).  The segments
    read back equal the file's, and a panoptic.json that does not fit the frame list is refused by name."""
    import shutil
    import tracemalloc

    from pvslam_core.datasets.base import DatasetError

    root = tmp_path / "long"
    shutil.copytree(moving_seq, root)
    n = 4000  # frames listed (the lists and panoptic.json only: the reader opens images when a frame is read)
    doc = json.loads((root / "panoptic.json").read_text())
    frames = [doc["frames"][i % len(doc["frames"])] for i in range(n)]
    (root / "panoptic.json").write_text(json.dumps({**doc, "frames": frames}))
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        rows = [r for r in (root / name).read_text().splitlines() if r and not r.startswith("#")]
        stamp = [float(r.split()[0]) for r in rows]
        step = stamp[1] - stamp[0]
        (root / name).write_text("".join(f"{k * step:.6f} {' '.join(rows[k % len(rows)].split()[1:])}\n"
                                         for k in range(n)))
    seq = SyntheticSequence(root)
    tracemalloc.start()
    seq.segments(0)  # panoptic.json is read on first use
    held = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    per_segment = held / sum(len(f["segments_info"]) for f in frames)
    assert per_segment < 40, per_segment  # a dict per segment: ~250 bytes
    for i in (0, 1, n - 1):
        want = frames[i]["segments_info"]
        assert [(s.id, s.category_id, s.isthing) for s in seq.segments(i)] == \
            [(w["id"], w["category_id"], w["isthing"]) for w in want]
    (root / "panoptic.json").write_text(json.dumps({**doc, "frames": frames[:-1]}))
    with pytest.raises(DatasetError, match="panoptic.json.*3999 frames"):
        SyntheticSequence(root).segments(0)
