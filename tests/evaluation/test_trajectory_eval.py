"""ATE / RPE through evo's API, checked against the evo command-line tool on the same files."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pvslam_core.evaluation.trajectory import aligned_positions, ate, ate_from_files, from_evo, rpe, to_evo
from pvslam_core.outputs.trajectory_io import write_tum


def make_gt(n: int = 120, seed: int = 0):
    """A smooth 3D loop-ish trajectory (T_wc) with 10 Hz timestamps."""
    t = np.linspace(0, 2 * np.pi, n)
    xyz = np.stack([10 * np.cos(t), 6 * np.sin(t), 0.5 * np.sin(3 * t)], axis=1)
    yaw = t + np.pi / 2
    rot = Rotation.from_euler("zyx", np.stack([yaw, 0.05 * np.sin(2 * t), 0.02 * np.cos(t)], axis=1))
    ts = 1000.0 + 0.1 * np.arange(n)
    return ts, np.concatenate([xyz, rot.as_quat()], axis=1)


def make_estimate(gt_poses, scale=0.37, seed=1, noise=0.05):
    """GT seen through an unknown similarity plus noise (what a monocular SLAM returns)."""
    rng = np.random.default_rng(seed)
    s_r = Rotation.from_rotvec([0.3, -0.2, 1.1])
    s_t = np.array([4.0, -2.0, 1.0])
    xyz = scale * (s_r.apply(gt_poses[:, :3]) + s_t) + rng.normal(0, noise * scale, gt_poses[:, :3].shape)
    rot = s_r * Rotation.from_quat(gt_poses[:, 3:]) * Rotation.from_rotvec(rng.normal(0, 0.01, (len(gt_poses), 3)))
    return np.concatenate([xyz, rot.as_quat()], axis=1)


def evo_cli(tool: str, gt: Path, est: Path, flags: list[str], tmp: Path) -> dict:
    exe = Path(sys.executable).parent / tool
    if not exe.exists():
        exe = shutil.which(tool)
        if exe is None:
            pytest.skip(f"{tool} command-line tool not installed")
    zip_path = tmp / f"res_{tool}_{'_'.join(f.strip('-') for f in flags)}.zip"
    env = dict(os.environ, HOME=str(tmp), MPLBACKEND="Agg")  # evo writes its settings under ~/.evo
    subprocess.run(
        [str(exe), "tum", str(gt), str(est), *flags, "--save_results", str(zip_path), "--no_warnings"],
        check=True, env=env, capture_output=True, text=True, timeout=120,
    )
    with zipfile.ZipFile(zip_path) as z:
        return json.loads(z.read("stats.json"))


def test_to_evo_quaternion_order():
    ts, poses = make_gt(5)
    traj = to_evo(ts, poses)
    np.testing.assert_array_equal(traj.orientations_quat_wxyz, poses[:, [6, 3, 4, 5]])
    np.testing.assert_array_equal(traj.positions_xyz, poses[:, :3])
    # evo's SE(3) matrices are T_wc: rotation of our xyzw quaternion, translation = camera centre.
    np.testing.assert_allclose(traj.poses_se3[2][:3, :3], Rotation.from_quat(poses[2, 3:]).as_matrix(), atol=1e-12)
    ts2, poses2 = from_evo(traj)
    np.testing.assert_array_equal(ts2, ts)
    np.testing.assert_allclose(poses2, poses, atol=1e-15)


@pytest.mark.parametrize("align, flags", [("sim3", ["-as"]), ("se3", ["-a"]), ("none", [])])
def test_ate_equals_evo_ape_cli(tmp_path, align, flags):
    gt_ts, gt = make_gt()
    est = make_estimate(gt)
    # Estimate at slightly jittered timestamps and missing a few frames: exercises the association too.
    keep = np.ones(len(gt), bool)
    keep[[3, 40, 41, 77]] = False
    est_ts = gt_ts[keep] + np.random.default_rng(5).uniform(-0.004, 0.004, keep.sum())
    est = est[keep]
    write_tum(tmp_path / "gt.txt", gt_ts, gt)
    write_tum(tmp_path / "est.txt", est_ts, est)
    ours = ate_from_files(tmp_path / "est.txt", tmp_path / "gt.txt", align=align)
    cli = evo_cli("evo_ape", tmp_path / "gt.txt", tmp_path / "est.txt", flags, tmp_path)
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours[key] == pytest.approx(cli[key], rel=1e-9, abs=1e-12), key
    assert ours["num_pairs"] == keep.sum()
    # Same numbers straight from arrays (no file round trip: writing is exact).
    direct = ate(est_ts, est, gt_ts, gt, align=align)
    assert direct["rmse"] == pytest.approx(cli["rmse"], rel=1e-9)


def test_rpe_equals_evo_rpe_cli(tmp_path):
    gt_ts, gt = make_gt(80)
    est = make_estimate(gt, scale=1.0, seed=4)
    write_tum(tmp_path / "gt.txt", gt_ts, gt)
    write_tum(tmp_path / "est.txt", gt_ts, est)
    ours = rpe(gt_ts, est, gt_ts, gt, delta=3, align="se3")
    cli_t = evo_cli("evo_rpe", tmp_path / "gt.txt", tmp_path / "est.txt", ["-a", "--delta", "3"], tmp_path)
    cli_r = evo_cli(
        "evo_rpe", tmp_path / "gt.txt", tmp_path / "est.txt", ["-a", "--delta", "3", "-r", "angle_deg"], tmp_path
    )
    assert ours["trans_rmse"] == pytest.approx(cli_t["rmse"], rel=1e-9)
    assert ours["rot_rmse"] == pytest.approx(cli_r["rmse"], rel=1e-9)
    assert ours["num_pairs"] == 79 // 3  # evo: consecutive (non-overlapping) pairs 3 frames apart


def test_ate_recovers_similarity_and_reports_path():
    gt_ts, gt = make_gt()
    est = make_estimate(gt, scale=0.25, noise=0.0)
    r = ate(gt_ts, est, gt_ts, gt, align="sim3")
    assert r["rmse"] < 1e-9
    assert r["scale"] == pytest.approx(4.0, rel=1e-9)
    seg = np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1).sum()
    assert r["path_length"] == pytest.approx(seg)
    assert r["rmse_percent_of_path"] == pytest.approx(100 * r["rmse"] / seg)
    # SE3 alignment cannot fix the scale.
    assert ate(gt_ts, est, gt_ts, gt, align="se3")["rmse"] > 1.0
    assert ate(gt_ts, est, gt_ts, gt, align="se3")["scale"] == 1.0


def test_ate_does_not_modify_inputs_and_handles_torch_and_nan():
    torch = pytest.importorskip("torch")
    gt_ts, gt = make_gt(50)
    est = make_estimate(gt)
    est_copy, gt_copy = est.copy(), gt.copy()
    r1 = ate(gt_ts, est, gt_ts, gt)
    np.testing.assert_array_equal(est, est_copy)
    np.testing.assert_array_equal(gt, gt_copy)
    r2 = ate(torch.tensor(gt_ts), torch.tensor(est), torch.tensor(gt_ts), torch.tensor(gt))
    assert r1["rmse"] == r2["rmse"]
    est_nan = est.copy()
    est_nan[[5, 6]] = np.nan
    r3 = ate(gt_ts, est_nan, gt_ts, gt)
    assert r3["num_invalid_est"] == 2 and r3["num_pairs"] == 48


def test_aligned_positions_for_plots():
    gt_ts, gt = make_gt(60)
    est = make_estimate(gt)
    r = aligned_positions(gt_ts, est, gt_ts, gt)
    assert r["est_xyz"].shape == r["gt_xyz"].shape == (60, 3)
    np.testing.assert_allclose(r["errors"], np.linalg.norm(r["est_xyz"] - r["gt_xyz"], axis=1), atol=1e-12)
    np.testing.assert_allclose(r["gt_xyz"], gt[:, :3])
    assert np.sqrt(np.mean(r["errors"] ** 2)) == pytest.approx(ate(gt_ts, est, gt_ts, gt)["rmse"], rel=1e-12)


def test_ate_errors_are_clear():
    gt_ts, gt = make_gt(10)
    with pytest.raises(ValueError, match="max_diff"):
        ate(gt_ts + 100.0, gt, gt_ts, gt)
    with pytest.raises(ValueError, match="at least 3"):
        ate(gt_ts[:2], gt[:2], gt_ts, gt)
    with pytest.raises(ValueError, match="align must be"):
        ate(gt_ts, gt, gt_ts, gt, align="sim2")


def test_ate_straight_line_ground_truth():
    """evo refuses a rank-deficient covariance (straight GT); the Umeyama optimum is still well defined."""
    ts = 0.1 * np.arange(30)
    gt = np.zeros((30, 7))
    gt[:, 6] = 1.0
    gt[:, 2] = np.arange(30)  # driving straight along z
    est = gt.copy()
    est[:, :3] = 0.5 * gt[:, [1, 2, 0]] + [1.0, -2.0, 3.0]  # straight along y, half scale
    r = ate(ts, est, ts, gt, align="sim3")
    assert r["rmse"] < 1e-9 and r["scale"] == pytest.approx(2.0)
    # SE3 cannot fix the scale: errors 0.5 |z - mean z|.
    z = np.arange(30.0)
    assert ate(ts, est, ts, gt, align="se3")["rmse"] == pytest.approx(np.sqrt(np.mean((0.5 * (z - z.mean())) ** 2)))
    frozen = est.copy()
    frozen[:, :3] = 0.0
    with pytest.raises(ValueError, match="all identical"):
        ate(ts, frozen, ts, gt)
