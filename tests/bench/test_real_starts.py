"""Tests of bench/real_starts.py on a tiny fake KITTI excerpt (no pvslam run, no ORB-SLAM3): the frame links from a
start, ORB-SLAM3's frame numbers read from the start on, and the best / median comparison."""
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

from bench import bench_real, matrix_jobs, real_starts  # noqa: E402

N = 30


def _fake_kitti(root: Path) -> np.ndarray:
    """An excerpt "00" of N frames on a curve (KITTI layout); returns its poses [N, 3, 4]."""
    seq = root / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    for i in range(N):
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), np.full((8, 8), i, np.uint8))
    (seq / "calib.txt").write_text("P0: 700 0 600 0 0 700 180 0 0 0 1 0\n")
    a = 1.5 * np.linspace(0.0, 1.0, N) ** 2  # a tightening curve: no stretch of it is a similar copy of another
    poses = np.zeros((N, 3, 4))
    poses[:, :, :3] = Rotation.from_euler("y", -a[:, None]).as_matrix()
    poses[:, :, 3] = np.stack([30 * np.sin(a), 0.2 * np.sin(4 * a), 30 * (1 - np.cos(a))], 1)
    (root / "poses").mkdir()
    np.savetxt(root / "poses" / "00.txt", poses.reshape(N, 12))
    return poses


@pytest.fixture
def kitti(tmp_path, monkeypatch):
    root = tmp_path / "kitti"
    poses = _fake_kitti(root)
    for mod in (matrix_jobs, bench_real, real_starts):
        monkeypatch.setattr(mod, "KITTI", root)
    return poses


def _tum(rows: np.ndarray, ts: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(rows[:, :, :3]).as_quat()
    return np.concatenate([ts[:, None], rows[:, :, 3], q], 1)


def test_the_frame_folder_holds_the_frames_from_the_start_and_a_start_past_the_end_is_refused(kitti, tmp_path):
    folder = real_starts.frames_from("00", 5, tmp_path / "out")
    names = sorted(p.name for p in folder.iterdir())
    assert names[0] == "000005.png" and len(names) == N - 5
    assert real_starts.frames_from("00", 10, tmp_path / "out").name != folder.name
    with pytest.raises(ValueError, match="start frame 29: excerpt 00 has 30 frames"):
        real_starts.frames_from("00", 29, tmp_path / "out")


def test_orb_slam3_from_a_later_start_is_scored_against_the_frames_it_saw(kitti, tmp_path, monkeypatch):
    """ORB-SLAM3's runner numbers the frames of its folder from 0: a run from frame 8 that is exact (up to a
    similarity) scores ~0 only when its frame k is read as frame 8 + k; pvslam's run (global frame numbers, 5 cm
    off) is scored over the same frames, and both counts are of the frames from the start on."""
    first = 8
    ts_all = np.arange(N) / 10.0

    def fake_child(cmd, log, timeout):  # ORB-SLAM3: writes the exact poses of the folder's frames, numbered from 0
        out = Path(cmd[cmd.index("--out") + 1])
        assert sorted(p.name for p in Path(cmd[2]).iterdir())[0] == f"{first:06d}.png"
        k = np.arange(N - first - 2)  # it lost the last two frames
        est = _tum(kitti[first + k], k / 10.0)
        est[:, 1:4] = 0.5 * est[:, 1:4] + 3.0  # another scale and origin
        np.savetxt(out, est)
        return 0, 1.0, 1.0, "tracked=20/22 saved=20 vocab_load_s=0.1"

    def fake_pvslam(seq, out, timeout, extra, tag):
        assert extra == ["--set", f"dataset.start={first}"] and tag == f"_from{first}"
        est = _tum(kitti[first:], ts_all[first:])
        est[:, 2] += 0.05 * (-1.0) ** np.arange(len(est))  # +-5 cm up and down, frame to frame
        return {"ts": est[:, 0], "poses": est[:, 1:], "posed": N - first, "cpu_s": 2.0}

    monkeypatch.setattr(bench_real, "run_child", fake_child)
    monkeypatch.setattr(bench_real, "run_pvslam", fake_pvslam)
    monkeypatch.setattr(bench_real, "orb_missing", lambda *a: None)
    args = type("A", (), {"orb_runs": 2, "orb_python": "py", "timeout": 10.0})()
    seq_dir = matrix_jobs.kitti_as_tum("00", tmp_path / "out" / "peers")
    gt = matrix_jobs.read_gt(seq_dir)
    row = real_starts.bench_start("00", first, tmp_path / "out", args, "voc.txt", seq_dir, gt)
    assert row["pvslam"]["ate_m"] == pytest.approx(0.05, rel=0.1) and row["pvslam"]["total"] == N - first
    assert [r["ate_m"] < 1e-6 for r in row["orbslam3"]] == [True, True]
    assert [r["posed"] for r in row["orbslam3"]] == [N - first - 2] * 2
    assert row["pvslam_on_orb"] == pytest.approx([0.05, 0.05], rel=0.1)
    assert row["ahead"] == {"best": False, "median": False}
    # the same ORB-SLAM3 run read as if it had started at frame 0 lands on the wrong frames
    wrong = bench_real.run_orb("00", seq_dir, "py", "voc.txt", 0, tmp_path / "out", 10.0,
                               real_starts.frames_from("00", first, tmp_path / "out"), 0, "_wrong")
    assert bench_real.evaluate("orbslam3", wrong, gt[0], gt[1], N)["ate_m"] > 0.1


def test_best_and_median_comparisons_and_the_summary_line():
    # ORB-SLAM3 runs 0.30 / 0.20 / 0.50 m; pvslam on their frames 0.25 / 0.22 / 0.24 m
    assert real_starts.compare([0.25, 0.22, 0.24], [0.30, 0.20, 0.50]) == {"best": False, "median": True}
    assert real_starts.compare([0.25, 0.19, 0.40], [0.30, 0.20, 0.50]) == {"best": True, "median": True}
    assert real_starts.compare([0.40, 0.35, 0.45], [0.30, 0.20, 0.50]) == {"best": False, "median": False}
    assert real_starts.compare([float("nan")], [float("nan")]) == {"best": None, "median": None}
    pv = {"ate_m": 0.2, "total": 30, "first": 14}
    orb = [{"ate_m": 0.3, "posed": 28}]
    rows = [{"sequence": "00", "start": s, "pvslam": pv, "orbslam3": orb, "pvslam_on_orb": [v],
             "ahead": real_starts.compare([v], [0.3])} for s, v in ((0, 0.4), (5, 0.1))]
    text = real_starts.lines(rows)
    assert "| 00 | 0 | frame 14 | 0.200 | 0.400 | 0.300 | 28 / 30 | no / no |" in text
    assert "| 00 | 5 | frame 14 | 0.200 | 0.100 | 0.300 | 28 / 30 | yes / yes |" in text
    assert text[-1] == "00: pvslam at or below ORB-SLAM3's best run from 1 of 2 starts, its median run from 1 of 2"
