"""The run summary on the console: a metric that is undefined says n/a and why, not nan or a meaningless 0."""
from __future__ import annotations

import json
import math

import torch

from pvslam_core.report import comparison_table, summary_lines
from pvslam_core.types import RunResult


def _result(metrics: dict, run_dir=None) -> RunResult:
    z = torch.zeros(0, 7, dtype=torch.float64)
    return RunResult(str(run_dir) if run_dir else None, torch.zeros(0, dtype=torch.float64), z,
                     torch.zeros(0, dtype=torch.int64), z, metrics=metrics)


def test_loops_without_detections_or_true_loops_say_why():
    lp = {"precision": math.nan, "recall": math.nan, "num_detected": 0, "num_gt_events": 0}
    (line,) = [ln for ln in summary_lines(_result({"loops": lp})) if ln.startswith("loops:")]
    assert line == ("loops: 0 detected  precision n/a (no loop detected)  "
                    "recall n/a (no true loop among the frames run)"), line
    lp = {"precision": 0.5, "recall": 1.0, "num_detected": 2, "num_gt_events": 1}
    assert "precision 0.50  recall 1.00" in "\n".join(summary_lines(_result({"loops": lp})))


def _panoptic_run(tmp_path, names: dict[int, str]):
    (tmp_path / "panoptic").mkdir()
    cats = [{"id": i, "name": n, "isthing": 0, "color": [1, 2, 3]} for i, n in names.items()]
    (tmp_path / "panoptic" / "segments.json").write_text(json.dumps({"annotations": [], "categories": cats}))
    per = {"1": {"name": "road", "pq": 0.0}, "2": {"name": "car", "pq": 0.0}}
    return {"panoptic": {"pq": 0.0, "vpq": 0.0, "pq_detail": {"per_category": per}}}


def test_pq_against_labels_of_other_categories_is_not_a_zero(tmp_path):
    m = _panoptic_run(tmp_path, {1: "person", 2: "bicycle"})  # e.g. COCO's ids against the dataset's labels
    (line,) = [ln for ln in summary_lines(_result(m, tmp_path)) if ln.startswith("PQ")]
    assert line.startswith("PQ: n/a (the segmenter's categories are not the labels'") and "'person'" in line, line


def test_pq_of_the_same_categories_is_printed(tmp_path):
    m = _panoptic_run(tmp_path, {1: "road", 2: "car"})
    assert "PQ: 0.000  VPQ: 0.000" in summary_lines(_result(m, tmp_path))


def test_the_comparison_table_shows_no_nan():
    table = comparison_table([("a", _result({"panoptic": {"pq": math.nan, "vpq": 0.25}}, "/runs/x/a"))])
    assert "nan" not in table and "n/a" in table and "0.250" in table


def test_revisits_beyond_the_frames_run_are_no_true_loops(tmp_path):
    """A run of 10 frames of a sequence whose revisits start at frame 440 has no true loop: recall is undefined
    (n/a), not 0."""
    import numpy as np

    from pvslam_core.config import PipelineConfig
    from pvslam_core.outputs.loops_io import write_loops
    from pvslam_core.outputs.trajectory_io import write_tum
    from pvslam_core.run_outputs import evaluate_saved_run

    poses = np.tile([0.0, 0, 0, 0, 0, 0, 1], (10, 1))
    write_tum(tmp_path / "trajectory.txt", np.arange(10) * 0.1, poses)
    write_loops(tmp_path / "loops.json", [])
    (tmp_path / "groundtruth_loops.json").write_text(json.dumps({"pairs": [[440, 0], [441, 1]]}))
    pcfg = PipelineConfig()
    pcfg.outputs.plots = False
    m = evaluate_saved_run(tmp_path, None, {}, pcfg=pcfg)
    assert m["loops"]["num_gt_events"] == 0 and math.isnan(m["loops"]["recall"])
    assert "recall n/a (no true loop among the frames run)" in "\n".join(summary_lines(_result(m)))
