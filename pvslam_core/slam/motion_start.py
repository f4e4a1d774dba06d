"""A second start for a new keyframe's window BA after a stretch without parallax: its camera centre where the last
measured motion, continued at constant velocity, puts it.

Why.  Through a pan or a turn on the spot the keyframes have no parallax: their depth is mostly filled guesses
(:mod:`.observed`) and the window BA fits their small translations to those guesses.  A camera with a narrow field
of view trades translation for rotation along an almost flat direction of the cost, so the translations come out
short and turned (synthetic head camera, handheld_fast/88: after a 60 deg pan the keyframe at frame 96 sits 2.7 of
its true 6 cm off), and the next keyframe's pose guess inherits the error.  When the camera moves again, the first
window BA with parallax has two minima of nearly equal cost, the true one (flow cost 25 at the truth with fitted
depth) and a wrong rotation/translation pair (27 after three rounds, 4-5 deg of rotation off); started from the
guess it settles in the wrong one (46 after the one round the mapper runs), and the map then fits its depth to it
(ATE 15 %).  Started with the keyframe's centre at the constant-velocity prediction from the last two keyframes
whose depth was measured, the same BA lands in the true one (cost 42 after one round, 0.98 deg; 26 and 0.11 deg
after two).  Probes: bench/RESULTS.md, session 12-04 c.

So, when the two keyframes before a new one are mostly unmeasured (below ``graph.guess_min_measured``), the mapper
(:meth:`.window_ba.WindowBA._optimize_new`) runs its window BA from both starts, the second on the first one's
observations, and keeps the result with the lower flow cost under the observations of the first round (those from
the common start): the prediction is only a start, and where the camera did stop (a stop-and-spin) the guess wins.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from .graph import FrameGraph


def constant_velocity_centre(graph: FrameGraph, k: int, measured: Callable[[int], float], min_measured: float,
                             span: float, horizon: float, first: int = 0, stretch: int = 2) -> Optional[torch.Tensor]:
    """Camera centre ``[3]`` (float64, map frame) of keyframe ``k`` (graph index) at constant velocity from two earlier
    keyframes of the fragment starting at ``first``: ``b``, the newest before ``k`` whose measured fraction
    (``measured(kf_id)``) is at least ``min_measured``, and ``a``, the newest such keyframe at least ``span`` seconds
    before ``b``.  None unless the ``stretch`` keyframes before ``k`` are all under ``min_measured`` (nothing to
    second-guess), when ``b`` is more than ``horizon`` seconds before ``k`` (a long extrapolation says nothing), or
    without such a pair.

    Why a stretch of 2: a driving camera's newest keyframe has 0.35-0.49 of its pixels measured after its first window
    BA, the one before it 0.5-0.8 (busy_street, tune seed 1); with the reference alone as the test the second start ran
    on most keyframes of a drive, where the guess is good (bench/RESULTS.md, 12-04 c).  After a pan the last few are
    all under (handheld_fast/88: 0.31, 0.18, 0.28 before frame 105)."""
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
