"""The checkpoint shipped in the package (the reduced PanopticFPN trained on the synthetic scenarios): it loads
strictly as the plugin's default and segments a short clip of held-out seeds above a PQ bound."""
from __future__ import annotations

import torch

from pvslam_plugins.segmenters.panoptic_fpn.checkpoint import read_weights
from pvslam_plugins.segmenters.panoptic_fpn.data import render_samples, synthetic_category_set
from pvslam_plugins.segmenters.panoptic_fpn.evaluate import evaluate
from pvslam_plugins.segmenters.panoptic_fpn.segmenter import SHIPPED_WEIGHTS, PanopticFPNSegmenterConfig, build_model
from pvslam_plugins.segmenters.panoptic_fpn.train import TrainConfig

# the shipped file scores well above this on the clip; the bound leaves room for the last-bit differences of
# another CPU, not for a broken model (an untrained one scores 0)
PQ_BOUND = 0.55


def test_shipped_checkpoint_is_small_and_loads_strictly():
    assert SHIPPED_WEIGHTS.is_file() and SHIPPED_WEIGHTS.stat().st_size <= 25 * 2 ** 20
    wf = read_weights(SHIPPED_WEIGHTS)
    assert wf.kind == "pvslam" and wf.categories["name"] == "synthetic"
    model = build_model(PanopticFPNSegmenterConfig())  # the default: preset reduced, the shipped weights
    assert model.categories == synthetic_category_set()
    assert set(model.state_dict()) == set(wf.state_dict)
    assert all(torch.equal(v, wf.state_dict[k].to(v.dtype)) for k, v in model.state_dict().items())


def test_shipped_checkpoint_segments_held_out_seeds():
    held_out = 100
    assert held_out not in TrainConfig().train_seeds
    samples = render_samples("moving_vehicles", held_out, 3) + render_samples("indoor_handheld", held_out, 2) + \
        render_samples("driving_city", held_out, 2)
    res = evaluate(build_model(PanopticFPNSegmenterConfig()), samples, min_gt_area=0)
    p = res["pq"]
    assert p["pq"] > PQ_BOUND, (p["pq"], p["things"], p["stuff"])
    cars = p["per_category"][11]
    assert cars["tp"] >= 5 and cars["sq"] > 0.6  # vehicles, the classes dynamic masking needs, are found
