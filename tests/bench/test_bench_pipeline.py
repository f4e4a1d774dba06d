"""bench/bench_pipeline.py's ``--set``: the overrides reach every run (after the run's own), the long run's child
process and the results file name, so a profile is measured on exactly the runs of the default."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_pipeline  # noqa: E402


@pytest.fixture
def extra():
    saved = list(bench_pipeline.EXTRA)
    yield bench_pipeline.EXTRA
    bench_pipeline.EXTRA[:] = saved


def test_set_overrides_come_last_in_every_run(monkeypatch, tmp_path, extra):
    seen = []
    import pvslam_core.api as api

    monkeypatch.setattr(api, "run_config", lambda config, overrides: seen.append((config, overrides)))
    extra[:] = ["optimizer.iters=5"]
    bench_pipeline.run(["--config-file", "configs/kitti.toml", "outputs.ply=false"], tmp_path)
    bench_pipeline.run(["outputs.plots=false"], tmp_path)
    assert seen[0][0] == "configs/kitti.toml" and seen[1][0] is None
    for _, ov in seen:
        assert ov[-1] == "optimizer.iters=5"  # last: it wins over the section's own overrides
    assert "outputs.ply=false" in seen[0][1] and "outputs.plots=false" in seen[1][1]
    extra[:] = []
    bench_pipeline.run(["outputs.plots=false"], tmp_path)
    assert seen[2][1][-1] == "outputs.plots=false"


def test_long_child_gets_the_overrides(monkeypatch, tmp_path, extra):
    calls = []

    class Done:
        returncode, stderr, stdout = 1, "stop here", ""

    monkeypatch.setattr(bench_pipeline, "generate", lambda *a, **k: tmp_path)
    monkeypatch.setattr(bench_pipeline.subprocess, "run", lambda cmd, **k: calls.append(cmd) or Done())
    extra[:] = ["optimizer.iters=5", "loop.plugin=none"]
    bench_pipeline.section_long(tmp_path, quick=True)
    cmd = calls[0]
    assert cmd[cmd.index("--long-child") + 1] == "600"
    sets = [cmd[i + 1] for i, a in enumerate(cmd) if a == "--set"]
    assert sets == ["optimizer.iters=5", "loop.plugin=none"]


def test_the_endless_input_runs_compare_peak_memory_as_a_live_source(monkeypatch, tmp_path, capsys):
    from pvslam_core.slam.revisits import LIVE_THRESH

    def child(frames, peak, peak_run):
        return {"frames": frames, "keyframes": frames // 20, "culled": frames // 5, "peak_mb": peak,
                "peak_run_mb": peak_run, "first_cpu": 0.1, "last_cpu": 0.1, "ate_pct": 0.01, "path_m": 1.0,
                "loops": 3, "unmerged": 1, "samples": [{"frame": 1000 * k, "keyframes": 100 + k, "rss_mb": 400.0 + k}
                                                       for k in (1, 2)]}

    results = {3000: child(3000, 1000.0, 650.0), 10000: child(10000, 1300.0, 700.0)}

    class Done:
        returncode, stderr = 0, ""

        def __init__(self, cmd):
            self.stdout = "log line\n" + __import__("json").dumps(results[int(cmd[cmd.index("--long-child") + 1])])

    calls = []
    monkeypatch.setattr(bench_pipeline, "generate", lambda *a, **k: tmp_path)
    monkeypatch.setattr(bench_pipeline.subprocess, "run", lambda cmd, **k: calls.append(cmd) or Done(cmd))
    monkeypatch.setattr(bench_pipeline, "RESULTS", {})
    monkeypatch.setattr(bench_pipeline, "EXTRA", ["optimizer.iters=5"])
    bench_pipeline.section_flat(tmp_path, 10000)
    assert [c[c.index("--long-child") + 1] for c in calls] == ["3000", "10000"]  # each in its own process
    for cmd in calls:  # culling as a live source gets it, then the user's overrides
        assert [cmd[i + 1] for i, a in enumerate(cmd) if a == "--set"] == [
            f"graph.keyframes.revisit_thresh={LIVE_THRESH}", "optimizer.iters=5"]
    out = capsys.readouterr().out
    assert "3000 frames: 150 keyframes (600 culled on revisits), peak RSS 1000 MB" in out
    assert "10000 frames: 500 keyframes (2000 culled on revisits), peak RSS 1300 MB" in out
    assert "[MISS] peak RSS 10000 / 3000 frames: 1.30" in out and "<= 1.10" in out
    assert "keyframes every 1000 frames: 101, 102" in out and "RSS (MB) every 1000 frames: 401, 402" in out
    assert bench_pipeline.RESULTS["flat"]["long"]["peak_mb"] == 1300.0
    results[10000] = child(10000, 1080.0, 700.0)
    bench_pipeline.section_flat(tmp_path, 10000)
    assert "[PASS] peak RSS 10000 / 3000 frames: 1.08" in capsys.readouterr().out
    calls.clear()
    bench_pipeline.section_flat(tmp_path, 0)  # --flat-frames 0: skipped
    assert calls == []


def test_speed_reports_the_pipeline_threads_time_not_computing(capsys):
    """``main_idle_ms``: the pipeline thread's stage wall time beyond its CPU, per frame (never negative)."""
    from types import SimpleNamespace

    timing = {"frames": 10, "keyframes": 4, "fps": 20.0, "seconds": 0.5, "cpu_seconds": 0.8,
              "stage_seconds": {"map": 0.45, "outputs": 0.02}, "stage_cpu_seconds": {"map": 0.30, "outputs": 0.02}}
    sp = bench_pipeline.speed(SimpleNamespace(metrics={"timing": timing}))
    assert sp["main_ms"] == pytest.approx(32.0) and sp["main_idle_ms"] == pytest.approx(15.0)
    assert sp["cpu_ms"] == pytest.approx(80.0) and sp["est_fps"] == pytest.approx(25.0)
    bench_pipeline.print_speed("x", sp)
    assert "(pipeline thread 32.0, and 15.0 not computing)" in capsys.readouterr().out
    timing["stage_seconds"] = {"map": 0.1}  # a clock that disagrees: no negative idle time
    assert bench_pipeline.speed(SimpleNamespace(metrics={"timing": timing}))["main_idle_ms"] == 0.0


def test_speed_prints_the_keyframe_steps_share_of_the_wall_time(capsys):
    """With ``timing.steps``, the printout says how long a keyframe step and another step take and what share of
    the steps' wall time the keyframe steps are (4 x 90 ms against 6 x 10 ms: 86 %)."""
    from types import SimpleNamespace

    timing = {"frames": 10, "keyframes": 4, "fps": 20.0, "seconds": 0.5, "cpu_seconds": 0.8,
              "stage_seconds": {"map": 0.42}, "stage_cpu_seconds": {"map": 0.30},
              "steps": {"keyframe": {"count": 4, "wall_ms": 90.0, "cpu_ms": 60.0},
                        "other": {"count": 6, "wall_ms": 10.0, "cpu_ms": 10.0}}}
    bench_pipeline.print_speed("x", bench_pipeline.speed(SimpleNamespace(metrics={"timing": timing})))
    assert "4 keyframe steps at 90.0 ms wall (60.0 CPU), 6 others at 10.0 ms (10.0 CPU): the keyframe steps take " \
           "86% of the steps' wall time" in capsys.readouterr().out
