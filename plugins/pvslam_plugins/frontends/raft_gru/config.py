"""Configuration of the learned ``raft_gru`` frontend (DROID-SLAM / PVO update operator).

Two profiles set the defaults of the fields left at ``None`` (:meth:`RaftGruConfig.resolved`):

* ``droid`` (default): DROID-SLAM's frontend as published - 4 + 2 update -> BA rounds per keyframe (``iters1`` /
  ``iters2``), every observed edge updated in every round, float32, stored correlation volumes.
* ``fast``: the CPU profile - 2 rounds per keyframe, only the edges touching the newest ``update_window`` keyframes
  get a GRU update (the others keep their last target and weight, exactly like DROID's inactive-edge store), bf16
  autocast where the CPU computes bf16 natively (fp32 elsewhere).  Same network, same semantics per update; fewer of
  them.

Units: flow thresholds are in pixels at the BA resolution (1/8 of the image: DROID's 1/8 feature resolution).
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_core.slam.dynamic_config import DynamicMaskingConfig

PROFILES: dict[str, dict] = {
    # DROID-SLAM 2021 frontend: iters1 = 4 updates, (keyframe removal check), iters2 = 2 updates (anchors 1.5)
    "droid": {"rounds": 6, "precision": "fp32", "update_window": 0, "corr_impl": "volume"},
    "fast": {"rounds": 2, "precision": "bf16", "update_window": 2, "corr_impl": "volume"},
}


class RaftGruDynamicConfig(DynamicMaskingConfig):
    """``frontend.dynamic`` of ``raft_gru``: the shared dynamic-masking settings, with this frontend's defaults and the
    mask head's own keys.  ``thresh`` and ``max_fraction`` are for variant droid's residual test (the residual is the
    update's step ``|target - reprojection|``)."""

    max_fraction: float = Field(
        0.5, gt=0.0, le=1.0, description="droid: an edge with more dynamic pixels than this fraction gets no mask (the "
        "estimate, not the scene, is off).")
    vote_thresh: Optional[float] = Field(
        None, ge=0.0, le=1.0, description="A segment becomes dynamic when more than this fraction of its pixels is; "
        "null: 0.8 for pvo (PVO's segm_filter), 0.5 for droid (the flow frontend's).")
    mask_thresh: float = Field(
        0.5, gt=0.0, lt=1.0, description="pvo: a pixel is static when sigmoid(raw mask) >= this (PVO's dy_thresh).")
    things_only: bool = Field(
        True, description="Only movable thing segments vote; false: every segment, as PVO's segm_filter.")


class RaftGruConfig(PluginConfig):
    """Learned correspondence frontend: RAFT-style encoders, correlation pyramid, ConvGRU update (DROID / PVO)."""

    renamed = {
        "dynamic_masking": "dynamic.enabled",
        "panoptic_offset": "dynamic.panoptic_offset",
        "convention": "dynamic.convention",
        "dynamic_thresh": "dynamic.thresh",
        "max_dynamic_fraction": "dynamic.max_fraction",
        "vote_thresh": "dynamic.vote_thresh",
        "mask_thresh": "dynamic.mask_thresh",
        "things_only": "dynamic.things_only",
    }
    # constants of frontend.py now
    retired = {"dynamic_rel_thresh": 3.0, "min_texture_std": 2.0}

    weights: Optional[str] = Field(
        "droid", description="checkpoint: a catalogue name (`pvslam weights list`) or a file path (droid.pth, a PVO or "
        "a pvslam checkpoint); \"random\": random weights with a loud warning, for tests and training")
    variant: Optional[Literal["droid", "pvo"]] = Field(
        None, description="network variant; null = the checkpoint's (droid for random weights). 'pvo' adds PVO's "
        "dynamic update module: its mask head refines a per-edge dynamic mask (eq. 6) that sets eq. 4's M_d")
    profile: Literal["droid", "fast"] = Field(
        "droid", description="defaults of rounds / precision / update_window / corr_impl (module docstring)")
    rounds: Optional[int] = Field(
        None, ge=1, le=16, description="observe -> BA rounds per new keyframe (Frontend.rounds); null = profile "
        "(droid 6 = DROID's iters1 4 + iters2 2; fast 2)")
    precision: Optional[Literal["fp32", "bf16"]] = Field(
        None, description="network arithmetic: fp32, or bf16 autocast (faster on CPUs with avx512_bf16 / AMX; other "
        "CPUs run fp32, bf16 being far slower there; fp16 autocast on CUDA, as DROID); null = profile")
    update_window: Optional[int] = Field(
        None, ge=0, description="only edges with an end among the newest N keyframes (and new edges) get a GRU "
        "update per observe; the others return their last target/weight; 0 = every edge (DROID); null = profile")
    corr_impl: Optional[Literal["volume", "onthefly"]] = Field(
        None, description="correlation: a stored pyramid per edge (built once, fast lookups, ~4 B x (h w)^2 x 1.33 "
        "per edge) or on the fly from the features (no memory per edge, slower lookups); null = profile")
    keyframe_thresh: float = Field(
        2.4, gt=0, description="motion filter: a frame becomes a keyframe when the mean flow of one update step "
        "against the last keyframe exceeds this (BA px); DROID's filter_thresh (2.4 demo/EuRoC/TartanAir, 1.75 TUM)")
    track_iters: int = Field(
        1, ge=1, le=8, description="update steps of the motion filter (DROID: 1); more refine the flow used to place "
        "non-keyframes (each step re-looks up the correlation at the new estimate)")
    feature_cache: int = Field(
        64, ge=4, description="keyframes whose features (fmap, context, upsampling mask) stay in memory (LRU); an "
        "older keyframe keeps its uint8 image and gets its features recomputed when a loop edge needs them")
    upsample: bool = Field(
        True, description="keep each keyframe's convex-upsampling mask (learned, from the GRU states of its edges) "
        "for full-resolution inverse depth (RaftGruFrontend.upsampled_disp)")

    dynamic: RaftGruDynamicConfig = Field(
        default_factory=RaftGruDynamicConfig, description="Dynamic masks and PV-SLAM eq. 4 weights (variant pvo: the "
        "mask head's; droid: the residual test).")

    @property
    def random_weights(self) -> bool:
        """True when the network is randomly initialised (``weights = "random"`` or None)."""
        return self.weights is None or self.weights == "random"

    def resolved(self, name: str):
        """The value of a profile-dependent field (``rounds``, ``precision``, ``update_window``, ``corr_impl``)."""
        v = getattr(self, name)
        return PROFILES[self.profile][name] if v is None else v
