"""Stretches of keyframes whose depth was not measured: where a monocular map's scale is not observed.

Why.  A monocular map measures depth only through parallax.  Through a turn on the spot (a pan from a tripod, a
person turning in place with the camera near the turning axis) no edge has any: each new keyframe's depth is the
previous one's moved into it, with the part of the view that is new filled by rows, a guess (:mod:`.observed`).
Once the turn has taken the measured part out of view, the scale of the map after the turn is the guessed depth's,
and the scene's own depth may differ on the other side: no depth guess can carry the scale (docs/decisions.md:
SCALE GAPS).  The run therefore says where it happened (``metrics.json``: ``tracking.scale_gaps``, and a warning),
and the evaluation aligns the parts on either side on their own too (``ate_segments``,
:func:`pvslam_core.evaluation.trajectory.ate_segments`).

A gap is a stretch of consecutive keyframes of one fragment that holds at least one *unmeasured* keyframe (at most
``MAX_SHARE`` of its pixels measured after its own window BA: :meth:`.observed.ObservedMasks.settled_fraction`, what
its depth was when the next keyframes were placed against it) and is bounded on both sides by a *well measured*
keyframe of the same fragment (at least ``WELL_MEASURED``); the keyframes in between are all under that.  Its
``turn_deg`` is the estimated rotation between the two bounding keyframes; ``beyond_fov``, whether that turn is wider
than the camera's horizontal field of view: then nothing whose depth was measured before the gap is in view after
it.  Those gaps warn and cut ``ate_segments``: most gaps of a head camera's stop-and-spins are beyond the view, and
the scale often changes across them.  Whether the camera stood cannot be told from the map: through such a gap its
translation is unobserved too.
"""
from __future__ import annotations

import bisect
import logging
import math
from dataclasses import asdict, dataclass
from typing import Callable

import torch

from .graph import FrameGraph
from .loops import rotation_deg

LOG = logging.getLogger("pvslam")

MAX_SHARE = 0.05  # a keyframe with at most this share of its pixels measured counts as unmeasured
WELL_MEASURED = 0.5  # ... with at least this share, as well measured (observed.GUESS_MIN_MEASURED)


@dataclass(frozen=True)
class ScaleGap:
    first_frame: int  # frame index of the first keyframe after the well measured one before the gap
    last_frame: int  # ... of the last one before the well measured one after it
    first_time: float  # their timestamps (s)
    last_time: float
    keyframes: int  # how many keyframes in between (all under well_measured)
    unmeasured: int  # ... of which unmeasured (at most max_share)
    turn_deg: float  # estimated rotation between the two well measured keyframes
    beyond_fov: bool  # turn_deg wider than the horizontal field of view

    def as_dict(self) -> dict:
        return asdict(self)


def horizontal_fov_deg(fx: float, width: int) -> float:
    """Horizontal field of view (degrees) of a pinhole camera ``fx`` pixels, ``width`` pixels wide."""
    return math.degrees(2.0 * math.atan(0.5 * width / fx))


def find_scale_gaps(poses_wc: torch.Tensor, shares: list[float], frames: list[int], times: list[float],
                    fragments: list[int], fov_deg: float) -> list[ScaleGap]:
    """The gaps (module docstring) among keyframes in graph order: camera-to-world poses ``poses_wc [N, 7]``, their
    measured shares, frame indices, timestamps and fragment numbers (``N`` each)."""
    n = len(shares)
    if not (poses_wc.shape[0] == len(frames) == len(times) == len(fragments) == n):
        raise ValueError(f"find_scale_gaps: {poses_wc.shape[0]} poses, {n} shares, {len(frames)} frames, "
                         f"{len(times)} timestamps, {len(fragments)} fragments")
    q = poses_wc[:, 3:7]
    gaps = []
    before = None  # the newest well measured keyframe so far (of the current fragment)
    for k in range(n):
        if before is not None and fragments[before] != fragments[k]:
            before = None
        if shares[k] < WELL_MEASURED:
            continue
        if before is not None and k - before > 1:
            a, b = before + 1, k - 1  # the gap's keyframes
            unmeasured = sum(1 for x in shares[a:k] if x <= MAX_SHARE)
            if unmeasured:
                turn = rotation_deg(q[before], q[k])
                gaps.append(ScaleGap(int(frames[a]), int(frames[b]), float(times[a]), float(times[b]), b - a + 1,
                                     unmeasured, round(turn, 1), turn > fov_deg))
        before = k
    return gaps


def graph_scale_gaps(graph: FrameGraph, measured: Callable[[int], float], fragment_starts: list[int]) -> list[ScaleGap]:
    """The gaps of ``graph``'s keyframes (``measured(kf_id)``: measured share; ``fragment_starts``: the first keyframe
    id of each map fragment, ascending); logs a warning for each one wider than the field of view."""
    ids = graph.ids.tolist()
    fragments = [bisect.bisect_right(fragment_starts, i) - 1 for i in ids]
    fov = horizontal_fov_deg(float(graph.intrinsics[0]), graph.ba_shape[1])
    gaps = find_scale_gaps(graph.poses.cpu(), [measured(i) for i in ids], graph.frame_index.tolist(),
                           graph.timestamps.tolist(), fragments, fov)
    for gap in gaps:
        if gap.beyond_fov:
            LOG.warning("frames %d-%d: the camera turned %.0f deg (wider than the %.0f deg field of view) while %d "
                        "keyframes had no depth measured: the map's scale after frame %d rests on guessed depth and "
                        "may differ from the scale before (a turn on the spot carries no scale for a single camera)",
                        gap.first_frame, gap.last_frame, gap.turn_deg, fov, gap.unmeasured, gap.last_frame)
    return gaps
