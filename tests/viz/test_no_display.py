"""No display (a server, a container, ssh without X): the viewer is refused at once with the way to record the view
to a file, instead of a viewer process that never connects and a command that waits forever."""
from __future__ import annotations

import sys
import time

import pytest

rr = pytest.importorskip("rerun")

from pvslam_core.cli import main  # noqa: E402


@pytest.fixture
def headless(monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)

    def spawn(*a, **kw):  # what waited forever: fail the test instead
        raise AssertionError("a viewer was spawned without a display")

    monkeypatch.setattr(rr.RecordingStream, "spawn", spawn)
    monkeypatch.setattr(rr, "spawn", spawn)


def _one_line(err: str) -> str:
    (line,) = [ln for ln in err.splitlines() if ln.startswith("pvslam: error:")]
    assert "Traceback" not in err
    return line


def test_view_without_a_display_says_to_save_a_recording(headless, tmp_path, capsys):
    t0 = time.perf_counter()
    assert main(["view", str(tmp_path)]) == 2
    assert time.perf_counter() - t0 < 10
    line = _one_line(capsys.readouterr().err)
    assert "no display" in line and "--save FILE.rrd" in line, line


def test_run_viz_without_a_display_says_viz_save(headless, tmp_path, capsys):
    assert main(["run", "--viz", "--output-dir", str(tmp_path / "runs")]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "no display" in line and "--viz-save FILE.rrd" in line, line
    assert not (tmp_path / "runs").exists()  # refused before the run started
