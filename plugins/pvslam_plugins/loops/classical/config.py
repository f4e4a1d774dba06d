"""Configuration of the ``classical`` loop detector."""
from __future__ import annotations

from pydantic import Field

from pvslam_core.config_base import PluginConfig


class ClassicalLoopConfig(PluginConfig):
    # --- retrieval -------------------------------------------------------------------------------------------
    threshold: float = Field(
        0.75, ge=-1.0, le=1.0,
        description="minimum cosine similarity of the global descriptors (paper eq. 8) for a loop candidate "
        "(unrelated photos score about 0-0.35; the self-similar synthetic city 0.6 median, 0.79 at the 90th "
        "percentile; revisits within 3 m 0.85-1.0). Only candidates above it are verified",
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
    # --- geometric verification --------------------------------------------------------------------------------
    verify: bool = Field(
        True,
        description="run geometric verification (ORB + essential-matrix RANSAC); false returns retrieval-only "
        "candidates (verified = None), which the loop policy accepts on score when loop_closure.accept_unverified "
        "is true (ablations; look-alike places then close false loops)",
    )
    orb_features: int = Field(
        500, ge=50,
        description="ORB keypoints per keyframe (extracted lazily, only for keyframes that take part in a "
        "verification; matching cost grows with the square of this)",
    )
    store_max_side: int = Field(
        640, ge=64,
        description="keyframe images are kept (grayscale JPEG, for lazy ORB extraction) with their longer side "
        "reduced to at most this many pixels",
    )
    jpeg_quality: int = Field(90, ge=50, le=100, description="JPEG quality of the stored keyframe images")
    feature_cache: int = Field(
        256, ge=1, description="ORB features of at most this many keyframes are kept in memory (LRU)"
    )
    ratio: float = Field(0.8, gt=0.0, le=1.0, description="Lowe ratio test on Hamming distances")
    cross_check: bool = Field(True, description="keep only mutual nearest-neighbour ORB matches")
    ransac_threshold_px: float = Field(
        1.5, gt=0.0, description="essential-matrix RANSAC threshold in pixels of the stored keyframe image"
    )
    min_inliers: int = Field(
        80, ge=5,
        description="accept a candidate if the essential-matrix RANSAC keeps at least this many inliers "
        "(between ORB matches of the two keyframes). Calibrated for orb_features=500: on the synthetic "
        "driving loop true revisits (<= 3 m) have 100-400 inliers, look-alike places elsewhere up to ~110",
    )
    min_inlier_ratio: float = Field(
        0.5, ge=0.0, le=1.0, description="... and at least this fraction of the tentative ORB matches"
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
