"""Configuration of the classical ``flow`` frontend (OpenCV DIS optical flow): ``[frontend]`` with ``plugin = "flow"``.

Sixteen settings in four tables.  The rest of the method is fixed in the code, each value a named constant next to
what it controls (``TEXTURE_TAU`` in :mod:`.pair_flow`, ``TRACK_VELOCITY_INIT`` in :mod:`.track_starts`, ...); the
keys of earlier releases still load (``renamed`` / ``retired`` below).
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from pvslam_core.config_base import PluginConfig, Retired
from pvslam_core.slam.dynamic_config import DynamicMaskingConfig


class DisConfig(PluginConfig):
    """OpenCV DIS optical flow: one set of settings for tracking and keyframe edges alike."""

    preset: Literal["ultrafast", "fast", "medium"] = Field(
        "ultrafast", description="OpenCV DIS preset (patch size and iterations); the pyramid depth (finest_scale) "
        "matters more on low-texture road.")
    scale: float = Field(
        0.5, description="Resolution at which the flow is computed, relative to the input image: 1.0 or 0.5.")
    finest_scale: Optional[int] = Field(
        0, ge=0, le=5, description="DIS finest pyramid level (0: the flow resolution itself); null: the preset's own "
        "(docs/decisions.md: frontend.dis.finest_scale).")
    threads: int = Field(
        2, ge=1, le=8, description="Threads for independent DIS calls (OpenCV releases the GIL); results do not "
        "depend on it (lanes.py).")

    @field_validator("scale")
    @classmethod
    def _check_scale(cls, v: float) -> float:
        if v not in (1.0, 0.5):
            raise ValueError(f"dis.scale must be 1.0 or 0.5, got {v}")
        return v


class KeyframeConfig(PluginConfig):
    """The motion filter: when a tracked frame becomes a keyframe."""

    flow_thresh: float = Field(
        2.0, gt=0.0, description="New keyframe when the mean flow to the last keyframe exceeds this (reference BA "
        "px: 1/34 rad of view at any size, adapt.ba_px_scale); DROID uses 2.4 BA px with its learned flow.")
    min_coverage: float = Field(
        0.7, ge=0.0, le=1.0, description="New keyframe when fewer than this fraction of the last keyframe's pixels "
        "are still tracked: on forward motion pixels leave the view before the mean flow grows.")


class RoadConfig(PluginConfig):
    """The road plane of a car camera: its homography's flow on the near road and the BA priors it gives."""

    enabled: bool = Field(
        True, description="Search the ground plane's motion and use its flow where DIS cannot follow the near road; "
        "false for a hand-held camera over a floor (docs/decisions.md: frontend.road.enabled).")
    depth_weight: float = Field(
        1.0, ge=0.0, description="Weight of the BA prior on the road pixels' inverse depth at one camera height, "
        "relative error squared; 0: off (docs/decisions.md: frontend.road.depth_weight).")
    distance_weight: float = Field(
        100.0, ge=0.0, description="Weight of the BA prior on the distance between consecutive keyframes from the "
        "road's motion, relative error squared; 0: off (docs/decisions.md: frontend.road.distance_weight).")


class FlowFrontendConfig(PluginConfig):
    """DIS optical flow with forward-backward, photometric and texture confidence, a motion filter, the road plane
    and panoptic-aware dynamic masking (PV-SLAM eq. 4)."""

    renamed = {
        "eta": "dynamic.panoptic_offset",
        "ba_downsample": None,  # the BA resolution comes from graph.ba_downsample (BuildContext.ba_downsample)
        "preset": "dis.preset",
        "flow_scale": "dis.scale",
        "finest_scale": "dis.finest_scale",
        "flow_threads": "dis.threads",
        "keyframe_thresh": "keyframes.flow_thresh",
        "keyframe_min_coverage": "keyframes.min_coverage",
        "road_plane": "road.enabled",
        "road_depth_weight": "road.depth_weight",
        "road_distance_weight": "road.distance_weight",
        "dynamic_masking": "dynamic.enabled",
        "panoptic_offset": "dynamic.panoptic_offset",
        "convention": "dynamic.convention",
        "dynamic_thresh": "dynamic.thresh",
        "max_dynamic_fraction": "dynamic.max_fraction",
        "vote_thresh": "dynamic.vote_thresh",
    }
    retired = {
        # the preset's own DIS iterations and patches (the presets are the choice a user makes)
        "gradient_descent_iterations": None, "variational_refinement_iterations": None, "patch_size": None,
        "patch_stride": None,
        # tracking uses the edges' DIS settings (null meant "the same")
        "track_preset": None, "track_finest_scale": None,
        # constants of the code now: pair_flow.py
        "fb_sigma": 1.0, "fb_fail_px": 3.0, "photo_sigma": 4.0, "texture_tau": 1e-3, "texture_quantile": 0.75,
        "weighted_pooling": True,
        # frontend.py
        "min_texture_std": 2.0, "max_fb_fail_fraction": 0.8, "reuse_track_flow": True, "use_reprojection_init": True,
        "init_min_flow": 1.0, "init_compare_min_gap": 4,
        # track_starts.py
        "track_velocity_init": True, "track_init_min_flow": 1.0, "track_recover_fail_fraction": 0.5,
        "track_predict_recover": True, "track_predict_init": True,
        # road_prior.py
        "road_region": 0.15, "road_max_gap": 5, "road_verify": True, "road_margin": 1.1,
        # dynamic_masking.py
        "dynamic_updates": 3, "dynamic_rel_thresh": Retired(2.0, earlier=(3.0,)), "dynamic_regions": True,
        "dynamic_min_area": 4, "dynamic_grow": 1, "dynamic_track": True, "things_only": True,
        "vote_keeps_candidates": True,
        # opt-in paths that no shipped configuration enabled, deleted with their code
        "dynamic_persist": False, "depth_check": 0.0, "epipolar_cue": False, "epipolar_track": False,
        "epipolar_with_segmenter": False, "epipolar_replaces_residual": False, "epipolar_edges": 2,
        "epipolar_thresh": 0.5, "epipolar_rel": 3.0, "epipolar_back": 0.5, "epipolar_min_conf": 0.05,
        "epipolar_ransac_px": 0.25, "epipolar_min_parallax": 0.05,
    }

    rounds: int = Field(
        1, ge=1, le=4, description="Observe -> BA rounds per new keyframe (Frontend.rounds); 2 applies a new edge's "
        "dynamic mask at once, at twice the BA cost.")
    dis: DisConfig = Field(default_factory=DisConfig, description="DIS optical flow.")
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig, description="When a frame becomes a keyframe.")
    road: RoadConfig = Field(default_factory=RoadConfig, description="The road plane of a car camera.")
    dynamic: DynamicMaskingConfig = Field(
        default_factory=DynamicMaskingConfig, description="Dynamic masks and PV-SLAM eq. 4 weights.")
