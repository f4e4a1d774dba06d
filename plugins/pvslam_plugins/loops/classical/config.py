"""Configuration of the ``classical`` loop detector (the verification fields are the shared ones of
:class:`~pvslam_plugins.loops.verification.VerificationConfig`)."""
from __future__ import annotations

from pydantic import Field

from ..verification import VerificationConfig


class ClassicalLoopConfig(VerificationConfig):
    # --- retrieval -------------------------------------------------------------------------------------------
    threshold: float = Field(
        0.75, ge=-1.0, le=1.0,
        description="minimum cosine similarity of the global descriptors (paper eq. 8) for a loop candidate "
        "(unrelated photos score about 0-0.35; the self-similar synthetic city 0.6 median, 0.79 at the 90th "
        "percentile; revisits within 3 m 0.85-1.0). Only candidates above it are verified",
    )
    adaptive_neighbours: int = Field(
        2, ge=0,
        description="adaptive threshold (ORB-SLAM's rule): when the new keyframe's lowest similarity to its this "
        "many predecessors is below `threshold`, candidates need only that (0: the fixed threshold); such "
        "candidates must also pass adaptive_min_spread (bench/RESULTS.md, issue 13)",
    )
    adaptive_floor: float = Field(
        0.5, ge=-1.0, le=1.0, description="the adaptive threshold never goes below this similarity"
    )
    adaptive_min_spread: float = Field(
        0.9, ge=0.0,
        description="a candidate below `threshold` (retrieved through the adaptive threshold) passes verification "
        "only when the new keyframe sees the matched structure about as large as the old one (inlier spread new / "
        "old at least this): a revisit of the same spot, not a view of it from far away",
    )
    exclude_recent: int = Field(
        20, ge=0,
        description="temporal exclusion: only keyframes more than this many keyframes older than the new one qualify",
    )
    min_time_gap: float = Field(
        10.0, ge=0.0,
        description="temporal exclusion: only keyframes at least this many seconds older than the new one qualify "
        "(applied together with exclude_recent)",
    )
    max_candidates: int = Field(
        3, ge=1, description="at most this many best-scoring candidates per keyframe are verified and returned"
    )
    # --- descriptor ----------------------------------------------------------------------------------------------
    thumbnail_size: tuple[int, int] = Field(
        (16, 12), description="(width, height) of the blurred, zero-mean grayscale thumbnail part of the descriptor"
    )
    hog_cells: tuple[int, int] = Field((4, 4), description="(columns, rows) of gradient-orientation histogram cells")
    hog_bins: int = Field(8, ge=2, description="unsigned orientation bins per cell")
    thumbnail_weight: float = Field(
        0.5, ge=0.0, le=1.0,
        description="share of the thumbnail in the cosine similarity (the rest is the orientation-histogram part)",
    )
