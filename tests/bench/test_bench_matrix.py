"""Tests of the benchmark matrix (bench/bench_matrix.py, bench/matrix_jobs.py): the seed sets of the ledger, which frames count
as posed, the straight-line baseline against an independent Sim(3) alignment, the KITTI excerpt as a TUM folder,
the target verdicts, the map at initialisation against the ground truth, and (slow) one real cell end to end."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_matrix, matrix_jobs  # noqa: E402
from bench.peers.common import ate_sim3, load_sequence  # noqa: E402


def test_seed_sets_come_from_the_ledger_and_every_seed_is_classified():
    sets = bench_matrix.SEED_SETS
    assert not set(sets["tune"]) & set(sets["report"]) and 0 in sets["default"]
    assert not set(sets["default"]) & (set(sets["tune"]) | set(sets["report"]))
    assert len(sets["report"]) >= 3
    assert bench_matrix.seed_set_of(4) == "report" and bench_matrix.seed_set_of(1) == "tune"
    fresh = bench_matrix.LEDGER.fresh(1)[0]
    assert bench_matrix.seed_set_of(fresh) == "fresh" and bench_matrix.seed_set_of(12) == "used"
    assert not set(bench_matrix.USED_SEEDS) & {s for v in sets.values() for s in v}
    assert [c["set"] for c in bench_matrix.plan(["driving_loop"], [3, 12, fresh], None, Path("."), False, False, 1)] \
        == ["report", "used", "fresh"]


def test_plan_has_every_scenario_and_seed_and_kitti_once(tmp_path):
    cells = bench_matrix.plan(["driving_loop", "busy_street", "kitti_06"], [3, 4], None, tmp_path, False, False, 1)
    keys = sorted((c["scenario"], c["seed"]) for c in cells if c["seed"] is not None)
    assert keys == [("busy_street", 3), ("busy_street", 4), ("driving_loop", 3), ("driving_loop", 4)]
    assert [c["set"] for c in cells if c["scenario"] == "kitti_06"] == ["shared"]
    assert cells[0]["scenario"] == "driving_loop"  # longest first


def test_posed_frames_follow_fragments_and_failures():
    T, F = True, False
    # initialises at frame 2 (frames 0-1 placed retroactively), re-initialises at frame 4 and never again
    np.testing.assert_array_equal(matrix_jobs.posed_frames([F, F, T, T, F, F], [F] * 6), [1, 1, 1, 1, 0, 0])
    # a failed frame carries a prediction; the second fragment initialises
    np.testing.assert_array_equal(matrix_jobs.posed_frames([F, T, T, F, F, T], [F, F, T, F, F, F]),
                                  [1, 1, 0, 1, 1, 1])
    assert not matrix_jobs.posed_frames([F, F, F], [F, F, F]).any()


def test_line_baseline_is_the_best_aligned_constant_velocity_line():
    rng = np.random.default_rng(0)
    ts = np.arange(40) / 10.0
    gt = np.zeros((40, 7))
    gt[:, 6] = 1.0
    gt[:, :3] = np.stack([2.0 * ts, 0.3 * np.sin(ts), 0.1 * ts ** 2], 1) + rng.normal(0, 0.01, (40, 3))
    got = matrix_jobs.line_baseline(ts, gt)
    # independent: a collinear constant-speed estimate, Sim(3)-aligned by Umeyama
    est = np.zeros((40, 7))
    est[:, 6] = 1.0
    est[:, 2] = ts
    ref = ate_sim3(ts, est, ts, gt)
    assert got["ate_m"] == pytest.approx(ref["rmse"], rel=1e-6)
    gt[:, :3] = np.outer(ts, [1.0, 2.0, 0.5]) + [3.0, -1.0, 0.0]  # exactly a line
    assert matrix_jobs.line_baseline(ts, gt)["ate_m"] < 1e-9


def test_kitti_excerpt_as_a_tum_folder(shared_dir, tmp_path, monkeypatch):
    kitti = shared_dir / "data" / "kitti-odometry"
    monkeypatch.setattr(matrix_jobs, "KITTI", kitti)
    root = matrix_jobs.kitti_as_tum("06", tmp_path)
    seq = load_sequence(root)
    assert len(seq) == 51 and seq.image_paths[3].is_file()
    assert seq.intrinsics[0] == pytest.approx(707.0912) and seq.intrinsics[2] == pytest.approx(601.8873)
    raw = np.loadtxt(kitti / "poses" / "06.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(seq.gt_poses[:, :3], raw[:, :, 3], atol=1e-8)
    times = np.loadtxt(kitti / "sequences" / "06" / "times.txt")
    np.testing.assert_allclose(seq.timestamps, times, atol=1e-6)
    root01 = matrix_jobs.kitti_as_tum("01", tmp_path)  # no times.txt: 10 Hz like the kitti reader
    np.testing.assert_allclose(load_sequence(root01).timestamps[:3], [0.0, 0.1, 0.2])


def _row(name, seed, pv, vo, init_s=0.5, posed=None, frames=100, colmap=None):
    r = {"scenario": name, "seed": seed, "frames": frames, "path_m": 100.0, "line": {"ate_pct": 5.0},
         "pvslam": {"ate_pct": pv, "init_s": init_s, "init_frame": None if init_s is None else 3,
                    "posed": frames if posed is None else posed, "frames": frames, "reinits": 0, "fps": 5.0},
         "vo": {"ate_pct": vo}}
    if colmap is not None:
        r["colmap"] = {"ate_pct": colmap, "registered": frames}
    return r


def test_targets_pass_and_miss_as_the_issue_states():
    good = [_row("driving_loop", 3, 0.4, 2.0), _row("busy_street", 3, 0.6, 3.0, colmap=0.4),
            _row("kitti_06", None, 0.5, 1.6)]
    verdict = {t["name"]: t["ok"] for t in bench_matrix.targets(good)}
    assert all(v for k, v in verdict.items() if v is not None)
    assert verdict["busy street, no segmenter: within 2x of COLMAP"] is True
    bad = [_row("driving_loop", 3, 0.6, 1.0), _row("handheld_fast", 3, 30.0, 31.0, init_s=None, posed=0),
           _row("busy_street", 4, 2.0, 9.0, init_s=2.5, colmap=0.5)]
    verdict = {t["name"]: t["ok"] for t in bench_matrix.targets(bad)}
    assert verdict["initialises within 2 s of motion, every frame posed"] is False
    assert verdict["ATE >= 3x lower than the textbook VO on every sequence"] is False
    assert verdict["median ATE over the matrix"] is False
    assert verdict["busy street, no segmenter: within 2x of COLMAP"] is False
    assert verdict["driving loop: no regression"] is False
    lines = bench_matrix.table(bad, labels=False, colmap=True)
    assert any("never" in line for line in lines) and any("0/100" in line for line in lines)


@pytest.mark.slow
def test_one_cell_end_to_end(tmp_path, monkeypatch):
    monkeypatch.setenv("PVSLAM_CACHE", str(tmp_path / "cache"))
    row = matrix_jobs.run_cell({"scenario": "driving_loop", "seed": 3, "frames": 25, "out": str(tmp_path)})
    assert row["frames"] == 25 and 15 < row["path_m"] < 18  # 8 m/s at 12 fps
    pv = row["pvslam"]
    assert "error" not in pv and pv["frames"] == 25 and 0 <= pv["posed"] <= 25
    assert pv["init_frame"] is None or pv["init_s"] == pytest.approx(pv["init_frame"] / 12.0, abs=1e-6)
    assert np.isfinite(pv["ate_pct"]) and np.isfinite(row["vo"]["ate_pct"]) and row["line"]["ate_pct"] < 1.0
    if pv["init_frame"] is not None:  # the first map against the ground truth (a straight drive: both small)
        assert pv["init_rot_err_deg"] < 3.0 and pv["init_t_err_deg"] < 20.0


def _tum(positions, yaws_deg):
    """TUM rows [N, 7] (T_wc) of camera centres ``positions`` [N, 3] turned by ``yaws_deg`` about the camera y."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("y", np.asarray(yaws_deg, float)[:, None], degrees=True).as_quat()
    return np.concatenate([np.asarray(positions, float), q], 1)


def test_init_errors_measure_the_first_maps_motion_against_the_ground_truth():
    gt_ts = np.arange(20) / 10.0
    gt = _tum(np.stack([np.zeros(20), np.zeros(20), 0.5 * np.arange(20)], 1), np.zeros(20))
    # the first map: keyframes at 0.0, 0.4, 0.9 s; the last one 2 deg too far turned and moved sideways by
    # tan(10 deg) of its forward motion, in a map of another scale (x 0.1)
    fwd = 0.5 * 9 * 0.1
    est = _tum([[0, 0, 0], [0, 0, 0.2 * 0.1], [fwd * np.tan(np.radians(10.0)), 0, fwd]], [0.0, 0.0, 2.0])
    got = matrix_jobs.init_errors(np.array([0.0, 0.4, 0.9]), est, gt_ts, gt)
    assert got["init_rot_err_deg"] == pytest.approx(2.0, abs=1e-6)
    assert got["init_t_err_deg"] == pytest.approx(10.0, abs=1e-6)
    # the same map in a world frame turned and shifted (W T_wc), only its first and last keyframes: the same errors
    from scipy.spatial.transform import Rotation

    W = Rotation.from_euler("xyz", [10.0, -40.0, 25.0], degrees=True)
    moved = np.concatenate([W.apply(est[:, :3]) + [3.0, -1.0, 2.0], (W * Rotation.from_quat(est[:, 3:])).as_quat()], 1)
    assert matrix_jobs.init_errors(np.array([0.0, 0.9]), moved[[0, 2]], gt_ts, gt) == pytest.approx(got)
    # a first map whose last keyframe has no ground truth within 20 ms has no errors, not wrong ones
    none = matrix_jobs.init_errors(np.array([0.0, 0.95]), est[[0, 2]], gt_ts, gt)
    assert none == {"init_rot_err_deg": None, "init_t_err_deg": None}


def test_summary_names_the_cells_whose_map_started_wrong():
    rows = [_row("driving_loop", 3, 0.4, 2.0), _row("busy_street", 70, 3.5, 3.8), _row("kitti_06", None, 0.1, 1.0)]
    for r, (a, b) in zip(rows, [(0.1, 1.0), (7.0, 87.0), (0.2, 25.0)]):
        r["pvslam"].update(init_rot_err_deg=a, init_t_err_deg=b)
    lines, out = bench_matrix.summary(rows)
    assert out["init_wrong"] == ["busy_street/70 (R 7.0, t 87)", "kitti_06 (R 0.2, t 25)"]
    assert out["init_rot_err_median_deg"] == pytest.approx(0.2) and out["init_t_err_median_deg"] == pytest.approx(25)
    assert any(line.startswith("  map at initialisation (3 sequences)") for line in lines)
    for r in rows:  # a saved run from before the measurement: no line, no keys
        del r["pvslam"]["init_rot_err_deg"], r["pvslam"]["init_t_err_deg"]
    lines, out = bench_matrix.summary(rows)
    assert "init_wrong" not in out and not any("initialisation" in line for line in lines)


def test_reprint_shows_a_saved_run(tmp_path, capsys):
    import json

    rows = [_row("driving_loop", 3, 0.4, 2.0), _row("forward_low_parallax", 3, 27.0, 29.0)]
    rows[1]["vo"]["init_frame"] = -1  # the VO never initialised
    saved = {"set": "report", "seeds": [3], "commit": "abc", "jobs": 1, "frames": None, "rows": rows}
    (tmp_path / "m.json").write_text(json.dumps(saved))
    assert bench_matrix.main(["--reprint", str(tmp_path / "m.json")]) == 0
    out = capsys.readouterr().out
    assert "seed set: REPORT" in out and "29.00*" in out and "never initialised" in out
    assert "[MISS] median ATE over the matrix" in out
    assert bench_matrix.main(["--reprint", str(tmp_path / "m.json"), "--markdown"]) == 0
    md = capsys.readouterr().out
    assert "| scenario | seed |" in md and "| 29.00 * | 1.07x |" in md


def test_overrides_reach_every_pvslam_run_and_a_typo_fails_first(tmp_path, monkeypatch):
    cells = bench_matrix.plan(["busy_street", "kitti_06"], [3], None, tmp_path, False, False, 1,
                              ("graph.init.warmup=3",))
    assert all(c["overrides"] == ["graph.init.warmup=3"] for c in cells)
    seen = []

    def fake_run(overrides, out, name):  # what the cell hands to the pipeline
        seen.append(list(overrides))
        raise RuntimeError("stop here")

    monkeypatch.setattr(matrix_jobs, "run_pvslam", fake_run)
    monkeypatch.setattr(matrix_jobs, "synthetic_sequence", lambda *a: _fake_sequence(tmp_path))
    row = matrix_jobs.run_cell({"scenario": "busy_street", "seed": 3, "frames": 5, "out": str(tmp_path),
                                "overrides": ["graph.warmup=3"]})
    assert "stop here" in row["pvslam"]["error"] and seen and seen[0][-1] == "graph.warmup=3"
    with pytest.raises(Exception, match="warmupp"):
        bench_matrix.main(["--scenarios", "busy_street", "--seeds", "3", "--override", "graph.warmupp=3",
                           "--out", str(tmp_path)])


def test_exposure_runs_every_method_on_an_exposed_copy(tmp_path, monkeypatch):
    """--exposure: synthetic cells (not KITTI) run on a copy of the sequence whose images follow the auto-exposure
    profile; the original folder is untouched."""
    import cv2

    cells = bench_matrix.plan(["busy_street", "kitti_06"], [3], None, tmp_path, False, False, 1, exposure=True)
    assert [c["exposure"] for c in cells] == [True, False]
    seq = _fake_sequence(tmp_path)
    (seq / "rgb").mkdir()
    for i in range(61):
        cv2.imwrite(str(seq / "rgb" / f"{i:06d}.png"), np.full((8, 8, 3), 100, np.uint8))
    seen = []

    def fake_run(overrides, out, name):
        seen.append([o for o in overrides if o.startswith("dataset.path=")][0])
        raise RuntimeError("stop here")

    monkeypatch.setattr(matrix_jobs, "run_pvslam", fake_run)
    monkeypatch.setattr(matrix_jobs, "synthetic_sequence", lambda *a: seq)
    matrix_jobs.run_cell({"scenario": "busy_street", "seed": 3, "frames": 5, "out": str(tmp_path / "out"),
                          "exposure": True})
    rgb = Path(seen[0].split("=", 1)[1].strip('"'))
    assert rgb.parent != seq and "exposure" in str(rgb)
    assert int(cv2.imread(str(rgb / "000060.png"))[0, 0, 0]) == 150  # 100 x the 1.5x hold
    assert int(cv2.imread(str(seq / "rgb" / "000060.png"))[0, 0, 0]) == 100


def _fake_sequence(tmp_path):
    """A 5-frame synthetic-like folder: meta.json and a TUM ground truth (all run_cell reads before pvslam)."""
    import json

    d = tmp_path / "seq"
    d.mkdir(exist_ok=True)
    (d / "meta.json").write_text(json.dumps({"fps": 10.0}))
    (d / "groundtruth.txt").write_text("".join(f"{0.1 * i:.1f} {i} 0 0 0 0 0 1\n" for i in range(5)))
    return d


def test_another_lens_reaches_the_synthetic_cells_and_a_bad_one_fails_first(tmp_path, monkeypatch):
    cells = bench_matrix.plan(["busy_street", "kitti_06"], [3], None, tmp_path, False, False, 1, hfov_deg=90.0)
    assert [c["hfov_deg"] for c in cells] == [90.0, 90.0]  # (a KITTI cell reads its own calibration)
    asked = []

    def fake_sequence(scenario, seed, frames, size, hfov_deg=None):
        asked.append(hfov_deg)
        raise RuntimeError("stop here")

    monkeypatch.setattr(matrix_jobs, "synthetic_sequence", fake_sequence)
    row = matrix_jobs.run_cell({"scenario": "busy_street", "seed": 3, "frames": 5, "out": str(tmp_path),
                                "hfov_deg": 90.0})
    assert asked == [90.0] and "stop here" in row["error"]
    with pytest.raises(SystemExit):
        bench_matrix.main(["--scenarios", "busy_street", "--seeds", "3", "--hfov", "200", "--out", str(tmp_path)])
