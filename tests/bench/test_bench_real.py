"""Tests of bench/bench_real.py's logic on tiny fake inputs (no pvslam run, no ORB-SLAM3): the scores against an
independent Sim(3) alignment, frames posed, ORB-SLAM3's timestamps, the table's ranges and notes, the vocabulary
options and the note when the ORB-SLAM3 peer cannot run."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_real, matrix_jobs  # noqa: E402


def _gt(n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A curved drive at 10 Hz: positions along an arc, heading along the path."""
    ts = np.arange(n) / 10.0
    a = np.linspace(0.0, 1.2, n)
    pos = np.stack([20 * np.sin(a), 0.1 * np.sin(5 * a), 20 * (1 - np.cos(a))], 1)
    q = Rotation.from_euler("y", -a[:, None]).as_quat()
    return ts, np.concatenate([pos, q], 1)


def _similar(poses: np.ndarray, s: float, rotvec, t) -> np.ndarray:
    R = Rotation.from_rotvec(rotvec)
    out = poses.copy()
    out[:, :3] = s * R.apply(poses[:, :3]) + np.asarray(t)
    out[:, 3:] = (R * Rotation.from_quat(poses[:, 3:])).as_quat()
    return out


def test_a_similar_copy_of_the_ground_truth_scores_zero_and_an_offset_scores_its_size():
    ts, gt = _gt()
    est = _similar(gt, 0.3, [0.1, -0.4, 0.2], [5.0, -1.0, 2.0])  # another scale, rotation and origin
    s = bench_real.score(ts, est, ts, gt, total=len(ts))
    assert s["ate_m"] < 1e-6 and s["rpe_t_m"] < 1e-6 and s["rpe_r_deg"] < 1e-4
    assert s["posed"] == s["total"] == len(ts)
    assert s["path_m"] == pytest.approx(np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1).sum())
    # a lateral error of +-0.5 m on alternate frames: ATE 0.5 m (the alignment cannot absorb it), RPE 1 m per frame
    noisy = gt.copy()
    a = np.linspace(0, 1.2, len(ts))
    normal = np.stack([np.sin(a), np.zeros(len(ts)), -np.cos(a)], 1)
    noisy[:, :3] += 0.5 * normal * np.where(np.arange(len(ts)) % 2 == 0, 1.0, -1.0)[:, None]
    s = bench_real.score(ts, noisy, ts, gt, total=len(ts))
    assert s["ate_m"] == pytest.approx(0.5, rel=0.05)
    assert s["ate_pct"] == pytest.approx(100 * s["ate_m"] / s["path_m"])
    assert s["rpe_t_m"] == pytest.approx(1.0, rel=0.05)


def test_frames_that_are_not_posed_count_and_too_few_poses_give_no_score():
    ts, gt = _gt()
    est = gt.copy()
    est[:10] = np.nan  # not initialised yet
    s = bench_real.score(ts, est, ts, gt, total=len(ts))
    assert s["posed"] == len(ts) - 10 and s["ate_m"] < 1e-6
    # a method returning only some frames (ORB-SLAM3's largest map): the missing rows are simply absent
    s = bench_real.score(ts[15:], gt[15:], ts, gt, total=len(ts))
    assert (s["posed"], s["total"]) == (len(ts) - 15, len(ts))
    s = bench_real.score(ts[:2], gt[:2], ts, gt, total=len(ts))
    assert math.isnan(s["ate_m"]) and "nothing to align" in s["error"] and s["posed"] == 2
    assert bench_real.score(ts, est, ts, gt, total=len(ts), posed=7)["posed"] == 7  # pvslam's count less failures


def test_pvslam_is_scored_on_the_frames_another_method_posed():
    """An estimate that is exact on frames 20-39 and off by a growing drift before: scored over every frame it has an
    error, over the frames a peer posed (20-39, within the timestamp tolerance) none; frames outside it do not count."""
    ts, gt = _gt()
    est = _similar(gt, 0.5, [0.0, 0.3, 0.0], [1.0, 0.0, 0.0])
    est[:20, :3] += np.linspace(2.0, 0.0, 20)[:, None] * np.array([0.0, 0.0, 1.0])
    res = {"ts": ts, "poses": est}
    assert bench_real.score(ts, est, ts, gt, total=len(ts))["ate_m"] > 0.1
    peer_ts = ts[20:] + 0.004  # a peer's timestamps, slightly off (times.txt against frame / fps)
    s = bench_real.on_frames(res, peer_ts, ts, gt, total=len(ts))
    assert s["ate_m"] < 1e-6 and (s["posed"], s["total"]) == (20, len(ts))
    assert s["path_m"] == pytest.approx(np.linalg.norm(np.diff(gt[20:, :3], axis=0), axis=1).sum())
    assert math.isnan(bench_real.on_frames(res, ts[:2], ts, gt, total=len(ts))["ate_m"])  # too few to align


def _extrapolated_start(n: int = 40, k: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """A drive whose first ``k`` + 1 poses lie on a constant-velocity line (KITTI's extrapolated start), measured
    after: the yaw increments then change by 0.02-0.2 deg from frame to frame."""
    rng = np.random.default_rng(0)
    inc = np.full(n - 1, -0.12)
    inc[k:] += rng.uniform(0.02, 0.2, n - 1 - k) * rng.choice([-1, 1], n - 1 - k)
    yaw = np.radians(np.concatenate([[0.0], np.cumsum(inc)]))
    R = Rotation.from_euler("y", yaw[:, None])
    pos = np.cumsum(R.apply(np.array([0.0, 0.0, 0.86])), 0)
    return np.arange(n) / 10.0, np.concatenate([pos, R.as_quat()], 1)


def test_an_extrapolated_start_of_the_ground_truth_is_found_and_scored_apart():
    ts, gt = _extrapolated_start(k=10)
    assert matrix_jobs.measured_from(gt) == 11  # increments 0-9 equal: frames 0-10 on the line
    assert matrix_jobs.measured_from(_extrapolated_start(k=4)[1]) == 5  # three repeats of the first increment
    assert matrix_jobs.measured_from(_extrapolated_start(k=3)[1]) == 0  # two may be chance
    assert matrix_jobs.measured_from(_extrapolated_start(k=0)[1]) == 0
    assert matrix_jobs.measured_from(_extrapolated_start(k=39)[1]) == 0  # steady all along: nothing to tell apart
    _, gt_real = _gt()
    assert matrix_jobs.measured_from(gt_real) == 0  # a curve whose rate changes
    # an estimate that follows another motion on the extrapolated frames and the truth after them
    est = _similar(gt, 0.4, [0.0, 0.2, 0.0], [1.0, 0.0, 2.0])
    est[:11, :3] += np.linspace(1.0, 0.0, 11)[:, None] * np.array([0.3, 0.0, 0.0])
    s = bench_real.score(ts, est, ts, gt, total=len(ts), first=11)
    assert s["ate_m"] < 1e-6 and s["rpe_t_m"] < 1e-6 and s["ate_all_m"] > 0.05 and s["first"] == 11
    assert s["posed"] == s["total"] == len(ts)
    full = bench_real.score(ts, est, ts, gt, total=len(ts))
    assert full["ate_m"] == full["ate_all_m"] == pytest.approx(s["ate_all_m"])
    on = bench_real.on_frames({"ts": ts, "poses": est}, ts[5:], ts, gt, total=len(ts), first=11)
    assert on["ate_m"] < 1e-6 and on["ate_all_m"] > 0.05


def test_orb_timestamps_map_to_the_sequence_timestamps():
    seq_ts = np.array([0.0, 0.1036, 0.2072, 0.3108])  # times.txt, not exactly 10 Hz
    assert np.allclose(bench_real.orb_timestamps(np.array([0.1, 0.3]), seq_ts), [0.1036, 0.3108])
    with pytest.raises(ValueError, match="frame 4 of a 4-frame"):
        bench_real.orb_timestamps(np.array([0.4]), seq_ts)


def test_the_table_shows_ranges_over_runs_and_notes_for_skipped_peers():
    def run(ate, posed, cpu, ate_all=None):
        return {"ate_m": ate, "ate_pct": ate, "ate_all_m": ate if ate_all is None else ate_all, "rpe_t_m": 0.01,
                "rpe_r_deg": 0.1, "posed": posed, "total": 160, "cpu_ms_per_frame": cpu, "first": 14}
    rows = [{"sequence": "00", "method": "pvslam", "runs": [run(0.5, 160, 900.0, 0.7)]},
            {"sequence": "00", "method": "orbslam3", "runs": [run(0.39, 119, 60.0), run(0.54, 159, 70.0)],
             "attempted": 3},
            {"sequence": "06", "method": "orbslam3", "runs": [], "note": "no --orb-vocab for this sequence"}]
    lines = bench_real.table(rows)
    assert lines[0].startswith("| sequence | method | runs | scored from | ATE m | ATE % | ATE m, all frames |")
    assert "| 00 | pvslam | 1 | frame 14 | 0.500 | 0.50 | 0.700 | 0.010 | 0.100 | 160 / 160 | 900 |" in lines
    assert "| 00 | orbslam3 | 2 of 3 | frame 14 | 0.390-0.540 | 0.39-0.54 | 0.390-0.540 | 0.010 | 0.100 | " \
           "119-159 / 160 | 60-70 |" in lines
    assert any("| 06 | orbslam3 | 0 | | no --orb-vocab" in line for line in lines)
    assert bench_real.run_details(rows) == ["00 orbslam3, each run: 0.390 m = 0.39 % (all frames 0.390 m; 119/160 "
                                            "frames), 0.540 m = 0.54 % (all frames 0.540 m; 159/160 frames)"]


def test_vocabulary_options_per_sequence_and_the_note_when_orb_slam3_cannot_run(tmp_path):
    specs = ["00=/v/a.txt", "/v/b.txt"]
    assert bench_real.vocab_for(specs, "00") == "/v/a.txt" and bench_real.vocab_for(specs, "06") == "/v/b.txt"
    assert bench_real.vocab_for(["00=/v/a.txt"], "01") is None
    runner = tmp_path / "orbslam3_traj.py"
    assert "no --orb-python" in bench_real.orb_missing(None, "/v/a.txt", runner)
    assert "no such file" in bench_real.orb_missing(str(tmp_path / "nope"), "/v/a.txt", runner)
    # this test's own python lacks pyorbslam3: said plainly, not a traceback
    note = bench_real.orb_missing(sys.executable, "/v/a.txt", runner)
    assert note is not None and "cannot run the ORB-SLAM3 runner" in note and "pyorbslam3" in note


def test_where_orb_slam3_lives_comes_from_the_environment_when_not_given(tmp_path, monkeypatch, capsys):
    """figures.py runs the tool without options: the ORB-SLAM3 python and vocabularies come from the environment,
    and options given on the command line win."""
    seen = {}

    def fake_bench(seq, out, args, vocab):
        seen[seq] = (args.orb_python, vocab)
        return []

    monkeypatch.setattr(bench_real, "bench_sequence", fake_bench)
    monkeypatch.setenv("PVSLAM_ORB_PYTHON", "/orb/bin/python")
    monkeypatch.setenv("PVSLAM_ORB_VOCAB", "00=/v/a.txt" + __import__("os").pathsep + "/v/b.txt")
    out = tmp_path / "real.json"
    assert bench_real.main(["--sequences", "00", "06", "--json", str(out)]) == 0
    assert seen == {"00": ("/orb/bin/python", "/v/a.txt"), "06": ("/orb/bin/python", "/v/b.txt")}
    assert bench_real.main(["--sequences", "06", "--orb-vocab", "/v/c.txt", "--json", str(out)]) == 0
    assert seen["06"] == ("/orb/bin/python", "/v/c.txt")


def test_pvslam_runs_at_its_size_and_two_percent_either_side():
    from pvslam_core.datasets.base import MAX_PIXELS

    assert bench_real.size_variants(0) == [("", [])]
    tags = bench_real.size_variants(2.0)
    assert [t for t, _ in tags] == ["", "_smaller", "_larger"]
    areas = [int(a[1].split("=")[1]) for _, a in tags[1:]]
    assert areas == [round(MAX_PIXELS * 0.98 ** 2), round(MAX_PIXELS * 1.02 ** 2)]
    assert all(a[0] == "--set" and a[1].startswith("dataset.max_pixels=") for _, a in tags[1:])


def test_a_sequence_row_holds_every_pvslam_size_and_each_is_scored_on_orb_slam3s_frames(tmp_path, monkeypatch):
    """Three pvslam runs (the sizes) and two ORB-SLAM3 runs: the pvslam row has three runs labelled by size, the
    same-frames row one score per (pvslam run, ORB-SLAM3 run), each over that ORB-SLAM3 run's frames only."""
    ts, gt = _gt()
    drift = {"": 0.0, "_smaller": 1.0, "_larger": 2.0}

    def fake_pvslam(seq, out, timeout, extra=(), tag=""):
        assert list(extra[-2:]) == ["--set", "graph.edges.active_window=16"]  # the variant, on every size
        est = gt.copy()
        est[:, 1] += drift[tag] * np.linspace(0, 1, len(ts)) ** 2  # a bend, not removable by a similarity
        return {"ts": ts, "poses": est, "posed": len(ts), "cpu_s": 1.0}

    orbs = iter([{"ts": ts[10:], "poses": gt[10:], "cpu_s": 0.5}, {"ts": ts[:25], "poses": gt[:25], "cpu_s": 0.5}])
    monkeypatch.setattr(bench_real, "kitti_as_tum", lambda seq, out: tmp_path)
    monkeypatch.setattr(bench_real, "read_gt", lambda d: (ts, gt))
    monkeypatch.setattr(bench_real, "run_pvslam", fake_pvslam)
    monkeypatch.setattr(bench_real, "orb_missing", lambda *a: None)
    monkeypatch.setattr(bench_real, "run_orb", lambda *a: next(orbs))
    monkeypatch.setattr(bench_real, "run_vo", lambda d: {"ts": ts, "poses": gt, "cpu_s": 0.1})

    class Args:
        timeout, orb_runs, orb_python, size_spread = 10.0, 2, "py", 2.0
        overrides = ["graph.edges.active_window=16"]

    rows = {r["method"]: r for r in bench_real.bench_sequence("00", tmp_path, Args, "voc")}
    pv = rows["pvslam"]["runs"]
    assert [r["size"] for r in pv] == ["default", "smaller", "larger"]
    assert pv[0]["ate_m"] < 1e-6 < pv[1]["ate_m"] < pv[2]["ate_m"]
    same = rows[bench_real.SAME_FRAMES]["runs"]
    assert [(r["orb_run"], r["size"]) for r in same] == [(0, "default"), (0, "smaller"), (0, "larger"),
                                                         (1, "default"), (1, "smaller"), (1, "larger")]
    assert [r["posed"] for r in same] == [30, 30, 30, 25, 25, 25]
    assert "size smaller; ORB-SLAM3 run 1" in " ".join(bench_real.run_details(list(rows.values())))
