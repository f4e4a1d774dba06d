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
         "results": {s: {"shipped": {"pq": p}} for s in (B.HELD_OUT, B.SEEN, B.PLAIN)}}
    return {**r, **kw}


def test_the_figure_is_the_shipped_weights_on_the_ledger_set_and_names_the_target():
    assert B.report_problem(_result()) is None
    for bad in (_result(models=["a=x.pth"]), _result(set=None), _result(heldout_seeds=[400, 401]),
                _result(frames_per_sequence=2)):
        assert "run with --set segmenter" in B.report_problem(bad)
    value, compared = B.figure(_result())
    assert value.startswith("PQ (things / stuff): held-out families and sizes **41.2 (45.0 / 40.0)**")
    assert "validation seeds 100, 101 41.2" in value and compared == "target: PQ >= 55 on the held-out families"


def test_set_reads_the_ledger_seeds(monkeypatch, tmp_path):
    seen = {}
    monkeypatch.setattr(B, "frame_sets", lambda held, plain, frames: seen.update(held=held, frames=frames) or {})
    monkeypatch.setattr(B, "load_models", lambda specs: {})
    assert B.main(["--set", "segmenter", "--json", str(tmp_path / "d.json")]) == 0
    assert seen == {"held": list(B.seeds.load().sets["segmenter"]), "frames": B.FRAMES}
    assert B.report_problem(B.provenance.read_json(tmp_path / "d.json")) is None
