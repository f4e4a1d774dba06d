"""The flow frontend's configuration: sixteen nested settings; the flat keys of earlier releases load (renamed) or, where
the setting became a constant of the code, load only at that constant's value and otherwise fail naming the key."""
import json

import pytest
from pydantic import BaseModel, ValidationError

from pvslam_core.config_base import retired_value
from pvslam_core.slam.dynamic_config import DynamicMaskingConfig
from pvslam_plugins.frontends.flow import dynamic_masking, frontend, pair_flow, road_prior, track_starts
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig

# the flat keys of the previous release, at values other than the defaults, and where each lands now
OLD_FLAT = {
    "preset": ("medium", "dis.preset"),
    "flow_scale": (1.0, "dis.scale"),
    "finest_scale": (1, "dis.finest_scale"),
    "flow_threads": (1, "dis.threads"),
    "keyframe_thresh": (3.0, "keyframes.flow_thresh"),
    "keyframe_min_coverage": (0.6, "keyframes.min_coverage"),
    "road_plane": (False, "road.enabled"),
    "road_depth_weight": (2.0, "road.depth_weight"),
    "road_distance_weight": (50.0, "road.distance_weight"),
    "dynamic_masking": (False, "dynamic.enabled"),
    "panoptic_offset": (7.0, "dynamic.panoptic_offset"),
    "convention": ("pvo_code", "dynamic.convention"),
    "dynamic_thresh": (1.5, "dynamic.thresh"),
    "max_dynamic_fraction": (0.5, "dynamic.max_fraction"),
    "vote_thresh": (0.7, "dynamic.vote_thresh"),
}

# retired key -> the constant that holds its value now
CONSTANTS = {
    "fb_sigma": (pair_flow, "FB_SIGMA"), "fb_fail_px": (pair_flow, "FB_FAIL_PX"),
    "photo_sigma": (pair_flow, "PHOTO_SIGMA"), "texture_tau": (pair_flow, "TEXTURE_TAU"),
    "texture_quantile": (pair_flow, "TEXTURE_QUANTILE"), "weighted_pooling": (pair_flow, "WEIGHTED_POOLING"),
    "min_texture_std": (frontend, "MIN_TEXTURE_STD"), "max_fb_fail_fraction": (frontend, "MAX_FB_FAIL_FRACTION"),
    "reuse_track_flow": (frontend, "REUSE_TRACK_FLOW"), "use_reprojection_init": (frontend, "USE_REPROJECTION_INIT"),
    "init_min_flow": (frontend, "INIT_MIN_FLOW"), "init_compare_min_gap": (frontend, "INIT_COMPARE_MIN_GAP"),
    "track_velocity_init": (track_starts, "TRACK_VELOCITY_INIT"),
    "track_init_min_flow": (track_starts, "TRACK_INIT_MIN_FLOW"),
    "track_recover_fail_fraction": (track_starts, "TRACK_RECOVER_FAIL_FRACTION"),
    "track_predict_recover": (track_starts, "TRACK_PREDICT_RECOVER"),
    "track_predict_init": (track_starts, "TRACK_PREDICT_INIT"),
    "road_region": (road_prior, "ROAD_REGION"), "road_max_gap": (road_prior, "ROAD_MAX_GAP"),
    "road_verify": (road_prior, "ROAD_VERIFY"), "road_margin": (road_prior, "ROAD_MARGIN"),
    "dynamic_updates": (dynamic_masking, "DYNAMIC_UPDATES"),
    "dynamic_rel_thresh": (dynamic_masking, "DYNAMIC_REL_THRESH"),
    "dynamic_regions": (dynamic_masking, "DYNAMIC_REGIONS"), "dynamic_min_area": (dynamic_masking, "DYNAMIC_MIN_AREA"),
    "dynamic_grow": (dynamic_masking, "DYNAMIC_GROW"), "dynamic_track": (dynamic_masking, "DYNAMIC_TRACK"),
    "things_only": (dynamic_masking, "THINGS_ONLY"),
    "vote_keeps_candidates": (dynamic_masking, "VOTE_KEEPS_CANDIDATES"),
}


def _get(cfg, path: str):
    for part in path.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _leaves(model, prefix=""):
    out = []
    for name, value in model:
        if isinstance(value, BaseModel):
            out += _leaves(value, prefix + name + ".")
        else:
            out.append(prefix + name)
    return out


def test_sixteen_settings_and_the_dynamic_model_is_the_shared_one():
    cfg = FlowFrontendConfig()
    assert len(_leaves(cfg)) == 16
    assert type(cfg.dynamic) is DynamicMaskingConfig
    assert (cfg.dis.preset, cfg.dis.scale, cfg.dis.finest_scale, cfg.dis.threads) == ("ultrafast", 0.5, 0, 2)
    assert (cfg.dynamic.max_fraction, cfg.dynamic.vote_thresh, cfg.dynamic.thresh) == (0.8, 0.5, 1.0)


def test_old_flat_keys_land_in_the_nested_tables(caplog):
    old = {k: v for k, (v, _) in OLD_FLAT.items()}
    with caplog.at_level("WARNING", logger="pvslam.config"):
        cfg = FlowFrontendConfig.model_validate(old)
    for key, (value, path) in OLD_FLAT.items():
        assert _get(cfg, path) == value, key
    assert "dis.preset" in caplog.text and "dynamic.enabled" in caplog.text
    assert FlowFrontendConfig.model_validate({"eta": 3.0}).dynamic.panoptic_offset == 3.0
    # a nested table and an old key for the same setting: they must agree (neither silently wins)
    assert FlowFrontendConfig.model_validate({"preset": "medium", "dis": {"preset": "medium"}}).dis.preset == "medium"
    with pytest.raises(ValidationError, match="'preset' \\(its old name\\) and 'dis.preset' are both given"):
        FlowFrontendConfig.model_validate({"preset": "fast", "dis": {"preset": "medium"}})


def test_retired_keys_load_at_their_constant_and_fail_otherwise():
    retired = {k: retired_value(v) for k, v in FlowFrontendConfig.retired.items()}
    for key, (module, name) in CONSTANTS.items():
        assert getattr(module, name) == retired[key], key
    # an old run directory's config.json: every key of the previous release, at the defaults of then
    every = {k: v for k, v in retired.items()}
    every.update({k: _get(FlowFrontendConfig(), path) for k, (_, path) in OLD_FLAT.items()})
    assert FlowFrontendConfig.model_validate(json.loads(json.dumps(every))) == FlowFrontendConfig()
    for key, other in (("texture_tau", 0.0), ("epipolar_cue", True), ("dynamic_persist", True),
                       ("track_preset", "medium"), ("road_verify", False), ("dynamic_rel_thresh", 2.5)):
        with pytest.raises(ValueError, match=f"'{key}' was retired"):
            FlowFrontendConfig.model_validate({key: other})


def test_a_retired_key_at_an_earlier_release_default_loads_with_a_warning(caplog):
    # dynamic_rel_thresh was 3.0 when it was retired; the constant is 2.0 since: files of then store 3.0
    with caplog.at_level("WARNING", logger="pvslam.config"):
        assert FlowFrontendConfig.model_validate({"dynamic_rel_thresh": 3.0}) == FlowFrontendConfig()
    assert "dynamic_rel_thresh = 3.0 (now 2.0)" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="pvslam.config"):
        FlowFrontendConfig.model_validate({"dynamic_rel_thresh": 2.0})
    assert "earlier release" not in caplog.text
