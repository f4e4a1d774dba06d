"""The ``[graph]`` and ``[loop_closure]`` tables: keys of earlier releases land in the nested tables (with a warning),
retired keys load only with the value the code now fixes, and each retired value is the constant the code uses."""
import json

import pytest

from pvslam_core import adapt
from pvslam_core.config import ConfigError, load_config
from pvslam_core.slam import bootstrap, edges, keyframes, loops, map_state, motion_start, new_keyframe, observed
from pvslam_core.slam import window_ba
from pvslam_core.slam.config import GraphSection, LoopClosureSection

# every flat key of the previous [graph] table that moved, with a value other than its default
OLD_GRAPH = {"warmup": 7, "init_min_parallax_deg": 0.8, "redundant_thresh": 2.5, "max_keyframe_gap_s": 0.75,
             "neighbours": 4, "active_window": 12, "proximity_window": 30, "proximity_thresh": 12.0,
             "max_proximity_edges": 3, "max_active_edges": 128, "max_edge_age": 20}
NEW_PLACE = {"warmup": "init.warmup", "init_min_parallax_deg": "init.min_parallax_deg",
             "redundant_thresh": "keyframes.redundant_thresh", "max_keyframe_gap_s": "keyframes.max_gap_s",
             "neighbours": "edges.neighbours", "active_window": "edges.active_window",
             "proximity_window": "edges.proximity_window", "proximity_thresh": "edges.proximity_thresh",
             "max_proximity_edges": "edges.max_proximity", "max_active_edges": "edges.max_active",
             "max_edge_age": "edges.max_age"}


def _at(model, dotted: str):
    for part in dotted.split("."):
        model = getattr(model, part)
    return model


def test_old_flat_keys_land_in_the_nested_tables(caplog):
    cfg = load_config({"graph": {**OLD_GRAPH, "ba_downsample": 4, "reinit_after": 6}})
    g = cfg.pipeline.graph
    for old, value in OLD_GRAPH.items():
        assert _at(g, NEW_PLACE[old]) == value, old
    assert g.ba_downsample == 4 and g.reinit_after == 6
    for old, new in NEW_PLACE.items():
        assert f"{old} -> {new}" in caplog.text
    # the same keys through --set, as old command lines give them
    cfg = load_config(overrides=["graph.warmup=4", "graph.max_edge_age=9"])
    assert cfg.pipeline.graph.init.warmup == 4 and cfg.pipeline.graph.edges.max_age == 9
    # a key that moved between tables in an earlier release still lands in [loop_closure]
    assert load_config({"graph": {"loop_max_rotation_deg": 45.0}}).pipeline.loop_closure.max_rotation_deg == 45.0


def test_an_old_run_directory_config_loads():
    """config.json of a run written before: every key of the previous tables at its default value."""
    old = {"graph": {**{k: _at(GraphSection(), v) for k, v in NEW_PLACE.items()}, **GraphSection.retired,
                     "ba_downsample": 8, "reinit_after": 4, "ba_min_rows": 30},
           "loop_closure": {"accept_unverified": True, "consecutive": 1, "max_rotation_deg": 60.0,
                            **LoopClosureSection.retired}}
    cfg = load_config(json.loads(json.dumps(old)))  # as JSON stores it (lists, null)
    assert cfg.pipeline.graph == GraphSection() and cfg.pipeline.loop_closure == LoopClosureSection()


@pytest.mark.parametrize("table, key, value", [
    ("graph", "provisional_keyframes", False), ("graph", "retired_margin", 3), ("graph", "motion_robust", "none"),
    ("graph", "unobserved_weight", 0.5), ("graph", "init_tries", 2), ("graph", "remove_redundant", False),
    ("loop_closure", "nms_keyframes", 0), ("loop_closure", "ba_min_gap", 3)])
def test_a_retired_key_at_another_value_fails_naming_it(table, key, value):
    with pytest.raises(ConfigError) as err:
        load_config({table: {key: value}})
    assert key in str(err.value) and "retired" in str(err.value)
    with pytest.raises(ConfigError) as err:  # and from the command line
        load_config(overrides=[f"{table}.{key}={json.dumps(value)}"])
    assert key in str(err.value)


def test_each_retired_value_is_the_constant_the_code_uses():
    """The fixed values that old files may still give are the code's constants (a constant changed without its
    retired entry would make old files that state the old value load silently with another behaviour)."""
    constants = {
        "ba_min_focal": adapt.BA_MIN_FOCAL, "warmup_seconds": bootstrap.WARMUP_SECONDS,
        "init_parallax_quantile": bootstrap.PARALLAX_QUANTILE,
        "init_relative_confidence": bootstrap.RELATIVE_CONFIDENCE,
        "init_chain_tol": bootstrap.CHAIN_TOL, "init_chain_fallback": bootstrap.CHAIN_FALLBACK,
        "init_ambiguity_ratio": bootstrap.AMBIGUITY_RATIO, "init_tie_ratio": bootstrap.TIE_RATIO,
        "init_tries": bootstrap.INIT_TRIES, "init_window": bootstrap.INIT_WINDOW,
        "unobserved_weight": observed.UNOBSERVED_WEIGHT, "guess_min_measured": observed.GUESS_MIN_MEASURED,
        "observed_parallax": observed.OBSERVED_PARALLAX, "second_start": window_ba.SECOND_START,
        "second_start_span": motion_start.SPAN, "second_start_horizon": motion_start.HORIZON,
        "proximity_nms": edges.PROXIMITY_NMS, "proximity_max_flow": edges.PROXIMITY_MAX_FLOW,
        "redundant_max_flow": keyframes.REDUNDANT_MAX_FLOW, "fill_row_min_frac": new_keyframe.FILL_ROW_MIN_FRAC,
        "motion_robust": map_state.MOTION_ROBUST, "motion_robust_scale": map_state.MOTION_ROBUST_SCALE,
        # switches whose setting is now the only code path
        "bidirectional": True, "remove_redundant": True, "provisional_keyframes": True, "retired_margin": None,
    }
    assert constants == GraphSection.retired
    assert LoopClosureSection.retired == {"consecutive_tolerance": loops.CONSECUTIVE_TOLERANCE,
                                          "nms_keyframes": loops.NMS_KEYFRAMES, "ba_min_gap": loops.LOOP_BA_MIN_GAP}


def test_the_tables_are_small():
    """The SLAM path's [graph] and [loop_closure] settings: 14 leaves in three sub-tables, and 3."""
    def leaves(model) -> int:
        n = 0
        for name, field in type(model).model_fields.items():
            value = getattr(model, name)
            n += leaves(value) if hasattr(type(value), "model_fields") else 1
        return n

    assert leaves(GraphSection()) == 14 and leaves(LoopClosureSection()) == 3
