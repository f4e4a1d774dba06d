"""Bad input and faults found by probing: names that escape the output directory, ablations with a
failing variant, unclear messages, and the tomllib fallback on Python 3.10."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import fakes
from pvslam_core.api import run_ablation
from pvslam_core.cli import main
from pvslam_core.config import ConfigError, load_ablation, load_config


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file below ``root`` with its content (to prove nothing was written or overwritten)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _outside(root: Path, out_dir: Path) -> dict[str, bytes]:
    return {k: v for k, v in _snapshot(root).items() if not (root / k).resolve().is_relative_to(out_dir.resolve())}


# ------------------------------------------------------------------------------------------------ item 1 --
BAD_NAMES = ["../../x", "../victim", "a/../../b", "sub/dir", "..", ".", "", "/abs/x", "a\\..\\b", "nul\x00byte"]


@pytest.mark.parametrize("name", BAD_NAMES)
def test_run_name_cannot_leave_the_output_dir(tmp_path, name):
    from pvslam_core.rundir import make_run_dir

    out = tmp_path / "deep" / "out"
    out.mkdir(parents=True)
    before = _snapshot(tmp_path)
    with pytest.raises((ValueError, ConfigError)) as err:
        make_run_dir(out, name)
    assert "name" in str(err.value)
    assert _snapshot(tmp_path) == before
    with pytest.raises(ConfigError, match="run.name"):
        load_config(overrides={"run.name": name, "run.output_dir": str(out)})


def test_absolute_and_dotdot_names_from_cli_and_config_write_nothing_outside(tmp_path, capsys, fake_config_file,
                                                                              fake_registry, monkeypatch):
    from pvslam_core import registry as r

    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    out = tmp_path / "runs"
    victim = tmp_path / "victim-file"
    victim.write_text("precious")
    cfg = tmp_path / "named.toml"
    cfg.write_text(fake_config_file.read_text().replace("[run]", '[run]\nname = "../../escape"'))
    before = _outside(tmp_path, out)
    for name in ("../../x", str(tmp_path / "abs"), "../victim-file"):
        assert main(["run", "-c", str(fake_config_file), "--name", name, "-q"]) == 2
        err = capsys.readouterr().err
        assert "run.name" in err and "inside" in err
    with pytest.raises(ConfigError, match=r"run\.name"):
        load_config(cfg, registry=fake_registry)
    assert main(["run", "-c", str(cfg), "-q"]) == 2
    assert _outside(tmp_path, out) == before and victim.read_text() == "precious"


def test_ablation_variant_name_cannot_escape(tmp_path, fake_registry):
    out = tmp_path / "a" / "b" / "runs"
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "config.json").write_text("mine")
    p = tmp_path / "abl.toml"
    p.write_text(fakes.FAKE_PIPELINE.format(output_dir=out.as_posix())
                 + '\n[[variant]]\nname = "ok"\n\n[[variant]]\nname = "../../../../victim"\n')
    before = _snapshot(tmp_path)
    with pytest.raises(ConfigError) as err:
        load_ablation(p, registry=fake_registry)
    assert "../../../../victim" in str(err.value) and "variant" in str(err.value)
    with pytest.raises(ConfigError):
        run_ablation(p, registry=fake_registry)
    assert _snapshot(tmp_path) == before


def test_run_dir_must_resolve_inside_output_dir_even_through_a_symlink(tmp_path):
    """Defence in depth: an existing name that is a symlink out of the output dir is not followed."""
    from pvslam_core.rundir import inside_dir

    out = tmp_path / "out"
    out.mkdir()
    (out / "link").symlink_to(tmp_path)
    assert inside_dir(out, out / "x")
    assert not inside_dir(out, out / "link" / "x")
    assert not inside_dir(out, tmp_path / "x")


# ------------------------------------------------------------------------------------------------ item 8 --
def _failing_variant_registry(fake_registry, monkeypatch):
    spec = fake_registry.get("dataset", "fake")
    good = spec.factory

    def factory(c, ctx):
        if c.frames == 13:
            raise ValueError("frames=13: corrupt sequence (test)")
        return good(c, ctx)

    monkeypatch.setattr(spec, "factory", factory)
    return fake_registry


def _ablation_file(tmp_path) -> Path:
    p = tmp_path / "abl.toml"
    p.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix())
                 + '\n[[variant]]\nname = "first"\n\n[[variant]]\nname = "broken"\n"dataset.frames" = 13\n'
                 + '\n[[variant]]\nname = "last"\n"frontend.keyframe_every" = 3\n')
    return p


def test_ablation_continues_after_a_failing_variant(tmp_path, fake_registry, monkeypatch):
    from pvslam_core.report import comparison_table

    reg = _failing_variant_registry(fake_registry, monkeypatch)
    results = run_ablation(_ablation_file(tmp_path), registry=reg)
    assert [n for n, _ in results] == ["first", "broken", "last"]
    assert results[0][1].metrics["timing"]["frames"] == 12
    assert results[2][1].metrics["timing"]["frames"] == 12  # the variant after the failure ran
    bad = results[1][1]
    assert "corrupt sequence" in bad.metrics["error"]
    base = Path(results[0][1].run_dir).parent
    rows = json.loads((base / "comparison.json").read_text())
    assert [r["variant"] for r in rows] == ["first", "broken", "last"]
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert "ValueError" in rows[1]["error"] and "corrupt sequence" in rows[1]["error"]
    assert rows[0]["error"] is None
    table = comparison_table(results)
    assert "broken" in table and "FAILED" in table and "corrupt sequence" in table


def test_ablation_cli_prints_table_and_exits_non_zero(tmp_path, fake_registry, monkeypatch, capsys):
    from pvslam_core import registry as r

    monkeypatch.setattr(r, "_REGISTRY", _failing_variant_registry(fake_registry, monkeypatch))
    assert main(["run", "-c", str(_ablation_file(tmp_path))]) == 1
    cap = capsys.readouterr()
    assert "first" in cap.out and "last" in cap.out and "FAILED" in cap.out
    assert "1 of 3 variants failed" in cap.err and "broken" in cap.err


# ------------------------------------------------------------------------------------------------ item 9 --
def test_non_utf8_config_is_a_clear_config_error(tmp_path, capsys):
    p = tmp_path / "latin1.toml"
    p.write_bytes('[run]\nname = "caf\xe9"\n'.encode("latin-1"))
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert str(p) in msg and "UTF-8" in msg and "line 2" in msg
    assert main(["config", "validate", str(p)]) == 2
    assert "UTF-8" in capsys.readouterr().err
    j = tmp_path / "c.json"
    j.write_bytes(b'{"run": {"name": "caf\xe9"}}')
    with pytest.raises(ConfigError, match="UTF-8"):
        load_config(j)


def test_config_path_that_is_a_folder(tmp_path):
    d = tmp_path / "conf.toml"
    d.mkdir()
    with pytest.raises(ConfigError, match="is a directory, not a config file"):
        load_config(d)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_output_dir_that_is_a_file(tmp_path, fake_config_file, capsys, fake_registry, monkeypatch):
    from pvslam_core import registry as r
    from pvslam_core.rundir import make_run_dir

    monkeypatch.setattr(r, "_REGISTRY", fake_registry)

    f = tmp_path / "runs"
    f.write_text("a file")
    with pytest.raises(NotADirectoryError) as err:
        make_run_dir(f, "x")
    assert str(f) in str(err.value) and "not a directory" in str(err.value) and "output_dir" in str(err.value)
    with pytest.raises(NotADirectoryError, match="not a directory"):
        make_run_dir(f / "below", "x")
    assert main(["run", "-c", str(fake_config_file), "-q"]) == 1
    err_text = capsys.readouterr().err
    assert "not a directory" in err_text and "File exists" not in err_text


def test_timestamps_in_messages_are_plain_numbers(tmp_path):
    from pvslam_core.datasets.base import DatasetError
    from pvslam_core.datasets.io import check_timestamps
    from pvslam_core.outputs.trajectory_io import TrajectoryFormatError, read_tum

    p = tmp_path / "t.txt"
    p.write_text("1.5 0 0 0 0 0 0 1\n1.25 0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError) as err:
        read_tum(p)
    assert "np.float64" not in str(err.value) and "1.25" in str(err.value) and "1.5" in str(err.value)
    with pytest.raises(DatasetError) as err2:
        check_timestamps(np.array([0.5, 0.5]), p)
    assert "np.float64" not in str(err2.value) and "0.5" in str(err2.value)


# ----------------------------------------------------------------------------------------------- item 12 --
def test_tomli_fallback_when_tomllib_is_missing(tmp_path):
    """Python 3.10 has no tomllib: every module that reads TOML falls back to tomli (simulated here)."""
    p = tmp_path / "c.toml"
    p.write_text('[loop]\nplugin = "none"\n')
    code = ("import sys, tomllib as real\n"
            "sys.modules['tomllib'] = None\n"  # `import tomllib` now raises ImportError, as on 3.10
            "sys.modules['tomli'] = real\n"
            "import pvslam_core.config as c, pvslam_core.catalog as cat\n"
            "assert c.tomllib is real and cat.tomllib is real\n"
            f"print(c.load_config({str(p)!r}).pipeline.loop.plugin, len(cat.load_catalog()) > 0)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["none", "True"]


def test_pyproject_declares_tomli_for_old_pythons():
    import tomllib

    root = Path(__file__).resolve().parents[2]
    deps = tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(d.replace(" ", "").startswith("tomli>=2;") and "python_version<\"3.11\"" in d.replace(" ", "")
               for d in deps), deps
    modules = [p for p in (root / "pvslam_core").rglob("*.py") if "import tomllib" in p.read_text()]
    for m in modules:  # every unconditional import has the fallback next to it
        assert "import tomli as tomllib" in m.read_text(), m
