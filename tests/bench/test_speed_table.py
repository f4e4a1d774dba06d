"""bench/speed_table.py: the per-stage CPU figures of a run's timing, the scenario means, the peers' rows and CPU
ratios, the target lines, and which runs the section makes (fakes instead of pipeline runs)."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import speed_table as S  # noqa: E402


def _timing(frames=100, keyframes=40, fps=20.0, cpu=9.0, track=1.0, ba=2.0, mapped=4.2):
    return {"frames": frames, "keyframes": keyframes, "fps": fps, "cpu_seconds": cpu,
            "stage_cpu_seconds": {"read": 0.1, "segment": 0.2, "map": mapped, "vps": 0.0, "outputs": 0.3,
                                  "finalize": 0.4},
            "map_cpu_seconds": {"track": track, "keyframe": 0.25, "edges": 0.5, "ba": ba, "loops": 0.1,
                                "pose_guess": 0.2, "fill": 0.05},
            "steps": {"keyframe": {"count": keyframes, "wall_ms": 80.0, "cpu_ms": 60.0},
                      "other": {"count": frames - keyframes, "wall_ms": 20.0, "cpu_ms": 12.0}}}


def test_a_run_row_is_per_frame_milliseconds_of_each_stage():
    r = S.run_row("default", "pvslam run", _timing())
    st = r["stage_ms"]
    assert r["frames"] == 100 and r["kf_per_frame"] == pytest.approx(0.4) and r["fps"] == 20.0
    assert r["cpu_ms"] == pytest.approx(90.0)
    assert st["track"] == pytest.approx(10.0) and st["BA"] == pytest.approx(20.0) and st["fill"] == pytest.approx(0.5)
    # the map stage less its named parts; the process less the pipeline thread
    assert st["new keyframe"] == pytest.approx(2.5)
    assert st["map other"] == pytest.approx(1000 * (4.2 - 4.1) / 100)
    assert st["other threads"] == pytest.approx(1000 * (9.0 - 5.2) / 100)
    assert st["final BA"] == pytest.approx(4.0) and st["read"] == pytest.approx(1.0)
    assert r["step_ms"] == {"keyframe": 80.0, "other": 20.0}
    no_kf = S.run_row("default", "pvslam run", {**_timing(), "steps": {"keyframe": {"count": 0, "wall_ms": 0.0}}})
    assert no_kf["step_ms"]["keyframe"] != no_kf["step_ms"]["keyframe"]  # nan: no such step, not 0 ms


def test_the_table_has_one_line_per_row_and_dashes_for_what_a_peer_lacks():
    rows = [S.run_row("KITTI 00", "pvslam run FOLDER --calib", _timing(frames=160, cpu=16.0)),
            S.peer_row("KITTI 00", "textbook VO", 160, 0.8, 2.0),
            S.peer_row("KITTI 00", "ORB-SLAM3 (less vocabulary load)", 160, 3.2, None)]
    lines = S.table(rows)
    assert len(lines) == 2 + 3
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    assert head[:8] == ["group", "run", "frames", "kf/frame", "frames/s wall", "ms/keyframe step", "ms/other step",
                        "CPU ms/frame"]
    mine = [c.strip() for c in lines[2].strip("|").split("|")]
    assert mine[5:7] == ["80.0", "20.0"]
    assert {"track", "edges", "BA", "loops", "pose guess", "fill", "outputs", "segment", "read"} <= set(head)
    vo = [c.strip() for c in lines[3].strip("|").split("|")]
    assert vo[:8] == ["KITTI 00", "textbook VO", "160", "-", "80.0", "-", "-", "5.0"] and set(vo[8:]) == {"-"}
    orb = [c.strip() for c in lines[4].strip("|").split("|")]
    assert orb[4] == "-" and orb[7] == "20.0"  # a paced run has no wall frames/s
    ratios = S.cpu_ratios(rows, "KITTI 00")
    assert len(ratios) == 2 and "20.0x textbook VO" in ratios[0] and "5.0x ORB-SLAM3" in ratios[1]


def test_a_scenario_mean_averages_its_seeds():
    a = S.run_row("busy_street", "seed 3", _timing(fps=20.0, cpu=9.0, track=1.0))
    b = S.run_row("busy_street", "seed 4", _timing(fps=40.0, cpu=5.0, track=3.0))
    b["step_ms"]["keyframe"] = 100.0
    m = S.mean_row([a, b], "busy_street", "mean")
    assert m["frames"] == 200 and m["fps"] == pytest.approx(30.0) and m["cpu_ms"] == pytest.approx(70.0)
    assert m["stage_ms"]["track"] == pytest.approx(20.0)
    assert m["step_ms"] == {"keyframe": pytest.approx(90.0), "other": pytest.approx(20.0)}


def test_targets_take_the_default_run_each_scenario_mean_and_the_real_excerpts():
    rows = [S.run_row("default", "pvslam run", _timing(fps=31.0)),
            S.run_row("busy_street", "seed 3", _timing(fps=10.0)), S.run_row("busy_street", "mean", _timing(fps=29.0)),
            S.run_row("KITTI 06", "pvslam run FOLDER --calib", _timing(fps=16.0, cpu=12.0)),
            S.peer_row("KITTI 06", "textbook VO", 100, 1.0, 1.0),
            S.peer_row("KITTI 06", "ORB-SLAM3 (less vocabulary load)", 100, 3.0, None)]
    seen = []
    S.targets(rows, lambda name, ok, measured, goal: seen.append((name, ok)))
    assert seen == [("speed 320x240 default", True), ("speed 320x240 busy_street", False),
                    ("speed KITTI 06 as a user runs it", True), ("CPU per frame KITTI 06 vs ORB-SLAM3", False)]


def test_the_section_runs_the_default_every_scenario_seed_and_the_real_sequences(monkeypatch, tmp_path, capsys):
    import bench.bench_real as B
    import bench.matrix_jobs as M
    import bench.seeds as seeds
    import pvslam_plugins.datasets.synthetic.scenarios as scen

    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "meta.json").write_text(json.dumps({"fps": 10.0}))
    monkeypatch.setattr(scen, "SCENARIOS", {"driving_loop": "", "busy_street": ""})
    monkeypatch.setattr(seeds, "load", lambda: SimpleNamespace(sets={"report": (3, 4, 5)}))
    made = []
    monkeypatch.setattr(M, "synthetic_sequence", lambda sc, seed, frames: made.append((sc, seed, frames)) or seq)
    kitti = tmp_path / "kitti"
    (kitti / "sequences" / "06" / "image_0").mkdir(parents=True)
    monkeypatch.setattr(M, "KITTI", kitti)
    monkeypatch.setattr(M, "kitti_as_tum", lambda s, out: tmp_path / "peer")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.json").write_text(json.dumps({"timing": _timing(frames=51, cpu=10.2)}))
    pv_calls = []
    monkeypatch.setattr(B, "run_pvslam", lambda s, out, timeout, extra=(): pv_calls.append((s, extra))
                        or {"run_dir": str(run_dir)})
    monkeypatch.setattr(B, "run_vo", lambda d: {"ts": list(range(51)), "cpu_s": 0.51, "wall_s": 1.0})
    monkeypatch.setattr(B, "orb_missing", lambda python, vocab, runner: None if python else "no --orb-python")
    monkeypatch.setattr(B, "run_orb", lambda *a, **k: {"cpu_s": 4.04, "wall_s": 5.1, "vocab_load_s": 2.0})
    monkeypatch.setattr(B, "read_gt", lambda d: (list(range(51)), None))
    runs = []

    def fake_run(overrides, out):
        runs.append(overrides)
        return SimpleNamespace(metrics={"timing": _timing()})

    results = {}
    rows = S.section(fake_run, tmp_path, quick=False, orb_python="/py", orb_vocab=["/voc.txt"], results=results)
    assert len(runs) == 1 + 2 * 3  # the default run, then two scenarios x three report seeds
    assert all("evaluation.enabled=false" in ov for ov in runs)
    assert [r["run"] for r in rows if r["group"] == "busy_street"] == ["seed 3", "seed 4", "seed 5", "mean"]
    assert made == [(sc, s, None) for sc in ("driving_loop", "busy_street") for s in (3, 4, 5)]
    assert pv_calls == [("06", [])]  # only the excerpt that is there, as a user runs it
    assert [r["run"] for r in rows if r["group"] == "KITTI 06"] == [
        "pvslam run FOLDER --calib", "textbook VO", "ORB-SLAM3 (less vocabulary load)"]
    assert results["speed"] == rows
    out = capsys.readouterr().out
    assert "| KITTI 06 | textbook VO | 51 |" in out and "pvslam's CPU per frame is 20.0x textbook VO's" in out
    assert "| KITTI 06 | ORB-SLAM3 (less vocabulary load) | 51 | - | - | - | - | 40.0 |" in out  # (4.04 - 2.0) s / 51
    rows = S.section(fake_run, tmp_path, quick=True)  # quick: one seed per scenario, few frames, no ORB-SLAM3
    assert pv_calls[-1] == ("06", ["--set", "run.max_frames=20"])
    assert [r["run"] for r in rows if r["group"] == "busy_street"] == ["seed 3", "mean"]
    assert made[-1] == ("busy_street", 3, None) and "run.max_frames=60" in runs[-1]  # the cached sequence's start
    assert "ORB-SLAM3 skipped: no --orb-python" in capsys.readouterr().out
