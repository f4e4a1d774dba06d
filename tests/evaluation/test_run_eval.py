"""evaluate_run recomputes metrics from the files of a run directory."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pvslam_core.evaluation.run_eval import evaluate_run
from pvslam_core.evaluation.trajectory import ate
from pvslam_core.outputs.loops_io import write_loops
from pvslam_core.outputs.metrics import write_json_atomic
from pvslam_core.outputs.panoptic_png import PanopticWriter
from pvslam_core.outputs.trajectory_io import write_tum
from pvslam_core.types import Category, LoopCandidate, PanopticSegmentation, Segment

CATS = [Category(1, "road", False, (128, 64, 128)), Category(2, "car", True, (0, 0, 142))]


def _trajectories(n=60):
    t = np.linspace(0, np.pi, n)
    gt = np.concatenate([np.stack([5 * np.cos(t), np.zeros(n), 5 * np.sin(t)], 1),
                         Rotation.from_euler("y", -t[:, None]).as_quat()], axis=1)
    ts = 0.1 * np.arange(n)
    est = gt.copy()
    est[:, :3] = 0.3 * gt[:, :3] + np.random.default_rng(0).normal(0, 0.01, (n, 3))
    return ts, gt, est


def _seg(t, switch=False):
    ids = np.ones((8, 12), np.int64)
    ids[3:6, t % 8 : t % 8 + 3] = 50 if not (switch and t >= 5) else 51
    return PanopticSegmentation(torch.from_numpy(ids), [Segment(1, 1, False), Segment(int(ids.max()), 2, True)])


def test_evaluate_run_full(tmp_path):
    ts, gt, est = _trajectories()
    write_tum(tmp_path / "trajectory.txt", ts, est)
    write_tum(tmp_path / "groundtruth.txt", ts, gt)
    write_tum(tmp_path / "keyframes.txt", ts[::5], est[::5])
    write_json_atomic(tmp_path / "metrics.json", {"timing": {"fps": 12.5}})
    # keyframes 0..11 are frames 0, 5, ..., 55; loop (kf 10 -> kf 1) = frames (50, 5): true; (kf 6 -> kf 2) false.
    write_loops(tmp_path / "loops.json", [LoopCandidate(10, 1, 0.9, True), LoopCandidate(6, 2, 0.8)],
                keyframe_frame_index=np.arange(0, 60, 5))
    gt_pan = {t: _seg(t) for t in range(10)}
    with PanopticWriter(tmp_path, categories=CATS) as w:
        for t in range(10):
            w.write(t, _seg(t, switch=True))

    m = evaluate_run(tmp_path, panoptic_gt=gt_pan, loop_gt=[(50 + k, 5 + k) for k in range(3)], vpq_ks=(0, 2))
    assert m["ate"]["rmse"] == pytest.approx(ate(ts, est, ts, gt)["rmse"], rel=1e-12)
    assert m["ate"]["scale"] == pytest.approx(1 / 0.3, rel=1e-2)
    assert m["rpe"]["num_pairs"] == 59
    assert m["ate_keyframes"]["num_pairs"] == 12
    assert m["loops"]["num_tp"] == 1 and m["loops"]["num_fp"] == 1 and m["loops"]["recall"] == 1.0
    assert m["panoptic"]["pq"] == 1.0 and m["panoptic"]["num_frames"] == 10
    assert m["panoptic"]["vpq"] < 1.0  # the id switch at frame 5
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["timing"] == {"fps": 12.5}  # kept
    assert saved["ate"]["rmse"] == pytest.approx(m["ate"]["rmse"])
    assert (tmp_path / "plots" / "trajectory_top.png").stat().st_size > 2000
    assert (tmp_path / "plots" / "ate_over_time.png").stat().st_size > 2000


def test_evaluate_run_without_gt_and_with_bad_files(tmp_path):
    ts, gt, est = _trajectories(20)
    write_tum(tmp_path / "trajectory.txt", ts, est)
    m = evaluate_run(tmp_path, plots=False)
    assert m == {} and json.loads((tmp_path / "metrics.json").read_text()) == {}
    # GT given by the caller (tuple), but with timestamps that do not match: an error entry, not an exception.
    m = evaluate_run(tmp_path, gt=(ts + 100.0, gt), plots=False)
    assert "max_diff" in m["ate"]["error"]
    m = evaluate_run(tmp_path, gt={"trajectory": (ts, gt)}, plots=False)
    assert m["ate"]["rmse"] < 0.1
    with pytest.raises(FileNotFoundError):
        evaluate_run(tmp_path / "missing")


def test_evaluate_run_panoptic_at_other_resolution(tmp_path):
    gt_pan = [_seg(t) for t in range(4)]
    with PanopticWriter(tmp_path, categories=CATS) as w:
        for t, g in enumerate(gt_pan):
            big = g.ids.repeat_interleave(2, 0).repeat_interleave(2, 1)
            w.write(t, PanopticSegmentation(big, g.segments))
    m = evaluate_run(tmp_path, panoptic_gt=gt_pan, plots=False)  # categories from segments.json
    assert m["panoptic"]["pq"] == 1.0 and m["panoptic"]["vpq"] == 1.0
    # Without any GT frame in common: an error entry.
    m = evaluate_run(tmp_path, panoptic_gt={100: gt_pan[0]}, plots=False)
    assert "no predicted panoptic frame" in m["panoptic"]["error"]


def test_run_eval_command_line(tmp_path, capsys):
    from pvslam_core.evaluation.run_eval import main

    ts, gt, est = _trajectories(30)
    write_tum(tmp_path / "trajectory.txt", ts, est)
    write_tum(tmp_path / "gt.txt", ts, gt)
    assert main([str(tmp_path), "--gt", str(tmp_path / "gt.txt"), "--no-plots", "--align", "se3"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["ate"]["align"] == "se3"
    assert json.loads((tmp_path / "metrics.json").read_text())["ate"]["rmse"] == pytest.approx(printed["ate"]["rmse"])


def test_a_scale_gap_splits_the_ate(tmp_path):
    """A map whose scale halves after t = 3 s (as after a turn on the spot): with the run's scale gap in metrics.json
    the two parts are also aligned on their own; each fits exactly, with the scales 1/0.3 and 1/0.15."""
    ts, gt, _ = _trajectories()
    est = gt.copy()
    steps = np.diff(gt[:, :3], axis=0) * np.where(ts[1:] > 3.0, 0.15, 0.3)[:, None]  # the step into t > 3 s: new
    est[:, :3] = np.concatenate([[0.3 * gt[0, :3]], 0.3 * gt[0, :3] + np.cumsum(steps, axis=0)])
    write_tum(tmp_path / "trajectory.txt", ts, est)
    write_tum(tmp_path / "groundtruth.txt", ts, gt)
    assert "ate_segments" not in evaluate_run(tmp_path, plots=False)  # no gap on record: one alignment
    gap = {"first_frame": 30, "last_frame": 31, "first_time": 3.0, "last_time": 3.1, "keyframes": 2,
           "unmeasured": 2, "turn_deg": 120.0, "beyond_fov": True}
    narrow = dict(gap, first_time=1.0, turn_deg=20.0, beyond_fov=False)  # not a cut
    write_json_atomic(tmp_path / "metrics.json", {"tracking": {"scale_gaps": [narrow, gap]}})
    m = evaluate_run(tmp_path, plots=False)
    whole, parts = m["ate"], m["ate_segments"]
    assert [p["num_pairs"] for p in parts] == [30, 30]
    assert [(p["start"], p["end"]) for p in parts] == [(0.0, pytest.approx(2.9)), (pytest.approx(3.0), pytest.approx(5.9))]
    assert parts[0]["scale"] == pytest.approx(1 / 0.3, rel=1e-6) and parts[0]["rmse"] < 1e-9
    assert parts[1]["scale"] == pytest.approx(1 / 0.15, rel=1e-6) and parts[1]["rmse"] < 1e-9
    assert whole["rmse"] > 0.1  # one Sim(3) for both parts
    assert json.loads((tmp_path / "metrics.json").read_text())["ate_segments"] == parts
