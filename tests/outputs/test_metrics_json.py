"""metrics.json writing: strict JSON, atomic, merging."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

from pvslam_core.outputs.metrics import MetricsFile, to_jsonable, write_json_atomic


def test_write_json_atomic_strict_json(tmp_path):
    p = tmp_path / "m.json"
    write_json_atomic(p, {"a": np.float32(1.5), "b": np.arange(3), "c": float("nan"), "d": (1, 2), 3: torch.tensor(2.0),
                          "e": {"inf": float("inf"), "ok": True, "none": None}})
    text = p.read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text)
    assert data == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": [1, 2], "3": 2.0, "e": {"inf": None, "ok": True, "none": None}}
    assert os.listdir(tmp_path) == ["m.json"]


def test_write_json_failure_keeps_old_file(tmp_path):
    p = tmp_path / "m.json"
    write_json_atomic(p, {"a": 1})
    with pytest.raises(TypeError):
        write_json_atomic(p, {"a": object()})
    assert json.loads(p.read_text()) == {"a": 1}
    assert os.listdir(tmp_path) == ["m.json"]


def test_metrics_file_merges_and_reloads(tmp_path):
    p = tmp_path / "metrics.json"
    m = MetricsFile(p)
    m.update(timing={"fps": 10.0})
    m.update({"ate": {"rmse": 0.1, "error": "old"}}, frames=5)
    m.update(ate={"rmse": 0.2})  # top-level keys are replaced
    assert json.loads(p.read_text()) == {"timing": {"fps": 10.0}, "ate": {"rmse": 0.2}, "frames": 5}
    m2 = MetricsFile(p)  # an existing file is extended
    m2.deep_update(timing={"seconds": 3.0})
    assert m2["timing"] == {"fps": 10.0, "seconds": 3.0}
    assert json.loads(p.read_text())["frames"] == 5


def test_metrics_file_refuses_to_clobber_bad_file(tmp_path):
    p = tmp_path / "metrics.json"
    p.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        MetricsFile(p)
    p.write_text("[1, 2]")
    with pytest.raises(ValueError, match="JSON object"):
        MetricsFile(p)


def test_to_jsonable_dataclass():
    from pvslam_core.types import LoopCandidate

    assert to_jsonable(LoopCandidate(3, 1, 0.5)) == {"i": 3, "j": 1, "score": 0.5, "verified": None, "inliers": 0}
    assert math.isnan(float("nan")) and to_jsonable([float("-inf")]) == [None]
