"""Tests of the benchmark peers (bench/peers): textbook OpenCV VO, COLMAP via pycolmap, ATE helpers.

The sequences are rendered here (a camera inside a textured box, ray-cast with numpy, exact poses), so the
tests do not depend on the synthetic generator plugin; when the generator exists, a ``slow`` test also runs the
VO on a short ``driving_loop`` sequence from it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.peers.common import ate_sim3, load_sequence, umeyama_sim3  # noqa: E402
from bench.peers.textbook_vo import run_textbook_vo  # noqa: E402

# --------------------------------------------------------------------------------------------------
# A tiny exact-GT sequence: camera inside a textured box (floor, ceiling, walls), moving forward with sway/yaw
# --------------------------------------------------------------------------------------------------

_BOX_MIN = np.array([-4.0, -3.0, -3.0])  # x right, y down, z forward (OpenCV-like world)
_BOX_MAX = np.array([4.0, 1.5, 40.0])
_TEXELS_PER_M = 24.0
_TEX = 256  # texture tile size (texels); the six faces share one atlas so a single cv2.remap renders a frame


def _atlas() -> np.ndarray:
    from skimage import data

    names = ["brick", "gravel", "astronaut", "coffee", "chelsea", "rocket"]
    tiles = []
    for k, n in enumerate(names):
        im = getattr(data, n)()
        if im.ndim == 2:
            tint = np.array([(0.9, 0.8, 1.0), (1.0, 0.9, 0.7)][k % 2])
            im = (im[..., None] * tint).clip(0, 255).astype(np.uint8)
        im = cv2.resize(np.ascontiguousarray(im[..., :3]), (_TEX, _TEX), interpolation=cv2.INTER_AREA)
        tiles.append(cv2.GaussianBlur(im, (0, 0), 0.8))
    return np.concatenate(tiles, axis=1).astype(np.float32)  # [TEX, 6*TEX, 3]


def _render(atlas: np.ndarray, K: np.ndarray, R_wc: np.ndarray, c: np.ndarray, w: int, h: int) -> np.ndarray:
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ R_wc.T.astype(
        np.float32)
    best_t = np.full((h, w), np.inf, np.float32)
    face = np.zeros((h, w), np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            for side, bound in enumerate((_BOX_MIN[axis], _BOX_MAX[axis])):
                t = (np.float32(bound - c[axis])) / rays[..., axis]
                better = (t > 1e-6) & (t < best_t)
                best_t[better] = t[better]
                face[better] = 2 * axis + side
    P = c.astype(np.float32) + rays * best_t[..., None]
    ax0 = np.array([1, 1, 0, 0, 0, 0])[face]  # the two in-plane axes of each face
    ax1 = np.array([2, 2, 2, 2, 1, 1])[face]
    a = np.take_along_axis(P, ax0[..., None], -1)[..., 0] * _TEXELS_PER_M
    b = np.take_along_axis(P, ax1[..., None], -1)[..., 0] * _TEXELS_PER_M
    mx = (np.mod(a, _TEX - 1) + face * _TEX).astype(np.float32)
    my = np.mod(b, _TEX - 1).astype(np.float32)
    img = cv2.remap(atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return img.clip(0, 255).astype(np.uint8)


def make_box_sequence(out: Path, num_frames: int = 40, w: int = 320, h: int = 240, step: float = 0.25) -> Path:
    """Write a TUM-style sequence folder (rgb/, rgb.txt, groundtruth.txt, calib.txt) with exact T_wc."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "rgb").mkdir(exist_ok=True)
    fx = 0.9 * w
    K = np.array([[fx, 0, (w - 1) / 2], [0, fx, (h - 1) / 2], [0, 0, 1.0]])
    tex = _atlas()
    rgb_lines, gt_lines = [], []
    for i in range(num_frames):
        s = i / max(num_frames - 1, 1)
        c = np.array([1.2 * np.sin(2 * np.pi * s), -0.3 * np.sin(4 * np.pi * s), step * i])
        R_wc = Rotation.from_euler("yxz", [12 * np.sin(2 * np.pi * s + 0.8), 3 * np.cos(3 * np.pi * s), 2 * s],
                                   degrees=True).as_matrix()
        img = _render(tex, K, R_wc, c, w, h)
        name = f"rgb/{i:06d}.png"
        cv2.imwrite(str(out / name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        ts = i / 10.0
        q = Rotation.from_matrix(R_wc).as_quat()
        rgb_lines.append(f"{ts:.6f} {name}")
        gt_lines.append(f"{ts:.6f} " + " ".join(f"{x:.9f}" for x in (*c, *q)))
    (out / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (out / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt_lines) + "\n")
    (out / "calib.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    return out


@pytest.fixture(scope="module")
def box_seq(tmp_path_factory) -> Path:
    return make_box_sequence(tmp_path_factory.mktemp("boxseq") / "seq", num_frames=40)


# --------------------------------------------------------------------------------------------------
# common.py
# --------------------------------------------------------------------------------------------------


def test_load_sequence(box_seq):
    seq = load_sequence(box_seq)
    assert len(seq) == 40 and seq.timestamps.shape == (40,)
    assert all(p.is_file() for p in seq.image_paths)
    assert seq.K.shape == (3, 3) and seq.K[0, 0] == pytest.approx(288.0)
    assert seq.gt_poses.shape == (40, 7)
    assert len(load_sequence(box_seq, max_frames=7)) == 7


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 3.0])
    s, R_est, t = umeyama_sim3(src, dst)
    assert s == pytest.approx(2.5, rel=1e-9)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t, [1.0, -2.0, 3.0], atol=1e-9)


def test_ate_sim3_invariant_to_similarity_and_skips_nan():
    rng = np.random.default_rng(1)
    n = 60
    ts = np.arange(n) / 10.0
    xyz = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    q = Rotation.random(n, random_state=2).as_quat()
    gt = np.concatenate([xyz, q], 1)
    R = Rotation.from_rotvec([0.1, 0.7, -0.3])
    est = gt.copy()
    est[:, :3] = 0.3 * R.apply(xyz) + 5.0
    est[:, 3:] = (R * Rotation.from_quat(q)).as_quat()
    est[[3, 10, 40]] = np.nan
    res = ate_sim3(ts, est, ts, gt)
    assert res["rmse"] < 1e-6
    assert res["num_valid"] == n - 3 and res["num_total"] == n
    assert res["num_pairs"] == n - 3
    noisy = est.copy()
    noisy[:, :3] += 0.3 * 0.1 * rng.normal(size=(n, 3))
    res2 = ate_sim3(ts, noisy, ts, gt)
    assert 0.02 < res2["rmse"] < 0.4
    assert np.isfinite(res2["rmse_percent_of_path"])


# --------------------------------------------------------------------------------------------------
# textbook VO
# --------------------------------------------------------------------------------------------------


def _path_length(gt: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1).sum())


def _relative_rotation_errors_deg(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Angle of (R_est_0^-1 R_est_i)(R_gt_0^-1 R_gt_i)^-1 per frame: checks the quaternion convention (xyzw,
    camera-to-world) independently of the Sim(3) gauge."""
    Re, Rg = Rotation.from_quat(est[:, 3:]), Rotation.from_quat(gt[:, 3:])
    return np.rad2deg(((Re[0].inv() * Re) * (Rg[0].inv() * Rg).inv()).magnitude())


def test_textbook_vo_box_sequence(box_seq):
    out = run_textbook_vo(box_seq)
    seq = load_sequence(box_seq)
    assert out["poses"].shape == (40, 7) and out["timestamps"].shape == (40,)
    assert np.all(np.isfinite(out["poses"]))
    np.testing.assert_allclose(np.linalg.norm(out["poses"][:, 3:], axis=1), 1.0, atol=1e-9)
    assert out["seconds"] > 0 and out["fps"] > 0 and out["cpu_seconds"] > 0
    res = ate_sim3(out["timestamps"], out["poses"], seq.gt_timestamps, seq.gt_poses)
    assert res["num_pairs"] == 40
    # bounded error: a few percent of the ~11 m path; orientations follow GT (checks the xyzw T_wc convention)
    assert res["rmse"] < 0.05 * _path_length(seq.gt_poses), res
    assert np.max(_relative_rotation_errors_deg(out["poses"], seq.gt_poses)) < 3.0


@pytest.mark.slow  # rendering the generator's frames dominates (~10 s of CPU)
def test_textbook_vo_on_generator_driving_loop(tmp_path):
    gen = pytest.importorskip("pvslam_plugins.datasets.synthetic.generator",
                              reason="synthetic generator plugin not importable")
    seq_dir = Path(gen.generate("driving_loop", tmp_path / "dl", num_frames=30, width=320, height=240,
                                progress=False))
    out = run_textbook_vo(seq_dir)
    seq = load_sequence(seq_dir)
    assert out["poses"].shape == (30, 7) and np.all(np.isfinite(out["poses"]))
    res = ate_sim3(out["timestamps"], out["poses"], seq.gt_timestamps, seq.gt_poses)
    assert res["rmse"] < 0.05 * _path_length(seq.gt_poses), res


# --------------------------------------------------------------------------------------------------
# COLMAP (pycolmap is a bench-only dependency)
# --------------------------------------------------------------------------------------------------


def test_colmap_box_sequence(box_seq, tmp_path):
    pytest.importorskip("pycolmap", reason="pycolmap not installed (pip install 'pvslam[bench]')")
    from bench.peers.colmap_peer import run_colmap

    n = 15
    out = run_colmap(box_seq, tmp_path / "colmap", max_frames=n, overlap=5, quadratic_overlap=False,
                     max_num_features=1024, first_octave=0, num_threads=2, max_runtime_s=600.0)
    seq = load_sequence(box_seq, max_frames=n)
    assert out["poses"].shape == (n, 7) and out["timestamps"].shape == (n,)
    assert out["num_frames"] == n
    assert out["num_registered"] >= n - 2
    valid = np.all(np.isfinite(out["poses"]), axis=1)
    assert valid.sum() == out["num_registered"]
    res = ate_sim3(out["timestamps"], out["poses"], seq.gt_timestamps, seq.gt_poses)
    assert res["num_pairs"] == out["num_registered"]
    assert res["rmse"] < 0.02 * _path_length(seq.gt_poses[:n]), res
    assert np.max(_relative_rotation_errors_deg(out["poses"][valid], seq.gt_poses[:n][valid])) < 1.0
    assert (tmp_path / "colmap" / "database.db").is_file()


def test_colmap_rejects_unknown_matching(box_seq, tmp_path):
    pytest.importorskip("pycolmap", reason="pycolmap not installed (pip install 'pvslam[bench]')")
    from bench.peers.colmap_peer import run_colmap

    with pytest.raises(ValueError, match="sequential"):
        run_colmap(box_seq, tmp_path / "c", max_frames=3, matching="vocabtree")
    with pytest.raises(AttributeError, match="no_such_option"):
        run_colmap(box_seq, tmp_path / "c", max_frames=3, max_num_features=64, first_octave=0,
                   mapper_options={"mapper.no_such_option": 1})


def test_textbook_vo_keeps_rotations_through_a_long_loss(box_seq):
    """Blank frames after the box sequence: tracking is lost for good and every frame is extrapolated at constant
    velocity.  The rotations stay rotations (composing them compounded the rounding: on handheld_fast seed 141 the
    peer's poses could not even be written after 174 such frames)."""
    from bench.peers.textbook_vo import TextbookVO

    seq = load_sequence(box_seq)
    vo = TextbookVO(seq.K)
    for path in seq.image_paths:
        vo.process(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    blank = np.full_like(cv2.imread(str(seq.image_paths[0]), cv2.IMREAD_GRAYSCALE), 128)
    for _ in range(400):
        vo.process(blank)
    assert vo.stats["const_velocity"] >= 390
    R = np.stack([T[:, :3] for T in vo.poses_cw])
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    assert np.all(np.isfinite(vo.poses_wc()))
