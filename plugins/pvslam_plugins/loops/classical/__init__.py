"""``classical`` loop detector (no weights): global image descriptor + ORB / essential-matrix verification.

* Descriptor (:mod:`.descriptor`): blurred zero-mean grayscale thumbnail + a grid of gradient-orientation
  histograms, L2-normalised; similarity = cosine (the paper's eq. 8).
* Candidates: keyframes older than the temporal exclusion window (``exclude_recent`` keyframes and
  ``min_time_gap`` seconds) with similarity >= ``threshold``, best ``max_candidates`` first.
* Verification (:mod:`pvslam_plugins.loops.verification`, shared with the ``deit`` detector): ORB matches (ratio
  test + mutual check), essential-matrix RANSAC with the keyframes' intrinsics; verified with >= ``min_inliers``
  inliers and inlier ratio >= ``min_inlier_ratio``.
  Which candidates close a loop is the mapper's loop policy (``[loop_closure]``: consecutive hits, suppression,
  orientation check), not the detector's.

Registered as loop plugin ``classical`` (entry point ``classical``).
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl


@hookimpl
def register_loop_detectors(register):  # type: ignore[no-untyped-def]
    from .config import ClassicalLoopConfig
    from .detector import make_loop_detector

    register(
        "classical",
        make_loop_detector,
        ClassicalLoopConfig,
        description="thumbnail + gradient-histogram descriptor (cosine), ORB + essential-matrix verification",
    )
