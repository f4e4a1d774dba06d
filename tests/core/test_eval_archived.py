"""`pvslam eval RUN_DIR` on an archived/copied run whose dataset is gone (issue 15, item 5)."""
from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import pytest

import fakes
from pvslam_core.api import evaluate_run_dir, run_config
from pvslam_core.cli import main


@pytest.fixture
def archived_run(tmp_path, fake_registry, monkeypatch):
    """A run on an npz sequence with ground-truth revisits, copied elsewhere, and its sequence deleted."""
    from pvslam_npz import write_npz

    seq = write_npz(tmp_path / "seq.npz", fakes.FakeDataset(fakes.FakeDatasetConfig(frames=12)))
    spec = fake_registry.get("dataset", "npz")
    make = spec.factory

    def with_loops(c, ctx):  # the npz reader knows no revisits; give it two so loop GT must be archived too
        reader = make(c, ctx)
        info = reader.info
        reader.info = lambda: type(info())(**{**info().__dict__, "loop_pairs": [(10, 2), (11, 3)]})
        return reader

    monkeypatch.setattr(spec, "factory", with_loops)
    cfg = tmp_path / "npz.toml"
    cfg.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix())
                   .replace('plugin = "fake"\nframes = 12', f'plugin = "npz"\npath = "{seq.as_posix()}"'))
    res = run_config(cfg, registry=fake_registry)
    original = json.loads((Path(res.run_dir) / "metrics.json").read_text())
    copy = tmp_path / "archive" / "my-run"
    shutil.copytree(res.run_dir, copy)
    seq.unlink()
    (copy / "metrics.json").unlink()
    return copy, original


def test_archived_run_is_re_evaluated_from_its_own_files(archived_run, fake_registry):
    copy, original = archived_run
    assert (copy / "groundtruth.txt").is_file() and (copy / "groundtruth_loops.json").is_file()
    m = evaluate_run_dir(copy, registry=fake_registry)
    assert m["ate"]["rmse"] == pytest.approx(original["ate"]["rmse"], rel=1e-12)
    assert m["loops"]["num_gt_pairs"] == original["loops"]["num_gt_pairs"] == 2
    src = m["evaluation_sources"]
    assert src["trajectory"] == "groundtruth.txt (run directory)"
    assert src["loops"] == "groundtruth_loops.json (run directory)"
    assert "seq.npz" in src["dataset"] and "not available" in src["dataset"]
    assert json.loads((copy / "metrics.json").read_text())["ate"]["rmse"] == m["ate"]["rmse"]


def test_archived_run_whose_dataset_plugin_is_not_installed(archived_run, fake_registry):
    copy, original = archived_run
    cfg = json.loads((copy / "config.json").read_text())
    cfg["dataset"] = {"plugin": "someone_elses_reader", "path": "/nowhere"}
    (copy / "config.json").write_text(json.dumps(cfg))
    m = evaluate_run_dir(copy, registry=fake_registry)
    assert m["ate"]["rmse"] == pytest.approx(original["ate"]["rmse"], rel=1e-12)
    assert "someone_elses_reader" in m["evaluation_sources"]["dataset"]


def test_eval_cli_says_which_source_was_used(archived_run, fake_registry, monkeypatch, capsys):
    from pvslam_core import registry as r

    copy, original = archived_run
    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["eval", str(copy)]) == 0
    out = json.loads(buf.getvalue())  # stdout stays pure JSON
    assert out["ate"]["rmse"] == pytest.approx(original["ate"]["rmse"], rel=1e-12)
    err = capsys.readouterr().err
    assert "groundtruth.txt" in err and "run directory" in err and "dataset" in err


def test_run_without_any_ground_truth_says_so(archived_run, fake_registry):
    copy, _ = archived_run
    (copy / "groundtruth.txt").unlink()
    m = evaluate_run_dir(copy, registry=fake_registry)
    assert "ate" not in m
    assert m["evaluation_sources"]["trajectory"].startswith("none")
