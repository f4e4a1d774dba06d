"""Exports: COLMAP text model, nerfstudio transforms.json, TUM Sim(3)-aligned trajectory; camera conventions are
checked numerically with projections written here independently of pvslam's geometry."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pvslam_core.cli import main
from pvslam_core.outputs.export import colmap_pose, export_run, nerfstudio_c2w
from pvslam_core.outputs.keyframes_io import read_keyframes, write_keyframes
from pvslam_core.outputs.ply import write_ply
from pvslam_core.outputs.trajectory_io import read_tum, write_tum
from pvslam_core.types import Intrinsics

K_IMG = Intrinsics(120.0, 118.0, 79.5, 59.5, 160, 120)
K_DEPTH = [15.0, 14.75, 9.5, 7.0]  # K_IMG.scaled(1/8)


def _poses(n=4, seed=0):
    rng = np.random.default_rng(seed)
    q = Rotation.from_euler("xyz", rng.uniform(-0.4, 0.4, (n, 3))).as_quat()
    return np.concatenate([rng.uniform(-2, 2, (n, 3)), q], axis=1)


def _pvslam_pixel(X, pose):
    """u = K R_wc^T (X - t_wc), pixel centres at integers (pvslam/OpenCV)."""
    Xc = Rotation.from_quat(pose[3:]).as_matrix().T @ (X - pose[:3])
    return np.array([K_IMG.fx * Xc[0] / Xc[2] + K_IMG.cx, K_IMG.fy * Xc[1] / Xc[2] + K_IMG.cy]), Xc[2]


def test_colmap_pose_projects_to_the_same_pixel():
    poses = _poses(6)
    qvec, tvec = colmap_pose(poses)
    assert (qvec[:, 0] >= 0).all()
    for pose, q, t in zip(poses, qvec, tvec):
        X = pose[:3] + Rotation.from_quat(pose[3:]).apply([0.3, -0.2, 4.0])  # a point in front of the camera
        # COLMAP: X_cam = R(q) X + t with q = (qw, qx, qy, qz); cx_colmap = cx + 0.5 (pixel corner convention)
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        Xc = R @ X + t
        u_colmap = np.array([K_IMG.fx * Xc[0] / Xc[2] + K_IMG.cx + 0.5, K_IMG.fy * Xc[1] / Xc[2] + K_IMG.cy + 0.5])
        u_pv, _ = _pvslam_pixel(X, pose)
        np.testing.assert_allclose(u_colmap, u_pv + 0.5, atol=1e-9)


def test_nerfstudio_c2w_is_opengl():
    poses = _poses(6, seed=1)
    c2w = nerfstudio_c2w(poses)
    for pose, m in zip(poses, c2w):
        np.testing.assert_allclose(m[:3, 3], pose[:3])  # camera centre unchanged
        X = pose[:3] + Rotation.from_quat(pose[3:]).apply([-0.5, 0.4, 3.0])
        x, y, z = (np.linalg.inv(m) @ np.append(X, 1.0))[:3]
        assert z < 0  # OpenGL: the camera looks down -z
        # OpenGL pinhole with y up: u = fx x / -z + cx', v = -fy y / -z + cy' (cx' = cx + 0.5, pixel corners)
        u = np.array([K_IMG.fx * x / -z + K_IMG.cx + 0.5, -K_IMG.fy * y / -z + K_IMG.cy + 0.5])
        np.testing.assert_allclose(u, _pvslam_pixel(X, pose)[0] + 0.5, atol=1e-9)
        # right-handed rotation, camera y axis points up in the world when pvslam's y points down
        assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
        np.testing.assert_allclose(m[:3, 1], -Rotation.from_quat(pose[3:]).as_matrix()[:, 1])


@pytest.fixture
def run_dir(tmp_path):
    """A run directory written through pvslam's own writers: 4 keyframes, depth, a cloud with frame_index."""
    d = tmp_path / "run"
    d.mkdir()
    poses = _poses(4, seed=2)
    fi = np.array([0, 3, 7, 12])
    disps = np.full((4, 15, 20), 0.25, np.float32)
    disps[1, 2, 3] = 0.0
    write_keyframes(d, fi, 0.1 * fi, poses, disps, K_DEPTH, K_IMG, names=[f"img{i}.jpg" for i in fi])
    rng = np.random.default_rng(3)
    pts, src = [], []
    for pose, f in zip(poses, fi):
        local = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 6, 50)]
        pts.append(Rotation.from_quat(pose[3:]).apply(local) + pose[:3])
        src.append(np.full(50, f))
    pts = np.concatenate(pts).astype(np.float32)
    cols = rng.integers(0, 256, (len(pts), 3)).astype(np.uint8)
    write_ply(d / "cloud_rgb.ply", pts, cols, extra={"frame_index": np.concatenate(src).astype(np.int32)})
    ts = 0.1 * np.arange(13)
    write_tum(d / "trajectory.txt", ts, np.tile([0, 0, 0, 0, 0, 0, 1.0], (13, 1)))
    return d


def test_keyframes_round_trip(run_dir):
    kf = read_keyframes(run_dir)
    assert kf["frame_index"].tolist() == [0, 3, 7, 12] and kf["names"][1] == "img3.jpg"
    assert kf["depth"].shape == (4, 15, 20) and kf["depth"][0, 0, 0] == pytest.approx(4.0)
    assert kf["depth"][1, 2, 3] == 0.0  # no depth there
    assert kf["intrinsics"]["depth"] == {"fx": 15.0, "fy": 14.75, "cx": 9.5, "cy": 7.0, "width": 20, "height": 15}
    assert kf["intrinsics"]["image"]["width"] == 160
    assert sorted(p.name for p in (run_dir / "keyframes").glob("*.npy")) == [
        "000000_depth.npy", "000003_depth.npy", "000007_depth.npy", "000012_depth.npy"]


def _read_colmap(out):
    cams = [ln.split() for ln in (out / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    lines = [ln for ln in (out / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    images = {}
    for head, pts2d in zip(lines[0::2], lines[1::2]):
        h = head.split()
        v = pts2d.split()
        images[int(h[0])] = {"q": np.array(h[1:5], float), "t": np.array(h[5:8], float), "name": h[9],
                             "p2d": np.array(v, float).reshape(-1, 3)}
    pts = {}
    for ln in (out / "points3D.txt").read_text().splitlines():
        if ln.startswith("#"):
            continue
        v = ln.split()
        pts[int(v[0])] = {"X": np.array(v[1:4], float), "track": np.array(v[8:], int).reshape(-1, 2)}
    return cams, images, pts


def test_colmap_export_projects_points_onto_their_observations(run_dir):
    s = export_run(run_dir, "colmap", images=False)
    out = run_dir / "export" / "colmap"
    cams, images, pts = _read_colmap(out)
    assert cams == [["1", "PINHOLE", "160", "120", "120", "118", "80", "60"]]  # cx, cy + 0.5
    fx, fy, cx, cy = (float(v) for v in cams[0][4:])
    assert [im["name"] for im in images.values()] == ["000000.png", "000003.png", "000007.png", "000012.png"]
    assert len(pts) == 200 and s["points"] == 200
    kf = read_keyframes(run_dir)
    for pid, p in pts.items():
        assert len(p["track"]) >= 1
        for img, idx in p["track"]:
            im = images[img]
            R = Rotation.from_quat([*im["q"][1:], im["q"][0]]).as_matrix()
            Xc = R @ p["X"] + im["t"]
            uv = np.array([fx * Xc[0] / Xc[2] + cx, fy * Xc[1] / Xc[2] + cy])
            x, y, back = im["p2d"][idx]
            assert int(back) == pid
            np.testing.assert_allclose(uv, [x, y], atol=1e-4)  # 6 decimals in the file
            # and that is pvslam's pixel of the point, in COLMAP's pixel-corner convention
            np.testing.assert_allclose(uv, _pvslam_pixel(p["X"], kf["poses"][img - 1])[0] + 0.5, atol=1e-4)


def test_colmap_camera_with_distortion(run_dir):
    meta = json.loads((run_dir / "keyframes" / "keyframes.json").read_text())
    meta["intrinsics"]["image"]["dist"] = [-0.1, 0.01, 0.001, -0.002]
    (run_dir / "keyframes" / "keyframes.json").write_text(json.dumps(meta))
    export_run(run_dir, "colmap", images=False)
    cams, _, _ = _read_colmap(run_dir / "export" / "colmap")
    assert cams[0][1] == "OPENCV" and [float(v) for v in cams[0][8:]] == [-0.1, 0.01, 0.001, -0.002]


def test_nerfstudio_export(run_dir):
    export_run(run_dir, "nerfstudio", images=False)
    out = run_dir / "export" / "nerfstudio"
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["w"] == 160 and meta["cx"] == 80.0 and meta["fl_y"] == 118.0
    assert meta["ply_file_path"] == "sparse_pc.ply" and (out / "sparse_pc.ply").is_file()
    kf = read_keyframes(run_dir)
    for n, fr in enumerate(meta["frames"]):
        assert fr["file_path"] == f"images/{kf['frame_index'][n]:06d}.png"
        m = np.array(fr["transform_matrix"])
        X = kf["poses"][n][:3] + Rotation.from_quat(kf["poses"][n][3:]).apply([0.2, 0.1, 5.0])
        x, y, z = (np.linalg.inv(m) @ np.append(X, 1))[:3]
        u = [meta["fl_x"] * x / -z + meta["cx"], -meta["fl_y"] * y / -z + meta["cy"]]
        np.testing.assert_allclose(u, _pvslam_pixel(X, kf["poses"][n])[0] + 0.5, atol=1e-9)
        assert fr["depth_file_path"] == f"depth/{kf['frame_index'][n]:06d}.png"


def test_tum_aligned_recovers_the_ground_truth(run_dir):
    rng = np.random.default_rng(4)
    n = 40
    t = np.linspace(0, 3, n)
    gt = np.c_[np.c_[5 * np.cos(t), 0.3 * np.sin(2 * t), 5 * np.sin(t)],
               Rotation.from_euler("y", -t[:, None]).as_quat()]
    # the estimate is the ground truth in another frame and scale: gt = s R est + T
    s, R, T = 2.5, Rotation.from_euler("xyz", [0.3, -0.7, 1.1]), np.array([1.0, -2.0, 0.5])
    est = gt.copy()
    est[:, :3] = R.inv().apply((gt[:, :3] - T) / s)
    est[:, 3:] = (R.inv() * Rotation.from_quat(gt[:, 3:])).as_quat()
    est[:, 3:] *= np.sign(rng.normal(size=(n, 1)))  # q and -q: the same rotation
    ts = 0.1 * np.arange(n)
    write_tum(run_dir / "trajectory.txt", ts, est)
    write_tum(run_dir / "groundtruth.txt", ts, gt)
    summary = export_run(run_dir, "tum-aligned")
    assert summary["scale"] == pytest.approx(s, rel=1e-9)
    ats, al = read_tum(run_dir / "export" / "tum-aligned" / "trajectory_aligned.txt")
    np.testing.assert_allclose(ats, ts)
    np.testing.assert_allclose(al[:, :3], gt[:, :3], atol=1e-6)
    angle = (Rotation.from_quat(al[:, 3:]).inv() * Rotation.from_quat(gt[:, 3:])).magnitude()
    assert angle.max() < 1e-6


def test_tum_aligned_without_ground_truth_says_so(run_dir):
    with pytest.raises(FileNotFoundError, match="groundtruth.txt"):
        export_run(run_dir, "tum-aligned")


def test_export_without_keyframes_says_why(run_dir):
    import shutil

    shutil.rmtree(run_dir / "keyframes")
    with pytest.raises(FileNotFoundError, match="keyframe_depth"):
        export_run(run_dir, "colmap")


def test_colmap_model_reads_in_pycolmap(run_dir):
    """COLMAP's own reader and projection (the `bench` extra installs pycolmap)."""
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap comes with the bench extra")
    export_run(run_dir, "colmap", images=False)
    rec = pycolmap.Reconstruction(str(run_dir / "export" / "colmap"))
    assert len(rec.images) == 4 and len(rec.points3D) == 200
    cam = rec.cameras[1]
    kf = read_keyframes(run_dir)
    for p3 in rec.points3D.values():
        for el in p3.track.elements:
            img = rec.images[el.image_id]
            uv = np.asarray(cam.img_from_cam(img.cam_from_world() * p3.xyz)).ravel()[:2]
            np.testing.assert_allclose(uv, img.points2D[el.point2D_idx].xy, atol=1e-4)
            np.testing.assert_allclose(uv, _pvslam_pixel(p3.xyz, kf["poses"][el.image_id - 1])[0] + 0.5, atol=1e-6)


def toy_writer(run_dir, out_dir, kf):
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "frames.txt").write_text(" ".join(str(int(f)) for f in kf["frame_index"]))
    return {"frames": len(kf["frame_index"])}


def test_a_new_format_is_one_line_in_the_formats_table(run_dir, monkeypatch, capsys):
    """A writer function plus its ExportFormat line: export_run and `pvslam export --format` know it."""
    from pvslam_core.cli import main
    from pvslam_core.outputs.formats import EXPORT_FORMATS, ExportFormat

    monkeypatch.setitem(EXPORT_FORMATS, "toy", ExportFormat("toy", f"{__name__}:toy_writer", True, "frame list"))
    summary = export_run(run_dir, "toy", images=False)
    assert summary["frames"] == 4 and (run_dir / "export" / "toy" / "frames.txt").read_text() == "0 3 7 12"
    assert main(["export", str(run_dir), "--format", "toy", "--no-images"]) == 0
    assert "frames: 4" in capsys.readouterr().out


# ------------------------------------------------------------------------- damaged or hostile keyframes.json --
def _edit(run_dir, change) -> None:
    path = run_dir / "keyframes" / "keyframes.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def _outside(run_dir):
    """A float32 .npy file of the keyframes' depth shape outside the run directory (would load if followed)."""
    secret = run_dir.parent / "secret" / "depth.npy"
    secret.parent.mkdir()
    np.save(secret, np.full((15, 20), 7.0, np.float32))
    return secret


@pytest.mark.parametrize("key", ["keyframes", "intrinsics"])
def test_missing_top_level_keys_are_named(run_dir, key, capsys):
    _edit(run_dir, lambda m: m.pop(key))
    with pytest.raises(ValueError, match=f"keyframes.json: '{key}'"):
        read_keyframes(run_dir)
    assert main(["export", str(run_dir), "--format", "colmap", "--no-images"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pvslam: error: ") and "keyframes.json" in err[0] and key in err[0]


def test_a_keyframe_without_a_key_is_named(run_dir):
    _edit(run_dir, lambda m: m["keyframes"][2].pop("pose"))
    with pytest.raises(ValueError, match="lack the key 'pose'"):
        export_run(run_dir, "nerfstudio", images=False)
    _edit(run_dir, lambda m: m.__setitem__("keyframes", {"not": "a list"}))
    with pytest.raises(ValueError, match="'keyframes' is missing or not a list"):
        export_run(run_dir, "colmap", images=False)


def test_a_depth_file_outside_the_run_directory_is_refused(run_dir):
    secret = _outside(run_dir)
    for name in ("../../secret/depth.npy", str(secret)):
        _edit(run_dir, lambda m: m["keyframes"][1].__setitem__("depth_file", name))
        with pytest.raises(ValueError, match=r"keyframe 1: depth_file .* leads out of the run directory"):
            export_run(run_dir, "nerfstudio", images=False)
    assert not (run_dir / "export").exists() or not list((run_dir / "export").rglob("*.npy"))


def test_a_symlinked_depth_file_leading_out_is_refused(run_dir):
    secret = _outside(run_dir)
    link = run_dir / "keyframes" / "000003_depth.npy"
    link.unlink()
    os.symlink(secret, link)  # the name is the writer's own; the file is elsewhere
    with pytest.raises(ValueError, match="keyframe 1: depth_file '000003_depth.npy' leads out of the run directory"):
        read_keyframes(run_dir)
    link.unlink()  # a link that stays inside the run directory is fine
    os.symlink(run_dir / "keyframes" / "000000_depth.npy", link)
    assert read_keyframes(run_dir)["depth"].shape == (4, 15, 20)


# ------------------------------------------------------------------ a plane seen by keyframes that agree on it --
PLANE_N, PLANE_C = np.array([-0.2, -0.3, 1.0]), 5.0  # the world plane z = 5 + 0.2 x + 0.3 y
PLANE_FI = np.array([0, 4, 8, 12, 16, 40])  # keyframe 5 (frame 40) comes back to keyframe 0's place
BAD = 4  # keyframe 4's depth is 1.3x too far: it disagrees with every other keyframe


def _plane_poses():
    x = [0.0, 0.25, 0.5, 0.75, 1.0, 0.05]
    yaw = [0.0, 0.02, -0.02, 0.03, 0.0, 0.01]
    return np.array([[xi, 0, 0, *Rotation.from_euler("y", a).as_quat()] for xi, a in zip(x, yaw)])


def _plane_depth(pose, fx, fy, cx, cy, u, v):
    """z-depth of the plane along the rays of pixels ``(u, v)`` of the camera ``pose``."""
    rays = Rotation.from_quat(pose[3:]).apply(np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1))
    return (PLANE_C - PLANE_N @ pose[:3]) / (rays @ PLANE_N)


@pytest.fixture
def plane_run(tmp_path):
    """A run directory (pvslam's own writers) of 6 keyframes over a tilted plane: depth rendered at the depth
    resolution, one pixel without depth, the cloud is every depth pixel moved into the world (as a run writes it)."""
    d = tmp_path / "plane"
    d.mkdir()
    poses = _plane_poses()
    fx, fy, cx, cy = K_DEPTH
    v, u = np.mgrid[0:15, 0:20].astype(np.float64)
    depth = np.stack([_plane_depth(p, fx, fy, cx, cy, u, v) for p in poses])
    depth[BAD] *= 1.3
    depth[2, 5, 7] = 0.0
    disps = np.where(depth > 0, 1.0 / np.where(depth > 0, depth, 1.0), 0.0).astype(np.float32)
    write_keyframes(d, PLANE_FI, 0.1 * PLANE_FI, poses, disps, K_DEPTH, K_IMG)
    pts, src = [], []
    for n, p in enumerate(poses):
        ok = depth[n] > 0
        local = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)[ok] * depth[n][ok][:, None]
        pts.append(Rotation.from_quat(p[3:]).apply(local) + p[:3])
        src.append(np.full(len(local), PLANE_FI[n]))
    pts = np.concatenate(pts).astype(np.float32)
    write_ply(d / "cloud_rgb.ply", pts, np.full((len(pts), 3), 200, np.uint8),
              extra={"frame_index": np.concatenate(src).astype(np.int32)})
    write_tum(d / "trajectory.txt", 0.1 * np.arange(41), np.tile([0, 0, 0, 0, 0, 0, 1.0], (41, 1)))
    return d


def _tracks(run_dir):
    export_run(run_dir, "colmap", images=False)
    return _read_colmap(run_dir / "export" / "colmap")


def test_colmap_tracks_are_multi_view_and_point_both_ways(plane_run):
    cams, images, pts = _tracks(plane_run)
    fx, fy, cx, cy = (float(v) for v in cams[0][4:])
    poses = _plane_poses()
    lengths = np.array([len(p["track"]) for p in pts.values()])
    assert (lengths >= 2).mean() > 0.5 and lengths.max() >= 4
    listed = set()
    for pid, p in pts.items():
        imgs = p["track"][:, 0].tolist()
        assert len(set(imgs)) == len(imgs)  # one observation per image
        for img, idx in p["track"]:
            im = images[img]
            x, y, back = im["p2d"][idx]
            assert int(back) == pid  # POINT2D_IDX names the point back
            listed.add((img, idx))
            R = Rotation.from_quat([*im["q"][1:], im["q"][0]]).as_matrix()
            Xc = R @ p["X"] + im["t"]
            uv = np.array([fx * Xc[0] / Xc[2] + cx, fy * Xc[1] / Xc[2] + cy])
            np.testing.assert_allclose(uv, [x, y], atol=1e-3)  # reprojection error
            assert 0 <= x <= 160 and 0 <= y <= 120  # inside the image
            if img - 1 != BAD:  # the point lies on the plane this keyframe sees there
                z = _plane_depth(poses[img - 1], K_IMG.fx, K_IMG.fy, K_IMG.cx, K_IMG.cy, x - 0.5, y - 0.5)
                assert Xc[2] == pytest.approx(z, rel=1e-3)
    # and every 2D point with a 3D point is in that point's track
    assert listed == {(img, j) for img, im in images.items() for j, row in enumerate(im["p2d"]) if row[2] != -1}


def test_colmap_tracks_need_the_depth_to_agree_and_a_pair(plane_run):
    _, _, pts = _tracks(plane_run)
    pairs = {(i, j) for i in range(6) for j in range(6) if 0 < abs(i - j) <= 2}
    around = 0
    for p in pts.values():
        imgs = sorted(p["track"][:, 0] - 1)
        if BAD in imgs:  # its depth disagrees with everyone's
            assert imgs == [BAD]
        # no loop file: the point's own keyframe and keyframes at most two before or after it
        assert any(all((s, j) in pairs for j in imgs if j != s) for s in imgs)
        around += {BAD - 1, BAD + 1} <= set(imgs)
    assert around > 100  # the keyframes on both sides of the bad one do share points


def test_colmap_tracks_follow_the_loops(plane_run):
    from pvslam_core.outputs.loops_io import write_loops

    def both(pts):
        return sum({1, 6} <= set(p["track"][:, 0].tolist()) for p in pts.values())

    assert both(_tracks(plane_run)[2]) == 0
    write_loops(plane_run / "loops.json", [{"frame_i": 40, "frame_j": 0, "score": 0.9}])
    assert both(_tracks(plane_run)[2]) > 100


def test_colmap_tracks_read_in_pycolmap(plane_run):
    """COLMAP's own reader: multi-view tracks, each element's 2D point names the 3D point and is its projection."""
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap comes with the bench extra")
    export_run(plane_run, "colmap", images=False)
    rec = pycolmap.Reconstruction(str(plane_run / "export" / "colmap"))
    cam = rec.cameras[1]
    lengths = [p3.track.length() for p3 in rec.points3D.values()]
    assert len(rec.images) == 6 and max(lengths) >= 4 and np.mean(np.array(lengths) >= 2) > 0.5
    for pid, p3 in rec.points3D.items():
        for el in p3.track.elements:
            img = rec.images[el.image_id]
            assert img.points2D[el.point2D_idx].point3D_id == pid
            uv = np.asarray(cam.img_from_cam(img.cam_from_world() * p3.xyz)).ravel()[:2]
            np.testing.assert_allclose(uv, img.points2D[el.point2D_idx].xy, atol=1e-3)


def test_nerfstudio_depth_png_at_image_size(plane_run):
    import cv2

    export_run(plane_run, "nerfstudio", images=False)
    out = plane_run / "export" / "nerfstudio"
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["depth_unit_scale_factor"] == 1e-3  # nerfstudio's default: millimetres
    kf = read_keyframes(plane_run)
    for n, fr in enumerate(meta["frames"]):
        png = cv2.imread(str(out / fr["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == (meta["h"], meta["w"]) == (120, 160)
        # nearest: image pixel (y, x) lies in depth pixel (y // 8, x // 8) of the 1/8 map
        expect = kf["depth"][n][np.arange(120)[:, None] // 8, np.arange(160)[None] // 8]
        np.testing.assert_allclose(png * 1e-3, expect, atol=5e-4)
    png = cv2.imread(str(out / "depth" / "000008.png"), cv2.IMREAD_UNCHANGED)
    assert (png[40:48, 56:64] == 0).all() and (png[40:48, 48:56] > 0).all()  # no depth stays no depth


def test_nerfstudio_depth_unit_follows_the_median_depth(plane_run):
    import cv2

    kf = read_keyframes(plane_run)
    for n, f in enumerate(kf["frame_index"]):  # a map 20x larger: median depth ~100, millimetres overflow 16 bits
        np.save(plane_run / "keyframes" / f"{f:06d}_depth.npy", kf["depth"][n] * 20.0)
    s = export_run(plane_run, "nerfstudio", images=False)
    out = plane_run / "export" / "nerfstudio"
    assert s["depth_unit_scale_factor"] == 0.1 == json.loads((out / "transforms.json").read_text())[
        "depth_unit_scale_factor"]
    png = cv2.imread(str(out / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(png[3::8, 3::8] * 0.1, kf["depth"][0] * 20.0, atol=0.05)


def test_nerfstudio_depth_beyond_16_bits_is_no_depth(plane_run):
    import cv2

    depth = read_keyframes(plane_run)["depth"][1]
    depth[0, 0] = 1000.0  # a pixel at the disparity floor: 1e6 thousandths
    np.save(plane_run / "keyframes" / "000004_depth.npy", depth)
    s = export_run(plane_run, "nerfstudio", images=False)
    png = cv2.imread(str(plane_run / "export" / "nerfstudio" / "depth" / "000004.png"), cv2.IMREAD_UNCHANGED)
    assert s["depth_unit_scale_factor"] == 1e-3 and s["depth_pixels_beyond_range"] == 64
    assert (png[:8, :8] == 0).all() and (png[:8, 8:16] > 0).all()
