"""The SLAM path's settings: the frame graph (``[graph]``) and the loop policy (``[loop_closure]``).

What a user may reasonably change is here; what was tuned once and should stay is a constant next to the code that
uses it (each retired key below names its value; docs/decisions.md says how the measured ones were chosen).
"""
from __future__ import annotations

from typing import Any, ClassVar, Optional

from pydantic import Field

from ..config_base import PluginConfig


class InitConfig(PluginConfig):
    """When and from which keyframe pair a map fragment starts (:mod:`pvslam_core.slam.bootstrap`)."""

    warmup: int = Field(5, ge=2, description="keyframes collected before the map is initialised (fewer, at least 3, "
                        "once they span bootstrap.WARMUP_SECONDS of video)")
    min_parallax_deg: float = Field(
        0.5, gt=0, description="two-view initialisation needs at least this parallax (degrees) at the 75th "
        "percentile of the pair's points (docs/decisions.md: graph.init.min_parallax_deg)")


class KeyframesConfig(PluginConfig):
    """Which proposed keyframes the map keeps (:mod:`pvslam_core.slam.keyframes`)."""

    redundant_thresh: float = Field(
        1.5, ge=0, description="frame distance (reference BA px: 1/34 rad, adapt.ba_px_scale) to the previous "
        "keyframe under which a keyframe is redundant and removed (0: every keyframe stays)")
    max_gap_s: float = Field(
        0.5, gt=0, description="seconds: a keyframe whose removal would leave a longer gap between its neighbours is "
        "never redundant (docs/decisions.md: graph.keyframes.max_gap_s)")
    revisit_thresh: Optional[float] = Field(
        None, ge=0, description="frame distance (reference BA px) to an older keyframe near a loop under which a "
        "keyframe leaving the window is culled; 0 keeps all; None: 4 for a live source, else 0. Bounds the map on "
        "repeated laps")


class EdgesConfig(PluginConfig):
    """Which edges a keyframe gets and when they retire (:mod:`pvslam_core.slam.edges`; DROID-SLAM's policy)."""

    neighbours: int = Field(3, ge=1, description="edges to the previous `neighbours` keyframes of each new keyframe")
    active_window: int = Field(10, ge=2, description="keyframes: the window BA observes the edges touching the last "
                               "N keyframes; edges that no longer do retire")
    proximity_window: int = Field(25, ge=0, description="look back this many keyframes for proximity edges")
    proximity_thresh: float = Field(16.0, gt=0, description="max frame distance for a proximity edge (reference BA "
                                    "px: 1/34 rad, adapt.ba_px_scale)")
    max_proximity: int = Field(2, ge=0, description="proximity edges added per new keyframe")
    max_active: int = Field(256, ge=8, description="cap on active edges: beyond it the oldest not touching the newest "
                            "keyframe retire (their last observations stay for the final BA)")
    max_age: int = Field(25, ge=1, description="an edge retires after this many optimisation rounds (DROID-SLAM's "
                         "max_age)")


class GraphSection(PluginConfig):
    """The frame graph: its resolution, when the map starts, which keyframes stay, which edges they get."""

    ba_downsample: int = Field(8, ge=1, description="BA resolution = image size / ba_downsample (halved for a short "
                               "focal length unless set: pvslam_core/adapt.py)")
    reinit_after: int = Field(4, ge=1, description="consecutive failed frames before the map is re-initialised")
    init: InitConfig = Field(default_factory=InitConfig, description="map initialisation")
    keyframes: KeyframesConfig = Field(default_factory=KeyframesConfig, description="keyframe policy")
    edges: EdgesConfig = Field(default_factory=EdgesConfig, description="edge policy")

    renamed: ClassVar[dict[str, Any]] = {
        "ba_min_rows": None,  # replaced by the focal-length rule of adapt.py
        "warmup": "init.warmup",
        "init_min_parallax_deg": "init.min_parallax_deg",
        "redundant_thresh": "keyframes.redundant_thresh",
        "max_keyframe_gap_s": "keyframes.max_gap_s",
        "neighbours": "edges.neighbours",
        "active_window": "edges.active_window",
        "proximity_window": "edges.proximity_window",
        "proximity_thresh": "edges.proximity_thresh",
        "max_proximity_edges": "edges.max_proximity",
        "max_active_edges": "edges.max_active",
        "max_edge_age": "edges.max_age",
    }
    # settings that became constants (module and name after each); a file may still give exactly this value
    retired: ClassVar[dict[str, Any]] = {
        "ba_min_focal": 24.0,  # adapt.BA_MIN_FOCAL
        "warmup_seconds": 0.65,  # bootstrap.WARMUP_SECONDS
        "init_parallax_quantile": 0.75,  # bootstrap.PARALLAX_QUANTILE
        "init_relative_confidence": True,  # bootstrap.RELATIVE_CONFIDENCE
        "init_chain_tol": 1.0,  # bootstrap.CHAIN_TOL
        "init_chain_fallback": True,  # bootstrap.CHAIN_FALLBACK
        "init_ambiguity_ratio": 3.0,  # bootstrap.AMBIGUITY_RATIO
        "init_tie_ratio": 1.25,  # bootstrap.TIE_RATIO
        "init_tries": 3,  # bootstrap.INIT_TRIES
        "init_window": 8,  # bootstrap.INIT_WINDOW
        "unobserved_weight": 0.3,  # observed.UNOBSERVED_WEIGHT
        "guess_min_measured": 0.5,  # observed.GUESS_MIN_MEASURED
        "observed_parallax": 1.0,  # observed.OBSERVED_PARALLAX
        "second_start": True,  # window_ba.SECOND_START
        "second_start_span": 0.25,  # motion_start.SPAN
        "second_start_horizon": 1.0,  # motion_start.HORIZON
        "proximity_nms": 1,  # edges.PROXIMITY_NMS
        "proximity_max_flow": 8.0,  # edges.PROXIMITY_MAX_FLOW
        "bidirectional": True,  # edges: always both directions
        "remove_redundant": True,  # keyframes: graph.keyframes.redundant_thresh = 0 keeps every keyframe
        "redundant_max_flow": 4.0,  # keyframes.REDUNDANT_MAX_FLOW
        "provisional_keyframes": True,  # keyframes: always on
        "fill_row_min_frac": 0.25,  # new_keyframe.FILL_ROW_MIN_FRAC
        "retired_margin": None,  # the window BA uses active edges only
        "motion_robust": "cauchy",  # map_state.MOTION_ROBUST
        "motion_robust_scale": 1.0,  # map_state.MOTION_ROBUST_SCALE
    }


class LoopClosureSection(PluginConfig):
    """Which loop candidates close a loop (the one loop policy: :mod:`pvslam_core.slam.loops`)."""

    accept_unverified: bool = Field(
        True, description="accept candidates a retrieval-only detector did not verify geometrically (verified = "
        "None), on their score; candidates that failed verification are never accepted")
    consecutive: int = Field(
        1, ge=1, description="require candidates to the same place from this many consecutive keyframes (DPVO uses 3)")
    max_rotation_deg: float = Field(
        60.0, gt=0, le=180, description="reject a loop whose keyframes' current orientations differ by more than "
        "this (degrees): look-alike places seen from opposite directions")

    retired: ClassVar[dict[str, Any]] = {
        "consecutive_tolerance": 3,  # loops.CONSECUTIVE_TOLERANCE
        "nms_keyframes": 5,  # loops.NMS_KEYFRAMES
        "ba_min_gap": 8,  # loops.LOOP_BA_MIN_GAP
    }
