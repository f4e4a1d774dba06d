"""``frontend.dynamic``: the dynamic-masking settings every frontend shares (PV-SLAM eq. 4 and the masks it needs).

One model for the classical ``flow`` and the learned ``raft_gru`` frontends: the same key means the same thing in
both.  A frontend whose default differs, or that has keys of its own, subclasses it (``raft_gru`` keeps
``max_fraction`` 0.5 and adds its mask head's threshold); the weights themselves are
:func:`pvslam_core.slam.confidence.observed_flow_weight` / :func:`~pvslam_core.slam.confidence.panoptic_aware_weight`.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from pvslam_core.config_base import PluginConfig


class DynamicMaskingConfig(PluginConfig):
    """Which pixels move on their own, and how much weight they keep in the bundle adjustment (PV-SLAM eq. 4)."""

    enabled: bool = Field(
        True, description="Dynamic masks with eq. 4 weights; false: every pixel keeps its flow confidence.")
    panoptic_offset: float = Field(
        10.0, ge=0.0, description="Eq. 4 logit offset (the paper's eta): a dynamic pixel keeps about e^-eta of a "
        "static pixel's weight.")
    convention: Literal["paper", "pvo_code"] = Field(
        "paper", description="Mask convention of eq. 4 (pvslam_core.slam.confidence): 'paper' down-weights dynamic "
        "pixels; 'pvo_code' is PVO's released code, for its checkpoints.")
    thresh: float = Field(
        1.0, gt=0.0, description="A pixel is dynamic when its target and the reprojection under the current estimate "
        "differ by more than this (BA px).")
    max_fraction: float = Field(
        0.8, gt=0.0, le=1.0, description="An edge whose mask would cover more than this fraction of its pixels gets "
        "none: the estimate is off, not the scene (docs/decisions.md: frontend.dynamic.max_fraction).")
    vote_thresh: float = Field(
        0.5, ge=0.0, le=1.0, description="A movable segment becomes dynamic as a whole when more than this fraction of "
        "its pixels is dynamic.")
