"""Configuration of the ``classical`` loop detector (the verification fields are the shared ones of
:class:`~pvslam_plugins.loops.verification.VerificationConfig`)."""
from __future__ import annotations

from typing import Any, ClassVar

from pydantic import Field

from ..verification import VerificationConfig


class ClassicalLoopConfig(VerificationConfig):
    threshold: float = Field(
        0.75, ge=-1.0, le=1.0, description="minimum cosine similarity of the global descriptors (eq. 8) for a loop "
        "candidate; lower it for scenes less self-similar than a city (docs/decisions.md: loop.threshold)")
    exclude_recent: int = Field(
        20, ge=0, description="temporal exclusion: only keyframes more than this many keyframes older than the new "
        "one qualify")
    min_time_gap: float = Field(
        10.0, ge=0.0, description="temporal exclusion: only keyframes at least this many seconds older than the new "
        "one qualify (applied together with exclude_recent)")
    max_candidates: int = Field(
        3, ge=1, description="at most this many best-scoring candidates per keyframe are verified and returned")
    # the adaptive threshold and the descriptor's layout are constants of .detector and .descriptor
    retired: ClassVar[dict[str, Any]] = {
        **VerificationConfig.retired, "adaptive_neighbours": 2, "adaptive_floor": 0.5, "adaptive_min_spread": 0.9,
        "thumbnail_size": [16, 12], "hog_cells": [4, 4], "hog_bins": 8, "thumbnail_weight": 0.5}
