"""Bad input and faults at the command line: one ``pvslam: error:`` line, what a run wrote is kept, nothing else."""
from __future__ import annotations

import errno
import io
import json
import logging
import os
from pathlib import Path

import numpy as np
import pytest

import fakes
from pvslam_core.api import run_config
from pvslam_core.cli import main


@pytest.fixture
def fake_cli(fake_registry, monkeypatch):
    """`pvslam ...` with the test-only plugins."""
    from pvslam_core import registry as r

    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    return fake_registry


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.startswith("pvslam: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ------------------------------------------------------------------------------------------- paths, names --
def test_output_dir_and_name_are_taken_as_given(fake_cli, fake_config_file, tmp_path, monkeypatch, capsys):
    """An emoji in --output-dir / --name reaches the run directory as it is (no TOML round trip of the text)."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out 😀 \\ q\"x"
    assert main(["run", "-c", str(fake_config_file), "-q", "--output-dir", str(out), "--name", "run😀"]) == 0
    (run_dir,) = list(out.iterdir())
    assert run_dir.name.startswith("run😀-") and (run_dir / "trajectory.txt").is_file()
    assert not (tmp_path / '"').exists()
    assert json.loads((run_dir / "config.json").read_text())["run"]["output_dir"] == str(out)


# ---------------------------------------------------------------------------------------------- bounds --
def test_a_huge_num_frames_is_a_config_error_naming_the_key(capsys):
    from pvslam_core.config import ConfigError, load_config

    with pytest.raises(ConfigError, match=r"dataset\.num_frames"):
        load_config(overrides=["dataset.num_frames=1e12"])
    assert main(["config", "validate", str(Path(__file__).parents[2] / "configs" / "default.toml"),
                 "--set", "dataset.num_frames=1e12"]) == 2
    assert "dataset.num_frames" in _one_error_line(capsys.readouterr().err)


def test_huge_laps_are_refused_before_anything_is_allocated():
    from pvslam_plugins.datasets.synthetic.scenario_base import count_frames

    with pytest.raises(ValueError, match="laps"):
        count_frames(None, 1e10, 200.0, 1.1)
    with pytest.raises(ValueError, match="num_frames"):
        count_frames(10**12, None, 200.0, 1.1)
    assert count_frames(None, None, 200.0, 1.1) == 220 and count_frames(7, None, 200.0, 1.1) == 7


# ------------------------------------------------------------------------------------------ OpenCV errors --
def test_an_opencv_assertion_names_the_stage_and_the_frame(fake_cli, fake_config_file, tmp_path, monkeypatch,
                                                            capsys):
    import cv2

    real = fakes.ExactFrontend.track

    def track(self, frame, seg):
        if frame.index == 5:  # a genuine OpenCV assertion: a map wider than remap takes
            cv2.remap(np.zeros((4, 4), np.float32), np.zeros((1, 40000), np.float32),
                      np.zeros((1, 40000), np.float32), cv2.INTER_LINEAR)
        return real(self, frame, seg)

    monkeypatch.setattr(fakes.ExactFrontend, "track", track)
    assert main(["run", "-c", str(fake_config_file), "-q"]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert "OpenCV" in line and "the map stage at frame 5" in line and "remap" in line, line
    (run_dir,) = list((tmp_path / "runs").iterdir())
    from pvslam_core.outputs.trajectory_io import read_tum

    assert len(read_tum(run_dir / "trajectory.txt")[0]) == 5  # frames 0-4 are kept


def test_an_opencv_assertion_before_any_frame_does_not_point_at_a_removed_directory(fake_cli, fake_config_file,
                                                                                   tmp_path, monkeypatch, capsys):
    import cv2

    def add_keyframe(self, kf_id, frame, seg):  # the first frame becomes a keyframe: nothing is written yet
        cv2.remap(np.zeros((4, 4), np.float32), np.zeros((1, 40000), np.float32),
                  np.zeros((1, 40000), np.float32), cv2.INTER_LINEAR)

    monkeypatch.setattr(fakes.ExactFrontend, "add_keyframe", add_keyframe)
    assert main(["run", "-c", str(fake_config_file), "-q"]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert "the map stage at frame 0" in line and "keeps what was written" not in line, line
    assert not (tmp_path / "runs").exists() or not list((tmp_path / "runs").iterdir())


# ----------------------------------------------------------------------------------- empty run directories --
def test_a_run_that_fails_before_its_first_frame_leaves_no_directory(fake_registry, fake_config_file, tmp_path,
                                                                      monkeypatch):
    spec = fake_registry.get("dataset", "fake")

    def cannot_open(cfg, ctx):
        raise FileNotFoundError("no such sequence (test)")

    monkeypatch.setattr(spec, "factory", cannot_open)
    with pytest.raises(FileNotFoundError):
        run_config(fake_config_file, registry=fake_registry)
    assert list((tmp_path / "runs").iterdir()) == []


# -------------------------------------------------------------------------------------------- full disk --
class _FullDisk(io.StringIO):
    """log.txt on a full disk: text is taken, flushing it fails."""

    def flush(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def close(self):
        try:
            self.flush()
        finally:
            super().close()


def test_a_full_disk_names_the_files_not_the_log(fake_registry, fake_config_file, tmp_path, monkeypatch, capsys):
    """log.txt and trajectory.txt cannot be written: the error raised names trajectory.txt (the log's own flush
    error does not replace it) and metrics.json records the failure."""
    from pvslam_core.run_outputs import OutputWriteError

    real_replace = os.replace

    def replace(src, dst, *a, **kw):
        if os.fspath(dst).endswith("trajectory.txt"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_replace(src, dst, *a, **kw)

    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(logging.FileHandler, "_open", lambda self: _FullDisk())
    with pytest.raises(OutputWriteError, match="trajectory.txt"):
        run_config(fake_config_file, registry=fake_registry)
    err = capsys.readouterr().err
    assert "Logging error" not in err and err.count("log.txt") == 1, err
    (run_dir,) = list((tmp_path / "runs").iterdir())
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["partial"] is True and any(k.endswith("trajectory.txt") for k in m["write_errors"])


# ---------------------------------------------------------------------------------------------- ablation --
def test_a_variant_named_like_the_ablations_own_file_is_refused(tmp_path, fake_registry):
    from pvslam_core.config import ConfigError, load_ablation

    abl = tmp_path / "abl.toml"
    abl.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix())
                   + '\n[[variant]]\nname = "comparison.json"\n\n[[variant]]\nname = "b"\n"run.seed" = 1\n')
    with pytest.raises(ConfigError, match="comparison.json"):
        load_ablation(abl, registry=fake_registry)
