"""bench_domain: held-out-domain and plain frame sets, every model scored on each, one table per set."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_domain as B  # noqa: E402


def test_frame_sets_render_the_held_out_domain_and_refuse_training_seeds():
    sets = B.frame_sets([400], [100], 1, scenarios=["indoor_handheld"], width=96, height=72)
    (held,), (seen,), (plain,) = sets[B.HELD_OUT], sets[B.SEEN], sets[B.PLAIN]
    assert held.name.endswith("/heldout") and seen.name.endswith("/train")
    assert "/heldout" not in plain.name and "/train" not in plain.name
    assert held.image.shape == plain.image.shape == (3, 72, 96)
    assert not torch.equal(held.image, plain.image) and not torch.equal(held.image, seen.image)
    with pytest.raises(ValueError, match=r"\[1\] are training seeds"):
        B.frame_sets([1], [100], 1, scenarios=["indoor_handheld"])


def test_compare_scores_each_model_on_each_set_and_tables_name_them(single_torch_thread):
    from pvslam_plugins.segmenters.panoptic_fpn.config import preset
    from pvslam_plugins.segmenters.panoptic_fpn.data import synthetic_category_set
    from pvslam_plugins.segmenters.panoptic_fpn.model import PanopticFPN

    sets = B.frame_sets([400], [100], 1, scenarios=["moving_vehicles"])
    shipped = B.load_models([])["shipped"]
    torch.manual_seed(0)
    untrained = PanopticFPN(preset("reduced"), synthetic_category_set()).eval()
    res = B.compare({"shipped": shipped, "again": shipped, "untrained": untrained}, sets)
    assert set(res) == {B.HELD_OUT, B.SEEN, B.PLAIN}
    for by_model in res.values():
        assert by_model["shipped"]["pq"]["pq"] == by_model["again"]["pq"]["pq"]
    assert res[B.PLAIN]["shipped"]["pq"]["pq"] > res[B.PLAIN]["untrained"]["pq"]["pq"] + 0.2
    table = B.format_tables(res)
    assert table.count("| shipped |") == 3 and "### heldout (1 frames)" in table and "### plain (1 frames)" in table
    with pytest.raises(SystemExit, match="NAME=PATH"):
        B.load_models(["no-equals-sign"])


def _result(**kw):
    p = {"pq": 0.412, "things": {"pq": 0.45}, "stuff": {"pq": 0.40}}
    r = {"models": ["shipped"], "set": B.FIGURE_SET, "heldout_seeds": list(B.seeds.load().sets[B.FIGURE_SET]),
         "plain_seeds": [100, 101], "frames_per_sequence": B.FRAMES,
         "results": {s: {"shipped": {"pq": p}} for s in (B.HELD_OUT, B.SEEN, B.PLAIN)},
         "vps": {"scenarios": ["moving_vehicles", "busy_street"], "frames": 80,
                 "vpq": {"none": 0.301, "warp_iou": 0.352, "fusion": 0.348}}}
    return {**r, **kw}


def test_the_figure_is_the_shipped_weights_on_the_ledger_set_and_names_the_target():
    assert B.report_problem(_result()) is None
    for bad in (_result(models=["a=x.pth"]), _result(set=None), _result(heldout_seeds=[400, 401]),
                _result(frames_per_sequence=2), _result(vps=None)):
        assert "run with --set segmenter --vps" in B.report_problem(bad)
    value, compared = B.figure(_result())
    assert value.startswith("PQ (things / stuff): held-out families and sizes **41.2 (45.0 / 40.0)**")
    assert "validation seeds 100, 101 41.2" in value
    assert value.endswith("(moving_vehicles and busy_street, 80 frames): `fusion` 34.8, `warp_iou` 35.2, per-frame "
                          "ids 30.1")
    assert compared == "targets: PQ >= 55 and VPQ `fusion` >= `warp_iou` on the held-out families"


def test_vps_section_runs_each_scenario_and_seed_in_the_held_out_looks(monkeypatch):
    from bench import bench_vps

    calls = []

    def fake(scenario, seed, frames, fusion_cfg, domain):
        calls.append((scenario, seed, frames, domain))
        return {"scenario": scenario, "seed": seed, "heads": {h: {"vpq": 0.1 * seed} for h in bench_vps.HEADS}}

    monkeypatch.setattr(bench_vps, "run_sequence", fake)
    out = B.vps_section([1, 3], frames=5)
    assert calls == [(sc, s, 5, "heldout") for sc in bench_vps.SCENARIOS for s in (1, 3)]
    assert out["vpq"]["fusion"] == pytest.approx(0.2) and len(out["runs"]) == 4


def test_set_reads_the_ledger_seeds(monkeypatch, tmp_path):
    seen = {}
    monkeypatch.setattr(B, "frame_sets", lambda held, plain, frames: seen.update(held=held, frames=frames) or {})
    monkeypatch.setattr(B, "load_models", lambda specs: {})
    monkeypatch.setattr(B, "vps_section", lambda held: {"held": held})
    assert B.main(["--set", "segmenter", "--vps", "--json", str(tmp_path / "d.json")]) == 0
    held = list(B.seeds.load().sets["segmenter"])
    assert seen == {"held": held, "frames": B.FRAMES}
    r = B.provenance.read_json(tmp_path / "d.json")
    assert r["vps"] == {"held": held} and B.report_problem(r) is None
    with pytest.raises(SystemExit):
        B.main(["--set", "segmenter", "--vps", "--model", "a=b.pth", "--json", str(tmp_path / "e.json")])
