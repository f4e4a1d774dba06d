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


def test_scenario_means_and_the_share_of_the_oracles_gain():
    runs = [_run("moving_vehicles", "1", "none", 2.0), _run("moving_vehicles", "1", "labels", 1.0),
            _run("moving_vehicles", "1", "panoptic_fpn", 1.5),
            _run("moving_vehicles", "2", "none", 4.0), _run("moving_vehicles", "2", "labels", 1.0),
            _run("moving_vehicles", "2", "panoptic_fpn", 4.5),
            _run("moving_vehicles", "3", "none", 9.0),  # not run by every segmenter: left out of the means
            _run("driving_block", "1", "none", 0.5), _run("driving_block", "1", "labels", 0.4),
            _run("driving_block", "1", "panoptic_fpn", 0.6)]
    scen = B.per_scenario(runs)
    assert scen["moving_vehicles"] == {"none": 3.0, "labels": 1.0, "panoptic_fpn": 3.0}
    assert scen["driving_block"] == {"none": 0.5, "labels": 0.4, "panoptic_fpn": 0.6}
    assert B.oracle_share(scen, "panoptic_fpn") == 0.0  # no better than none on the moving scenario's mean
    scen["moving_vehicles"]["panoptic_fpn"] = 1.5
    assert B.oracle_share(scen, "panoptic_fpn") == 0.75
    scen["moving_vehicles"]["panoptic_fpn"] = 4.0
    assert B.oracle_share(scen, "panoptic_fpn") == -0.5  # worse than none
    scen["moving_vehicles"]["labels"] = 3.5  # the oracle gains nothing: no share
    assert B.oracle_share(scen, "panoptic_fpn") is None
    assert B.oracle_share({"driving_block": scen["driving_block"]}, "panoptic_fpn") is None  # no moving scenario


def test_the_report_runs_the_ledgers_segmenter_seeds_in_held_out_looks_and_renders_one_figure(monkeypatch, tmp_path):
    seeds = B.seeds.load().sets["segmenter"]
    seen, written = [], {}
    ate = {"panoptic_fpn": 1.2, "labels": 0.5, "none": 1.0}

    def run_one(sc, sd, segm, frames, out, ov):
        seen.append((sc, sd, segm, frames, ov))
        return {"ate": {"rmse": ate[segm] * (2.0 if sc == "driving_block" else 1.0)}, "scenario": sc, "seed": sd,
                "segmenter": segm}

    monkeypatch.setattr(B, "run_one", run_one)
    monkeypatch.setattr(B, "print_summary", lambda *a: None)
    monkeypatch.setattr(B.provenance, "check", lambda path: {})
    monkeypatch.setattr(B.provenance, "write_json", lambda path, data, prov: written.update(data))
    assert B.main(["--report", "--json", str(tmp_path / "x.json")]) == 0
    assert {(sc, int(sd)) for sc, sd, *_ in seen} == {(sc, s) for sc in B.REPORT_SCENARIOS for s in seeds}
    assert all(segm in ("panoptic_fpn", "labels", "none") and frames == 0 and ov == ['dataset.domain="heldout"']
               for _, _, segm, frames, ov in seen) and len(seen) == 3 * len(B.REPORT_SCENARIOS) * len(seeds)
    assert written["report"] and B.report_problem(written) is None
    assert written["scenarios"]["driving_block"] == {"panoptic_fpn": 2.4, "labels": 1.0, "none": 2.0}
    assert abs(written["oracle_share"]["panoptic_fpn"] - (-0.4)) < 1e-9  # (1.0 - 1.2) / (1.0 - 0.5)
    value, compared = B.figure(written)
    n = len(B.REPORT_SCENARIOS) * len(seeds)
    assert f"**{n} of {n}** runs" in value and "driving_block 2.400 / 1.000 / 2.000" in value
    assert "it reaches -40 % of the oracle's gain" in value and "no run worse than `none`" in compared
    # a part of the report, or one measured with overrides, is not the report
    partial = dict(written, runs=[r for r in written["runs"] if r["scenario"] != "busy_street"])
    assert "busy_street:" in B.report_problem(partial)
    assert "the oracle itself is no better than `none`" in B.figure(dict(written, oracle_share={"panoptic_fpn": None}))[0]
    assert "not the held-out report" in B.report_problem(dict(written, overrides=["x=1"]))
