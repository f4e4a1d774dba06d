"""`pvslam eval RUN_DIR --gt FILE`: ground truth a user brings to a finished run (TUM by timestamp, KITTI poses by
frame), written as the run's groundtruth.txt; files that cannot describe the run are errors that say why."""
from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from pvslam_core.api import evaluate_run_dir
from pvslam_core.cli import main
from pvslam_core.evaluation.user_gt import load_user_groundtruth, sniff_format
from pvslam_core.outputs.trajectory_io import TrajectoryFormatError, read_tum, write_kitti, write_tum


def _without_gt(copy):
    ts, poses = read_tum(copy / "groundtruth.txt")
    (copy / "groundtruth.txt").unlink()
    return ts, poses


def test_a_tum_file_gives_the_runs_own_figures(archived_run, fake_registry, tmp_path):
    copy, original = archived_run
    ts, poses = _without_gt(copy)
    assert "ate" not in evaluate_run_dir(copy, registry=fake_registry)  # nothing to compare with any more
    write_tum(tmp_path / "mocap.txt", ts, poses)
    m = evaluate_run_dir(copy, registry=fake_registry, gt=tmp_path / "mocap.txt")
    assert m["ate"]["rmse"] == pytest.approx(original["ate"]["rmse"], rel=1e-9)
    assert m["rpe"]["trans_rmse"] == pytest.approx(original["rpe"]["trans_rmse"], rel=1e-9)
    assert "TUM" in m["evaluation_sources"]["trajectory"] and "mocap.txt" in m["evaluation_sources"]["trajectory"]
    assert (copy / "groundtruth.txt").is_file()  # later evaluations and exports find it
    assert json.loads((copy / "metrics.json").read_text())["evaluation_sources"]["trajectory"].startswith(
        str(tmp_path / "mocap.txt"))


def test_a_kitti_pose_file_is_matched_by_frame(archived_run, fake_registry, tmp_path):
    copy, original = archived_run
    ts, poses = _without_gt(copy)
    write_kitti(tmp_path / "00.txt", poses)  # no timestamps: line i is frame i
    m = evaluate_run_dir(copy, registry=fake_registry, gt=tmp_path / "00.txt")
    assert m["ate"]["rmse"] == pytest.approx(original["ate"]["rmse"], rel=1e-6)
    assert "KITTI" in m["evaluation_sources"]["trajectory"]
    # a pose file of another, shorter input
    write_kitti(tmp_path / "short.txt", poses[:5])
    with pytest.raises(ValueError, match="5 KITTI poses, but the run read 12 frames"):
        evaluate_run_dir(copy, registry=fake_registry, gt=tmp_path / "short.txt")


def test_kitti_lines_follow_the_runs_start_and_stride(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"dataset": {"plugin": "images", "start": 3, "stride": 2}}))
    write_tum(run / "trajectory.txt", np.arange(4) * 0.2, np.tile([0, 0, 0, 0, 0, 0, 1.0], (4, 1)))
    poses = np.zeros((12, 7))
    poses[:, 0] = np.arange(12)  # x = the line's index
    poses[:, 6] = 1.0
    write_kitti(tmp_path / "gt.txt", poses)
    ts, got, what = load_user_groundtruth(tmp_path / "gt.txt", run)
    assert got[:, 0].tolist() == [3, 5, 7, 9] and ts.tolist() == pytest.approx([0, 0.2, 0.4, 0.6])
    assert "line 3 + 2 i" in what
    write_kitti(tmp_path / "gt9.txt", poses[:9])  # frame 3 of the run would be line 9
    with pytest.raises(ValueError, match="input frames 3 to 9, stride 2"):
        load_user_groundtruth(tmp_path / "gt9.txt", run)


def test_files_that_cannot_describe_the_run_are_clear_errors(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    write_tum(run / "trajectory.txt", np.arange(10) * 0.1, np.tile([0, 0, 0, 0, 0, 0, 1.0], (10, 1)))
    write_tum(tmp_path / "later.txt", 100 + np.arange(10) * 0.1, np.tile([0, 0, 0, 0, 0, 0, 1.0], (10, 1)))
    with pytest.raises(ValueError, match="0 of the run's 10 frames .* do not share a time base"):
        load_user_groundtruth(tmp_path / "later.txt", run)
    (tmp_path / "euroc.csv").write_text("#timestamp,p_x\n" + ",".join(["1403636579758555392"] + ["0"] * 16) + "\n")
    with pytest.raises(TrajectoryFormatError, match="17 values.*EuRoC"):
        sniff_format(tmp_path / "euroc.csv")
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    with pytest.raises(TrajectoryFormatError, match="no poses"):
        sniff_format(tmp_path / "empty.txt")
    with pytest.raises(FileNotFoundError, match="ground-truth file not found"):
        sniff_format(tmp_path / "missing.txt")


def test_the_cli_names_the_file_and_fails_cleanly(archived_run, fake_registry, monkeypatch, tmp_path,
                                                  capsys):
    from pvslam_core import registry as r

    copy, original = archived_run
    ts, poses = _without_gt(copy)
    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    write_kitti(tmp_path / "poses.txt", poses)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["eval", str(copy), "--gt", str(tmp_path / "poses.txt")]) == 0
    assert json.loads(buf.getvalue())["ate"]["rmse"] == pytest.approx(original["ate"]["rmse"], rel=1e-6)
    assert "poses.txt (KITTI poses" in capsys.readouterr().err
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    assert main(["eval", str(copy), "--gt", str(tmp_path / "bad.txt")]) != 0
    assert "bad.txt:1: 3 values" in capsys.readouterr().err
