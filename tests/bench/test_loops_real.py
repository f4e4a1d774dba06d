"""The loop detectors on real frames (bench/loops_real.py): no false loop on any KITTI excerpt (none revisits a
place) and precision 1.0, recall >= 0.8 on a revisit built from KITTI 00 frames, for the classical detector (the
default) and DeiT, each with its geometric verification, at the processing size of configs/kitti.toml.  The
frames are subsampled (DeiT's forward pass is the cost) with the temporal exclusion scaled to keep its distance in
frames.  Skipped without ../shared."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import loops_real  # noqa: E402

# per excerpt: keyframe stride (frames), exclude_recent (keyframes)
EXCERPTS = {"classical": {"00": (1, 20), "06": (1, 20), "01": (1, 20)},
            "deit": {"00": (4, 10), "06": (2, 10), "01": (2, 10)}}
REVISITS = {"classical": (2, 21, 4, None), "deit": (3, 22, 6, 130)}  # first stride, second start/stride, end


@pytest.fixture
def kitti(shared_dir, monkeypatch):
    path = shared_dir / "data" / "kitti-odometry"
    if not (path / "sequences" / "00" / "image_0").is_dir():
        pytest.skip(f"{path}: no KITTI excerpts")
    monkeypatch.setattr(loops_real, "KITTI", path)
    return path


def test_same_place_is_distance_and_heading():
    q0, turned = [0, 0, 0, 1], [0, np.sin(np.radians(20)), 0, np.cos(np.radians(20))]  # 40 degrees about y
    a = np.array([[0, 0, 0, *q0]], float)
    b = np.array([[0, 0, 4, *q0], [0, 0, 9, *q0], [0, 0, 11, *q0], [0, 0, 1, *turned]], float)
    assert loops_real.same_place(a, b).tolist() == [[True, True, False, False]]
    assert loops_real.same_place(a, b, radius_m=5.0).tolist() == [[True, False, False, False]]


@pytest.mark.parametrize("plugin", ["classical", "deit"])
@pytest.mark.parametrize("seq", ["00", "06", "01"])
def test_no_false_loop_on_a_real_excerpt(kitti, plugin, seq):
    stride, exclude = EXCERPTS[plugin][seq]
    r = loops_real.excerpt_report(plugin, seq, stride, exclude_recent=exclude)
    assert r["false_loops"] == []
    best = r["best_wrong"]  # the pair of different places that looks most alike: verification turns it down
    assert best["distance_m"] > loops_real.SAME_PLACE_M and not best["accepted"], best


@pytest.mark.parametrize("plugin", ["classical", "deit"])
def test_a_real_revisit_is_found_without_a_false_loop(kitti, plugin):
    first, start, step, end = REVISITS[plugin]
    r = loops_real.revisit_report(plugin, first, start, step, end)
    assert r["queries_with_a_revisit"] >= 15
    assert r["false_loops"] == [] and r["precision"] == 1.0
    assert r["recall"] >= 0.8, r["missed_frames"]


def _result(plugins=loops_real.PLUGINS, sequences=loops_real.SEQUENCES, accepted=False):
    def best(score):
        return {"frame_i": 9, "frame_j": 1, "score": score, "threshold": 0.75, "distance_m": 60.0,
                "accepted": accepted, "inliers": 0, "matches": 7}

    excerpts = [{"plugin": p, "sequence": q, "false_loops": [[9, 1]] if accepted and q == "06" else [],
                 "best_wrong": best(0.70 + 0.01 * k)} for p in plugins for k, q in enumerate(sequences)]
    revisits = [{"plugin": p, "queries_with_a_revisit": 35, "precision": 1.0, "recall": 0.9 + 0.05 * k}
                for k, p in enumerate(plugins)]
    return {"plugins": list(plugins), "sequences": list(sequences), "excerpts": excerpts, "revisits": revisits}


def test_the_figure_row_states_false_loops_the_closest_wrong_pair_and_the_revisit():
    r = _result()
    assert loops_real.report_problem(r) is None
    value, compared = loops_real.figure(r)
    assert value.startswith("`classical`: false loops 0 / 0 / 0, best wrong pair 0.720 against its threshold 0.750 "
                            "(rejected by verification); revisit precision 1.00, recall 0.90 (35 revisiting "
                            "keyframes); `deit`:")
    assert compared == "targets: no false loop on any excerpt; revisit precision 1.0, recall >= 0.8"
    assert "false loops 0 / 1 / 0" in loops_real.figure(_result(accepted=True))[0]


def test_a_detector_that_scored_no_wrong_pair_still_gets_its_figure_row():
    r = _result()
    for e in r["excerpts"]:
        if e["plugin"] == "deit":
            e["best_wrong"] = None
    value, _ = loops_real.figure(r)
    assert "`deit`: false loops 0 / 0 / 0, no pair of different places scored; revisit precision 1.00" in value
    assert "`classical`: false loops 0 / 0 / 0, best wrong pair 0.720" in value


@pytest.mark.parametrize("kw", [{"plugins": ("classical",)}, {"sequences": ("00", "06")}])
def test_a_result_without_every_detector_or_excerpt_is_no_figure(kw):
    assert "not every detector" in loops_real.report_problem(_result(**kw))
