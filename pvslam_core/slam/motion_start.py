"""A second start for a new keyframe's window BA after a stretch without parallax: its camera centre where the last
measured motion, continued at constant velocity, puts it.

Why.  Through a pan or a turn on the spot the keyframes have no parallax: their depth is mostly filled guesses
(:mod:`.observed`) and the window BA fits their small translations to those guesses.  A camera with a narrow field
of view trades translation for rotation along an almost flat direction of the cost, so the translations come out
short and turned, and the next keyframe's pose guess inherits the error.  When the camera moves again, the first
window BA with parallax can have two minima of nearly equal cost, the true one and a wrong rotation/translation
pair; started from the guess it may settle in the wrong one, and the map then fits its depth to it.  Started with
the keyframe's centre at the constant-velocity prediction from the last two keyframes whose depth was measured, the
same BA lands in the true one (docs/decisions.md: SECOND_START).

So, when the two keyframes before a new one are mostly unmeasured (below ``observed.GUESS_MIN_MEASURED``), the window
BA (:meth:`.window_ba.WindowBA.optimize_new`) runs from both starts, the second on the first one's observations, and
keeps the result with the lower flow cost under the observations of the first round (those from the common start):
the prediction is only a start, and where the camera did stop (a stop-and-spin) the guess wins.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from .graph import FrameGraph

SPAN = 0.25  # seconds between the two measured keyframes whose motion the second start continues
HORIZON = 1.0  # the second start predicts at most this many seconds past the last measured keyframe


def constant_velocity_centre(graph: FrameGraph, k: int, measured: Callable[[int], float], min_measured: float,
                             span: float, horizon: float, first: int = 0, stretch: int = 2) -> Optional[torch.Tensor]:
    """Camera centre ``[3]`` (float64, map frame) of keyframe ``k`` (graph index) at constant velocity from two earlier
    keyframes of the fragment starting at ``first``: ``b``, the newest before ``k`` whose measured fraction
    (``measured(kf_id)``) is at least ``min_measured``, and ``a``, the newest such keyframe at least ``span`` seconds
    before ``b``.  None unless the ``stretch`` keyframes before ``k`` are all under ``min_measured`` (nothing to
    second-guess), when ``b`` is more than ``horizon`` seconds before ``k`` (a long extrapolation says nothing), or
    without such a pair.

    Why a stretch of 2: a driving camera's newest keyframe is often under half measured after its first window BA
    while the one before it is not; with the reference alone as the test the second start would run on most keyframes
    of a drive, where the guess is good.  After a pan the last few are all under."""
    if k - stretch < first or any(measured(graph.id_of(k - n)) >= min_measured for n in range(1, stretch + 1)):
        return None
    ts = graph.timestamps.tolist()
    b = a = None
    for i in range(k - 1, first - 1, -1):
        if ts[k] - ts[i] > horizon + span:
            break
        if measured(graph.id_of(i)) < min_measured:
            continue
        if b is None:
            if ts[k] - ts[i] > horizon:
                return None
            b = i
        elif ts[b] - ts[i] >= span:
            a = i
            break
    if a is None:
        return None
    ca, cb = graph.poses[a, :3].double(), graph.poses[b, :3].double()
    return cb + (cb - ca) * ((ts[k] - ts[b]) / (ts[b] - ts[a]))
