"""Result-file permissions and write errors."""
from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path

import pytest

from pvslam_core.api import run_config


@pytest.fixture
def umask():
    def set_(mask: int) -> None:
        os.umask(mask)

    old = os.umask(0o022)
    yield set_
    os.umask(old)


def _modes(run_dir: Path) -> dict[str, int]:
    return {str(p.relative_to(run_dir)): stat.S_IMODE(p.stat().st_mode) for p in run_dir.rglob("*")}


@pytest.mark.parametrize("mask, file_mode, dir_mode", [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700),
                                                       (0o002, 0o664, 0o775)])
def test_result_files_follow_the_umask(tmp_path, fake_registry, fake_config_file, umask, mask, file_mode, dir_mode):
    umask(mask)
    res = run_config(fake_config_file, registry=fake_registry)
    modes = _modes(Path(res.run_dir))
    for name in ("trajectory.txt", "keyframes.txt", "groundtruth.txt", "metrics.json", "loops.json",
                 "config.json", "versions.json", "log.txt", "panoptic/segments.json", "panoptic/000000.png"):
        assert modes[name] == file_mode, (name, oct(modes[name]))
    for name, mode in modes.items():
        assert mode == (dir_mode if (Path(res.run_dir) / name).is_dir() else file_mode), (name, oct(mode))


def test_atomic_writer_modes(tmp_path, umask):
    from pvslam_core.outputs._atomic import atomic_write_bytes, atomic_write_text

    umask(0o022)
    atomic_write_text(tmp_path / "a.txt", "x")
    atomic_write_bytes(tmp_path / "b.bin", b"x")
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "b.bin").stat().st_mode) == 0o644
    assert os.umask(0o022) == 0o022  # the writer leaves the process umask as it found it


def _fail_writes_to(monkeypatch, suffix: str) -> None:
    """``os.replace`` onto a path ending in ``suffix`` fails as a full disk does (an OSError with no file name)."""
    real = os.replace

    def replace(src, dst, *a, **kw):
        if os.fspath(dst).endswith(suffix):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(src, dst, *a, **kw)

    monkeypatch.setattr(os, "replace", replace)


def test_write_error_names_the_file(tmp_path, monkeypatch):
    from pvslam_core.outputs._atomic import atomic_write_text

    _fail_writes_to(monkeypatch, "out.txt")
    with pytest.raises(OSError) as err:
        atomic_write_text(tmp_path / "out.txt", "x")
    assert err.value.errno == errno.ENOSPC and str(tmp_path / "out.txt") in str(err.value)
    assert os.listdir(tmp_path) == []  # no temporary file left behind


@pytest.mark.parametrize("victim", ["trajectory.txt", "keyframes.txt", "segments.json"])
def test_failed_write_still_saves_metrics_json(tmp_path, fake_registry, fake_config_file, monkeypatch, victim):
    _fail_writes_to(monkeypatch, victim)
    with pytest.raises(OSError) as err:
        run_config(fake_config_file, registry=fake_registry)
    assert victim in str(err.value) and "No space left" in str(err.value)
    (run_dir,) = list((tmp_path / "runs").iterdir())
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["partial"] is True
    (failed,) = [k for k in m["write_errors"] if k.endswith(victim)]
    assert "No space left" in m["write_errors"][failed]
    # the other files of the same checkpoint were still written
    for other in {"trajectory.txt", "keyframes.txt", "groundtruth.txt", "loops.json"} - {victim}:
        assert (run_dir / other).is_file(), other
    assert victim in (run_dir / "log.txt").read_text()


def test_metrics_json_itself_unwritable_says_exactly_what(tmp_path, fake_registry, fake_config_file, monkeypatch,
                                                          caplog):
    _fail_writes_to(monkeypatch, "metrics.json")
    with pytest.raises(OSError) as err:
        run_config(fake_config_file, registry=fake_registry)
    assert "metrics.json" in str(err.value)
    (run_dir,) = list((tmp_path / "runs").iterdir())
    assert (run_dir / "trajectory.txt").is_file()
    assert "metrics.json" in (run_dir / "log.txt").read_text()
