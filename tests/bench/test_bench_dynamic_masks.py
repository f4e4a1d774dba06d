"""bench_dynamic_masks counts what the masks take: per ground-truth category the static pixels removed, the moving
pixels kept and the share of static confidence lost, against a hand-made keyframe whose answer is written here."""
from __future__ import annotations

import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_dynamic_masks as B  # noqa: E402


def test_tally_counts_false_dynamic_missed_and_lost_confidence():
    t = B.Tally()
    h, w = 2, 4
    moving = torch.tensor([[False, False, True, True], [False, False, False, False]])
    cat = torch.tensor([[1, 1, 11, 11], [3, 3, 3, 3]])  # road, road, car, car / building x 4
    in_thing = torch.tensor([[False, True, True, True], [False, False, False, False]])
    t.kf[7] = (moving, cat, in_thing)
    dyn = torch.tensor([[[1.0, 1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]]])  # both road pixels, one car pixel
    conf = torch.full((1, h, w), 0.5)
    weight = torch.where(dyn > 0, torch.full_like(conf, 0.1), conf)
    t.observe([(7, 8)], dyn, conf, weight)
    t.observe([(99, 7)], dyn, conf, weight)  # a keyframe without ground truth is not counted
    s = B.summarise(t, {1: "road", 3: "building", 11: "car"})
    road, car, bldg = s["categories"]["road"], s["categories"]["car"], s["categories"]["building"]
    assert road["false_dyn"] == 1.0 and road["by_thing"] == 0.5 and road["missed"] is None
    assert car["missed"] == 0.5 and car["static_px"] == 0
    assert bldg["false_dyn"] == 0.0
    # static confidence 6 x 0.5 = 3.0, of which the two road pixels lost 2 x 0.4
    assert abs(s["w_lost_static"] - 0.8 / 3.0) < 1e-6 and abs(s["w_lost_scale_bearing"] - 0.8 / 3.0) < 1e-6  # float32
    assert abs(s["all_pixels"]["removed"] - 3 / 8) < 1e-9 and abs(s["all_pixels"]["removed_in_thing"] - 2 / 8) < 1e-9


def test_trace_follows_each_keyframe_from_its_edges_latest_masks():
    t = B.Tally()
    moving = torch.tensor([[True, True, False, False]])  # half the view moves
    cat = torch.ones(1, 4, dtype=torch.int64)
    none = torch.zeros(1, 4, dtype=torch.bool)
    t.kf[5], t.frame[5] = (moving, cat, none), 40
    t.kf[3], t.frame[3] = (torch.zeros(1, 4, dtype=torch.bool), cat, none), 10  # nothing moves there
    conf = torch.ones(2, 1, 4)
    held = torch.tensor([[[1.0, 1.0, 0.0, 0.0]], [[1.0, 0.0, 0.0, 0.0]]])
    t.observe([(5, 3), (5, 6)], held, conf, conf)
    flipped = torch.tensor([[[0.0, 0.0, 1.0, 1.0]], [[0.0, 0.0, 0.0, 1.0]]])  # later: the background instead
    t.observe([(5, 3), (3, 5)], flipped, conf, conf)
    rows = B.trace(t)
    assert [r["frame"] for r in rows] == [10, 40]
    assert rows[0] == {"frame": 10, "moving": 0.0, "held": None, "false": 0.25}
    # keyframe 5: edge (5, 3) now holds none of the mover and marks both static pixels; (5, 6) kept its first mask
    assert rows[1]["moving"] == 0.5 and rows[1]["held"] == (0.0 + 0.5) / 2 and rows[1]["false"] == (0.5 + 0.0) / 2


def _run(scenario, seed, segm, rmse):
    return {"scenario": scenario, "seed": seed, "segmenter": segm, "ate": {"rmse": rmse}}


def test_each_segmenter_is_compared_with_none_on_the_same_sequence_and_worse_runs_are_counted():
    runs = [_run("mv", "1", "panoptic_fpn", 2.0), _run("mv", "1", "none", 1.0),
            _run("mv", "2", "panoptic_fpn", 1.04), _run("mv", "2", "none", 1.0), _run("mv", "2", "labels", 0.5),
            _run("mv", "3", "panoptic_fpn", 9.0)]  # no none run on seed 3: left out
    rows = {r["segmenter"]: r for r in B.against_none(runs)}
    assert set(rows) == {"panoptic_fpn", "labels"}
    p = rows["panoptic_fpn"]
    assert p["runs"] == ["mv:1", "mv:2"] and p["ratios"] == [2.0, 1.04]
    assert p["worse"] == 1  # 1.04 is within the 5 % a run may differ by
    assert abs(p["mean_ate"] - 1.52) < 1e-12 and p["mean_ate_none"] == 1.0
    assert rows["labels"]["worse"] == 0 and rows["labels"]["ratios"] == [0.5]
    assert B.against_none([_run("mv", "1", "none", 1.0)]) == []


def test_the_domain_option_reaches_the_run_config(monkeypatch, tmp_path):
    seen = []
    monkeypatch.setattr(B, "run_one", lambda sc, sd, segm, frames, out, ov: seen.append(ov) or
                        {"ate": {"rmse": 1.0}, "scenario": sc, "seed": sd, "segmenter": segm})
    monkeypatch.setattr(B, "print_summary", lambda *a: None)
    monkeypatch.setattr(B.provenance, "check", lambda path: {})
    monkeypatch.setattr(B.provenance, "write_json", lambda *a: None)
    assert B.main(["--runs", "moving_vehicles:5", "--segmenters", "none", "--domain", "heldout",
                   "--json", str(tmp_path / "x.json")]) == 0
    assert seen == [['dataset.domain="heldout"']]
