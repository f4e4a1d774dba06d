"""`pvslam eval RUN_DIR` on an archived/copied run whose dataset is gone."""
from __future__ import annotations

import contextlib
import io
import json

import pytest

from pvslam_core.api import evaluate_run_dir
from pvslam_core.cli import main


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


# ------------------------------------------------------------------------------------ damaged run directories --
@pytest.mark.parametrize("name,text,found", [("metrics.json", "[1, 2]", "list"), ("config.json", '"a run"', "str"),
                                             ("metrics.json", "{not json", None)])
def test_eval_of_a_run_file_that_is_no_json_object_is_one_error_line(archived_run, fake_registry, monkeypatch,
                                                                     capsys, name, text, found):
    from pvslam_core import registry as r

    copy, _ = archived_run
    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    (copy / name).write_text(text)
    assert main(["eval", str(copy)]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    err = err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pvslam: error: ") and str(copy / name) in err[0], err
    assert (f"expected a JSON object, found a JSON {found}" if found else "not valid JSON") in err[0]
    assert (copy / name).read_text() == text  # left as it was


@pytest.mark.parametrize("text,why", [("[[0, 5]]", "expected a JSON object, found a JSON list"),
                                      ('{"pairs": [[0, "5"]]}', "integer frame indices"),
                                      ('{"pairs": 3}', "integer frame indices")])
def test_eval_with_loop_ground_truth_of_another_shape_is_one_error_line(archived_run, fake_registry, monkeypatch,
                                                                         capsys, text, why):
    from pvslam_core import registry as r

    copy, _ = archived_run
    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    (copy / "groundtruth_loops.json").write_text(text)
    assert main(["eval", str(copy)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pvslam: error: ") and "groundtruth_loops.json" in err[0], err
    assert why in err[0]


def test_eval_without_trajectory_fails_and_reports_no_old_ate(archived_run, fake_registry, monkeypatch, capsys):
    from pvslam_core import registry as r

    copy, _ = archived_run
    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    evaluate_run_dir(copy, registry=fake_registry)
    before = (copy / "metrics.json").read_text()
    assert "ate" in json.loads(before)
    (copy / "trajectory.txt").unlink()
    assert main(["eval", str(copy)]) == 1
    out, err = capsys.readouterr()
    assert out == "" and "ate" not in out
    assert err.startswith("pvslam: error: ") and "trajectory.txt not found" in err and len(err.splitlines()) == 1
    assert (copy / "metrics.json").read_text() == before  # a failed eval writes nothing


def test_trajectory_metrics_that_cannot_be_recomputed_are_removed(archived_run, fake_registry):
    copy, _ = archived_run
    assert "ate" in evaluate_run_dir(copy, registry=fake_registry)
    (copy / "groundtruth.txt").unlink()  # the ATE of metrics.json no longer has its ground truth here
    m = evaluate_run_dir(copy, registry=fake_registry)
    saved = json.loads((copy / "metrics.json").read_text())
    assert "ate" not in m and "ate" not in saved and "rpe" not in saved
    assert "timing" in saved  # what the pipeline wrote stays
