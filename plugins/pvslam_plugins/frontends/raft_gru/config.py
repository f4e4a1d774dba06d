"""Configuration of the learned ``raft_gru`` frontend (DROID-SLAM / PVO update operator).

Two profiles set the defaults of the fields left at ``None`` (:meth:`RaftGruConfig.resolved`):

* ``droid`` (default): DROID-SLAM's frontend as published - 4 + 2 update -> BA rounds per keyframe (``iters1`` /
  ``iters2``), every observed edge updated in every round, float32, stored correlation volumes.
* ``fast``: the CPU profile - 2 rounds per keyframe, only the edges touching the newest ``update_window`` keyframes
  get a GRU update (the others keep their last target and weight, exactly like DROID's inactive-edge store), bf16
  autocast.  Same network, same semantics per update; fewer of them.

Units: flow thresholds are in pixels at the BA resolution (1/8 of the image: DROID's 1/8 feature resolution).
"""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from pvslam_core.config_base import PluginConfig

PROFILES: dict[str, dict] = {
    # DROID-SLAM 2021 frontend: iters1 = 4 updates, (keyframe removal check), iters2 = 2 updates (anchors 1.5)
    "droid": {"rounds": 6, "precision": "fp32", "update_window": 0, "corr_impl": "volume"},
    "fast": {"rounds": 2, "precision": "bf16", "update_window": 2, "corr_impl": "volume"},
}


class RaftGruConfig(PluginConfig):
    """Learned correspondence frontend: RAFT-style encoders, correlation pyramid, ConvGRU update (DROID / PVO)."""

    weights: Optional[str] = Field(
        "droid", description="checkpoint: a catalogue name (`pvslam weights list`: droid, pvo-vo-vkitti2) or a file "
        "path (droid.pth, a PVO checkpoint or this project's own); \"random\" (or null in Python) = RANDOM weights, "
        "with a loud warning: only for tests and training from scratch")
    variant: Optional[Literal["droid", "pvo"]] = Field(
        None, description="network variant; null = the checkpoint's (droid for random weights). 'pvo' adds PVO's "
        "dynamic update module: its mask head refines a per-edge dynamic mask (eq. 6) that sets eq. 4's M_d")
    profile: Literal["droid", "fast"] = Field(
        "droid", description="defaults of rounds / precision / update_window / corr_impl (module docstring)")
    rounds: Optional[int] = Field(
        None, ge=1, le=16, description="observe -> BA rounds per new keyframe (Frontend.rounds); null = profile "
        "(droid 6 = DROID's iters1 4 + iters2 2; fast 2)")
    precision: Optional[Literal["fp32", "bf16"]] = Field(
        None, description="network arithmetic: fp32, or bf16 autocast (CPUs with avx512_bf16/AMX: ~2-3x faster; "
        "fp16 autocast on CUDA, as DROID); null = profile")
    update_window: Optional[int] = Field(
        None, ge=0, description="only edges with an end among the newest N keyframes (and new edges) get a GRU "
        "update per observe; the others return their last target/weight; 0 = every edge (DROID); null = profile")
    corr_impl: Optional[Literal["volume", "onthefly"]] = Field(
        None, description="correlation: per-edge stored pyramid (built once per edge, fast lookups, ~4 B x (h w)^2 "
        "x 1.33 per edge: 7.7 MB at 320x240) or on the fly from the keyframes' features (no per-edge memory, no "
        "build, ~3.5x the time of a stored-volume lookup: bench/RESULTS.md); null = profile")
    keyframe_thresh: float = Field(
        2.4, gt=0, description="motion filter: a frame becomes a keyframe when the mean flow of one update step "
        "against the last keyframe exceeds this (BA px); DROID's filter_thresh (2.4 demo/EuRoC/TartanAir, 1.75 TUM)")
    track_iters: int = Field(
        1, ge=1, le=8, description="update steps of the motion filter (DROID: 1); more refine the flow used to place "
        "non-keyframes (each step re-looks up the correlation at the new estimate)")
    min_texture_std: float = Field(
        2.0, ge=0, description="tracking failure when the frame's grayscale std is below this (black/blank frame)")
    feature_cache: int = Field(
        64, ge=4, description="keyframes whose features (fmap, context, upsampling mask) stay in memory (LRU); an "
        "older keyframe keeps its uint8 image and gets its features recomputed when a loop edge needs them")
    upsample: bool = Field(
        True, description="keep each keyframe's convex-upsampling mask (learned, from the GRU states of its edges) "
        "for full-resolution inverse depth (RaftGruFrontend.upsampled_disp)")

    # --- panoptic-aware confidence (PV-SLAM eq. 4) ----------------------------------------------------------------
    dynamic_masking: bool = Field(
        True, description="eq. 4 with a dynamic mask: variant pvo - the mask head's (eq. 6); variant droid - pixels "
        "whose update still moves them (|target - reprojection|) after a BA round, as the flow frontend")
    panoptic_offset: float = Field(10.0, ge=0, description="eq. 4's logit offset (the paper's eta = 10)")
    convention: Literal["paper", "pvo_code"] = Field(
        "paper", description="mask convention of eq. 4 (pvslam_core.slam.confidence): 'paper' down-weights dynamic "
        "pixels; 'pvo_code' reproduces PVO's released code (static pixels get the raw logit), e.g. with PVO's "
        "checkpoint")
    mask_thresh: float = Field(0.5, gt=0, lt=1, description="pvo: a pixel is static when sigmoid(raw mask) >= this "
                               "(PVO's dy_thresh)")
    vote_thresh: Optional[float] = Field(
        None, ge=0, le=1, description="a segment becomes dynamic when more than this fraction of its pixels is; "
        "null = 0.8 for pvo (PVO's segm_filter), 0.5 for droid (the flow frontend's)")
    things_only: bool = Field(True, description="only movable thing segments vote (PVO's segm_filter: every segment)")
    dynamic_thresh: float = Field(1.0, gt=0, description="droid: residual (BA px) above which a pixel is dynamic")
    dynamic_rel_thresh: float = Field(
        3.0, ge=0, description="droid: ... and above this multiple of the edge's median residual (0 disables)")
    max_dynamic_fraction: float = Field(
        0.5, gt=0, le=1, description="droid: an edge with more dynamic pixels than this gets no mask (the estimate, "
        "not the scene, is off)")

    @property
    def random_weights(self) -> bool:
        """True when the network is randomly initialised (``weights = "random"`` or None)."""
        return self.weights is None or self.weights == "random"

    def resolved(self, name: str):
        """The value of a profile-dependent field (``rounds``, ``precision``, ``update_window``, ``corr_impl``)."""
        v = getattr(self, name)
        return PROFILES[self.profile][name] if v is None else v
