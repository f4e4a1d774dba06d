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
