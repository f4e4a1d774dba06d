"""Configuration pieces of the ``deit`` loop detector.

Flat mixins, combined into the detector's config :class:`DeitLoopConfig` (flat like the classical one):

* :class:`DeitModelConfig`: which architecture and weights;
* :class:`DeitDescriptorConfig`: preprocessing, token choice, PCA / whitening, batching;
* :class:`RetrievalConfig`: threshold, temporal exclusion, candidates (model-independent);
* :class:`~pvslam_plugins.loops.verification.VerificationConfig`: the optional geometric verification shared with
  the classical detector.

Consecutive hits, suppression near accepted loops and the orientation check are the mapper's loop policy
(``[loop_closure]``), not the detector's.

A project checkpoint stores the descriptor settings its weights were trained and calibrated with (input size,
token, PCA, threshold); they replace the defaults of the fields the user did not set (:func:`with_checkpoint`).
"""
from __future__ import annotations

from typing import Any, ClassVar, Literal, Optional, Union

from pydantic import Field, field_validator

from pvslam_core.config_base import PluginConfig

from ..verification import VerificationConfig

#: ``weights`` value meaning "the checkpoint shipped in this package for the chosen variant" (``weights/
#: deit_synth_<variant>.pt``, see weights/README.md)
BUILTIN = "builtin"
_VARIANT_ALIASES = {"deit-base": "base", "deit_base_patch16_224": "base", "deit-base-distilled": "distilled",
                    "deit_base_distilled_patch16_224": "distilled", "plain": "base"}


class DeitModelConfig(PluginConfig):
    variant: Literal["base", "distilled"] = Field(
        "distilled", description="architecture: plain DeiT (class token) or DeiT-distilled (class + distillation "
        "token; the paper's choice); the checkpoint named by 'weights' must be of this variant")
    weights: Optional[str] = Field(
        BUILTIN, description="'builtin' (the shipped checkpoint trained on the generator), a catalogue name "
        "('deit-base', 'deit-base-distilled'), an official .pth or a project checkpoint; none: random (timing only)")
    pos_embed_antialias: bool = Field(
        True, description="position-embedding resampling for other input grids: true = timm's antialiased bicubic, "
        "false = plain bicubic as DeiT's own fine-tuning used")

    @field_validator("variant", mode="before")
    @classmethod
    def _variant_alias(cls, v):  # type: ignore[no-untyped-def]
        return _VARIANT_ALIASES.get(v, v) if isinstance(v, str) else v


class DeitDescriptorConfig(PluginConfig):
    # --- preprocessing ---------------------------------------------------------------------------------------
    resize: Literal["full_frame", "center_crop"] = Field(
        "full_frame", description="full_frame: the whole frame resized (a loop detector should see all of it); "
        "center_crop: DeiT's eval transform (shorter side to input_size / 0.875, centre crop)")
    input_size: Union[int, tuple[int, int]] = Field(
        224, description="int S: center_crop -> S x S; full_frame -> aspect ratio kept on a budget of (S/16)^2 "
        "patches. (h, w): full_frame resized to exactly that (multiples of 16)")
    # --- descriptor ----------------------------------------------------------------------------------------------
    token: Literal["cls", "dist", "mean", "concat"] = Field(
        "cls", description="final-norm token(s) used: cls (the paper's eq. 12), dist (distillation token), mean "
        "((cls + dist) / 2), concat ([cls, dist]); all but cls need the distilled variant")
    pca: Literal["none", "online", "fixed"] = Field(
        "online", description="none: L2-normalised raw tokens; online: PCA/whitening refit on the descriptors seen "
        "so far; fixed: loaded from pca_file (or the project checkpoint's 'pca' entry)")
    pca_file: Optional[str] = Field(None, description="PCA for pca='fixed' (PCAWhitening.save file or checkpoint)")
    pca_dim: Optional[int] = Field(256, ge=1, description="output dimension (capped by the rank of the fit set)")
    whiten: bool = Field(True, description="divide each principal component by its standard deviation")
    pca_min_samples: int = Field(32, ge=2, description="online: first fit after this many keyframes")
    # --- cost ----------------------------------------------------------------------------------------------------
    batch_size: int = Field(8, ge=1, description="keyframes per forward pass (memory)")
    # the DeiT crop ratio and the online PCA's regulariser and refit schedule are constants of .descriptor
    retired: ClassVar[dict[str, Any]] = {"crop_pct": 0.875, "whiten_shrinkage": 0.1, "pca_refit_growth": 1.25,
                                         "pca_freeze_after": None}

    @field_validator("input_size")
    @classmethod
    def _check_size(cls, v):  # type: ignore[no-untyped-def]
        sizes = [v] if isinstance(v, int) else list(v)
        if any(s < 16 for s in sizes):
            raise ValueError(f"input_size {v} is smaller than one 16-pixel patch")
        return v


class RetrievalConfig(PluginConfig):
    threshold: float = Field(
        0.8, ge=-1.0, le=1.0, description="minimum cosine similarity (eq. 8) of two descriptors for a loop "
        "candidate; whitened scores are lower, so calibrate it per PCA setting")
    exclude_recent: int = Field(
        20, ge=0, description="temporal exclusion: only keyframes more than this many stored keyframes older qualify")
    min_time_gap: float = Field(
        10.0, ge=0.0, description="temporal exclusion: only keyframes at least this many seconds older qualify")
    max_candidates: int = Field(
        3, ge=1, description="at most this many best-scoring candidates per keyframe are (verified and) returned")


class DeitLoopConfig(DeitModelConfig, DeitDescriptorConfig, RetrievalConfig, VerificationConfig):
    """Config of the ``deit`` loop detector (all fields flat: ``[loop] plugin = "deit"``, ``variant = ...``).

    Verification is on by default although the paper's DeiT loop closure has none: the calibrated threshold sits
    just above the best wrong score, so it does not carry from one sequence to another, and retrieval alone then
    closes false loops (docs/decisions.md: loop.deit.verify)."""

    verify: bool = Field(
        True, description="geometric verification of the retrieved candidates (ORB + essential-matrix RANSAC, "
        "shared with classical); false: retrieval only, as in the paper (false loops at look-alikes)")
    retired: ClassVar[dict[str, Any]] = {**DeitDescriptorConfig.retired, **VerificationConfig.retired}


def with_checkpoint(config: DeitLoopConfig, stored: dict[str, Any]) -> DeitLoopConfig:
    """``config`` with the settings a checkpoint stores (its ``descriptor`` entry) in place of the defaults of the
    fields the user did not set; unknown stored keys are ignored (newer checkpoints), invalid ones raise."""
    fields = type(config).model_fields
    update = {k: v for k, v in stored.items() if k in fields and k not in config.model_fields_set}
    if not update:
        return config
    return type(config).model_validate({**config.model_dump(exclude_unset=True), **update})
