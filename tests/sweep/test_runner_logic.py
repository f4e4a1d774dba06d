"""The driver's bookkeeping with a stand-in cell function (no SLAM runs): which cells run on resume (done kept,
failed kept unless retried, unfinished cleaned, stale moved aside), the markers, and the progress display."""
from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from pvslam_core.outputs.metrics import write_json_atomic
from pvslam_core.sweep import cells as C
from pvslam_core.sweep import executors as X
from pvslam_core.sweep.progress import GridProgress
from pvslam_core.sweep.runner import run_sweep
from pvslam_core.sweep.spec import load_sweep

from sweep_helpers import sweep_text


@pytest.fixture
def fake_cells(monkeypatch):
    ran = []

    def fake(payload):
        d = Path(payload["dir"])
        d.mkdir(parents=True, exist_ok=True)
        assert not (d / "leftover.txt").exists(), "a cell must start from a clean folder"
        ran.append(payload["name"])
        if payload["meta"]["variant"] == "offline_ba" and payload["meta"]["seed"] == 1:
            C.mark_failed(d, payload["key"], "RuntimeError: planned", "Traceback ...")
            return {"name": payload["name"], "status": C.FAILED, "error": "RuntimeError: planned", "seconds": 0.0}
        write_json_atomic(d / "metrics.json", {"timing": {"fps": 5.0}, "ate": {"rmse": 0.1 * (1 + payload["meta"]["seed"])}})
        write_json_atomic(d / "done.json", {"status": C.DONE, "key": payload["key"], "seconds": 0.01})
        return {"name": payload["name"], "status": C.DONE, "error": "", "seconds": 0.01}

    monkeypatch.setitem(X.FUNCTIONS, "cell", fake)
    return ran


def test_resume_rules(tmp_path, fake_cells):
    cfg = tmp_path / "s.toml"
    cfg.write_text(sweep_text(tmp_path / "out", seeds=(0, 1)).replace("plots = true", "plots = false"))
    plan = load_sweep(cfg)
    names = [c.name for c in plan.cells]  # seed0 online, seed0 offline, seed1 online, seed1 offline
    first = run_sweep(cfg, serial=True, progress=False)
    assert first.ran == names and list(first.failed) == [names[3]]
    cells = plan.directory / "cells"

    # done stays done; an interrupted cell (no marker, partial files) is cleaned and rerun; a failed one is kept
    (cells / names[2] / "done.json").unlink()
    (cells / names[2] / "leftover.txt").write_text("partial")
    fake_cells.clear()
    second = run_sweep(cfg, serial=True, progress=False)
    assert fake_cells == [names[2]] and sorted(second.skipped) == sorted([names[0], names[1], names[3]])
    assert second.failed == {names[3]: "RuntimeError: planned"}

    # a finished cell whose config changed since is moved aside, never mixed into the table
    done = json.loads((cells / names[0] / "done.json").read_text())
    done["key"] = "0" * 16
    (cells / names[0] / "done.json").write_text(json.dumps(done))
    assert C.cell_status(cells / names[0], plan.cells[0].key) == "stale"
    fake_cells.clear()
    run_sweep(cfg, serial=True, progress=False, report_only=True)  # a report changes nothing
    assert fake_cells == [] and C.cell_status(cells / names[0], plan.cells[0].key) == "stale"
    run_sweep(cfg, serial=True, progress=False)
    assert fake_cells == [names[0]]
    assert len(list((plan.directory / "stale").glob(f"{names[0]}-*"))) == 1

    status = json.loads((plan.directory / "status.json").read_text())
    assert status["counts"] == {"done": 3, "failed": 1}
    assert json.loads((plan.directory / "plan.json").read_text())["cells"][0]["name"] == names[0]
    assert (plan.directory / "sweep.toml").read_text() == cfg.read_text()


def test_progress_lines_and_eta():
    buf = io.StringIO()  # not a terminal: one line per finished cell
    p = GridProgress(total=5, skipped=1, slots=2, stream=buf, label="t")
    assert p.eta() is None
    p.start("a")
    p.start("b")
    p.durations.append(10.0)  # as if a cell of 10 s had finished
    p.done += 1
    p.running.pop("a")
    # 2 cells left to start + b in flight: (3 x 10 s - b's few ms) / 2 slots
    assert p.eta() == pytest.approx(15.0, abs=0.1)
    p.finish("b", "failed", "ValueError: x")
    out = buf.getvalue()
    assert "failed b: ValueError: x" in out.replace("  ", " ") and "3/5 cells" in out and "1 failed" in out
    assert "1 already finished" in out and "remaining ~" in out
