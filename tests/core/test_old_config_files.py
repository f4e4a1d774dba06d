"""Config files and run directories of the release before the knobs were pruned still load: a retired key with its
old default loads (and is gone from the resolved config), any other value is an error naming the key; the
resolved ``config.json`` of an old run (``data/config_before_one_house.json``, every key of the default pipeline)
loads to the same values of the run, dataset, segmenter, loop, VPS, outputs and evaluation sections."""
import json
from pathlib import Path

import pytest

from pvslam_core.config import ConfigError, load_config

OLD = json.loads((Path(__file__).parent / "data" / "config_before_one_house.json").read_text())

# table -> {retired key: the value the code now fixes}
RETIRED = {
    "outputs": {"ply_edge_ratio": 1.5, "ply_neighbours": 2, "ply_consistency": 0.05},
    "loop": {"orb_features": 500, "store_max_side": 640, "jpeg_quality": 90, "feature_cache": 256, "ratio": 0.8,
             "cross_check": True, "ransac_threshold_px": 1.5, "adaptive_neighbours": 2, "adaptive_floor": 0.5,
             "adaptive_min_spread": 0.9, "thumbnail_size": [16, 12], "hog_cells": [4, 4], "hog_bins": 8,
             "thumbnail_weight": 0.5},
    "vps": {"flow_preset": "ultrafast", "flow_max_side": 320, "rigid_stuff": True, "splat": "bilinear",
            "warp_max_side": None},
}
# table -> keys added since (a 320x240 input is under the default max_pixels: the old run's frames are unchanged)
NEW_KEYS = {"dataset": ("max_pixels", "domain")}
OTHER = {"ply_edge_ratio": 2.0, "ply_neighbours": 3, "ply_consistency": 0.1, "orb_features": 1000,
         "store_max_side": 320, "jpeg_quality": 80, "feature_cache": 16, "ratio": 0.7, "cross_check": False,
         "ransac_threshold_px": 1.0, "adaptive_neighbours": 0, "adaptive_floor": 0.4, "adaptive_min_spread": 0.8,
         "thumbnail_size": [8, 6], "hog_cells": [2, 2], "hog_bins": 4, "thumbnail_weight": 0.3,
         "flow_preset": "fast", "flow_max_side": 160, "rigid_stuff": False, "splat": "nearest", "warp_max_side": 160}


@pytest.mark.parametrize("table, key", [(t, k) for t, keys in RETIRED.items() for k in keys])
def test_retired_key_loads_at_its_old_default_and_refuses_another_value(table, key):
    cfg = load_config({table: {key: RETIRED[table][key]}})
    assert key not in cfg.to_dict()[table]
    with pytest.raises(ConfigError, match=f"'{key}' was retired: its setting is now fixed at"):
        load_config({table: {key: OTHER[key]}})


def test_deit_and_fusion_retired_keys():
    deit = {"loop.plugin": "deit", "loop.weights": None}
    cfg = load_config(None, {**deit, "loop.crop_pct": 0.875, "loop.whiten_shrinkage": 0.1,
                             "loop.pca_refit_growth": 1.25, "loop.pca_freeze_after": None, "loop.orb_features": 500})
    assert not {"crop_pct", "whiten_shrinkage", "pca_refit_growth", "pca_freeze_after"} & set(cfg.to_dict()["loop"])
    with pytest.raises(ConfigError, match="'pca_freeze_after' was retired"):
        load_config(None, {**deit, "loop.pca_freeze_after": 100})
    fusion = {"segmenter.plugin": "panoptic_fpn", "vps.plugin": "fusion"}
    cfg = load_config(None, {**fusion, "vps.flow_preset": "ultrafast", "vps.flow_max_side": 320, "vps.splat": "bilinear"})
    assert "splat" not in cfg.to_dict()["vps"]
    with pytest.raises(ConfigError, match="'splat' was retired"):
        load_config(None, {**fusion, "vps.splat": "nearest"})


def test_an_old_run_directory_config_loads_to_the_same_settings(tmp_path):
    path = tmp_path / "config.json"
    path.write_text(json.dumps(OLD))
    new = load_config(path).to_dict()
    for table in ("run", "dataset", "segmenter", "loop", "vps", "outputs", "evaluation"):
        kept = {k: v for k, v in OLD[table].items() if k not in RETIRED.get(table, {})}
        added = NEW_KEYS.get(table, ())  # keys that did not exist then, at their defaults
        assert {k: v for k, v in new[table].items() if k not in added} == kept, table
    assert new == load_config(None).to_dict()  # the old defaults are today's defaults
