"""Where the ``flow`` frontend's tracking DIS starts, and its recovery when a fast turn defeats it.

DIS from zero finds a few tens of flow px at most (its coarsest level); a frame's motion against its keyframe can be
more.  So a frame's tracking DIS starts from, in order of need:

* the previous frame's flows at constant velocity (``TRACK_VELOCITY_INIT``), when the previous frame tracked against
  the same keyframe and the motion is large enough;
* else, for the first frame after a keyframe, the motion predicted at constant rate (``TRACK_PREDICT_INIT``), kept
  when more consistent than DIS from zero;
* when too many pixels still fail the forward-backward check (``TRACK_RECOVER_FAIL_FRACTION``: a fast turn), the
  homography of LK-tracked corners and then the predicted motion again (``TRACK_PREDICT_RECOVER``; the homography and
  the predictor: :mod:`.recover`).

:class:`TrackStarts` owns what these need across frames: the previous frame's flows and the motion predictor.  Flows
are at the flow resolution, ``float32 [H, W, 2]``.
"""
from __future__ import annotations

from concurrent.futures import Future
from typing import Callable, Optional

import numpy as np

from . import flow_ops as F
from .pair_flow import FlowPairs
from .recover import MotionPredictor, homography_flow

# start DIS from the previous frame's flows scaled to this frame's gap (constant velocity) instead of zero
# (docs/decisions.md: TRACK_VELOCITY_INIT)
TRACK_VELOCITY_INIT = True
# ... and from a predicted motion only when its mean flow is at least this (BA px): a smaller motion is found from
# zero, where the prediction only adds the previous flow's noise
TRACK_INIT_MIN_FLOW = 1.0
# recover when more than this fraction of the pixels fail the forward-backward check (docs/decisions.md:
# TRACK_RECOVER_FAIL_FRACTION)
TRACK_RECOVER_FAIL_FRACTION = 0.5
# when the corners' homography does not recover a failing frame, try the motion predicted at constant rate too (a
# fast turn over a scene with few corners; docs/decisions.md: TRACK_PREDICT_RECOVER)
TRACK_PREDICT_RECOVER = True
# a frame without a velocity init also tries the predicted motion and keeps the more consistent flow (a fast pan that
# DIS from zero finds only in part; docs/decisions.md: TRACK_PREDICT_INIT)
TRACK_PREDICT_INIT = True

Tracked = tuple[int, int, np.ndarray, np.ndarray]  # (reference frame index, frame index, fwd, bwd) of a tracked frame
# a frame's starting flows (fwd, bwd) and the counts they took: DIS calls, their seconds, predicted starts tried / used
Started = tuple[np.ndarray, np.ndarray, dict]


class TrackStarts:
    """The starts of a frame's tracking DIS (module docstring).  Per frame: :meth:`new_frame`, :meth:`start`,
    :meth:`recover` and, when the frame tracked, :meth:`tracked`."""

    def __init__(self, pairs: FlowPairs, ba_downsample: int):
        self._pairs = pairs
        self._ba_downsample = int(ba_downsample)
        self._last: Optional[Tracked] = None  # the last tracked frame (set when it tracked)
        self._prev: Optional[Tracked] = None  # ... as the current frame sees it: the frame before, if it tracked
        self._predictor = MotionPredictor()  # per-frame homographies for the predicted starts (recover.py)
        # the predictor's last observation, running on a flow worker: its RANSAC homography (~1 ms a frame) is needed
        # only when a later frame asks for a prediction, so the pipeline thread does not wait for it (predictor())
        self._observing: Optional[Future] = None
        self.stats = {"track_recoveries": 0, "track_recovered": 0, "track_predicted_starts": 0,
                      "track_predicted_used": 0}

    def new_frame(self) -> None:
        """A new frame is being tracked: the previous one's flows can start it only if it tracked."""
        self._prev, self._last = self._last, None

    @property
    def previous(self) -> Optional[Tracked]:
        """The tracked frame that starts the frame being tracked (None: it starts from zero or the prediction)."""
        return self._prev

    def start(self, g0: np.ndarray, g1: np.ndarray, ref_index: int, index: int,
              ahead: Optional[Started] = None) -> tuple[np.ndarray, np.ndarray]:
        """Both tracking flows ``(fwd, bwd)`` of frame ``index`` (gray ``g1``) against the reference ``ref_index``
        (gray ``g0``): from the velocity init, else from zero or the predicted motion, whichever is more consistent.
        ``ahead``: what :meth:`ahead`'s job computed for these inputs (the caller checked they are these)."""
        fwd, bwd, counts = ahead if ahead is not None else \
            self._start(g0, g1, ref_index, index, self._prev, self.predictor)
        self._pairs.count(counts["dis_calls"], counts["dis_s"])
        for k in ("track_predicted_starts", "track_predicted_used"):
            self.stats[k] += counts[k]
        return fwd, bwd

    def ahead(self, g0: np.ndarray, ref_index: int) -> tuple[Optional[Tracked], Callable[[np.ndarray, int], Started]]:
        """The next frame's :meth:`start` before :meth:`new_frame`: ``(prev, job)``, ``prev`` the tracked frame that
        will start it and ``job(g1, index)`` its flows against ``ref_index`` (gray ``g0``), for another thread.  The job
        reads the motion predictor once its pending observation is done and changes nothing here (:meth:`start`
        counts), so the flows are those :meth:`start` would compute, as long as the next frame tracks against
        ``ref_index`` from ``prev``."""
        prev, observing = self._last, self._observing

        def predictor() -> MotionPredictor:
            if observing is not None:
                observing.result()  # on the lane worker, queued before this job's DIS calls
            return self._predictor

        return prev, lambda g1, index: self._start(g0, g1, ref_index, index, prev, predictor)

    def _start(self, g0: np.ndarray, g1: np.ndarray, ref_index: int, index: int, prev: Optional[Tracked],
               predictor: Callable[[], MotionPredictor]) -> Started:
        counts = {"dis_calls": 0, "dis_s": 0.0, "track_predicted_starts": 0, "track_predicted_used": 0}

        def flows(calls):
            out, seconds = self._pairs.lanes.run(calls)
            counts["dis_calls"] += len(calls)
            counts["dis_s"] += seconds
            return out

        init_f, init_b = self._velocity_init(prev, ref_index, index)
        fwd, bwd = flows(self._pairs.pair_calls(g0, g1, init_f, init_b, kind="track"))
        if init_f is None and TRACK_PREDICT_INIT:  # no velocity init (e.g. the first frame after a keyframe)
            fwd, bwd = self._predicted_start(g0, g1, ref_index, index, fwd, bwd, predictor, flows, counts)
        return fwd, bwd, counts

    def recover(self, g0: np.ndarray, g1: np.ndarray, ref_index: int, index: int, h: int, w: int,
                fail_frac: float) -> Optional[tuple]:
        """When more than ``TRACK_RECOVER_FAIL_FRACTION`` of the pixels fail the forward-backward check (a fast
        turn): DIS again from the homography of LK-tracked corners (:mod:`.recover`), and if that does not bring the
        failures under the threshold, from the motion predicted at constant rate (``TRACK_PREDICT_RECOVER``).
        Returns the best flows that fail on fewer pixels than ``fail_frac``, ``(fwd, bwd, target, weight, fb,
        fail fraction)`` as :meth:`.FlowPairs.direction` gives them, or None."""
        starts = [lambda: homography_flow(g0, g1)]
        if TRACK_PREDICT_RECOVER:
            starts.append(lambda: self.predictor().flows(ref_index, index, *g1.shape))
        best = None
        for start in starts:
            if fail_frac <= TRACK_RECOVER_FAIL_FRACTION:
                break
            hf = start()
            if hf is None:
                continue
            fwd2, bwd2 = self._pairs.flows(self._pairs.pair_calls(g0, g1, hf[0], hf[1], kind="track"))
            tf2, wf2, fb2 = self._pairs.direction(g0, g1, fwd2, bwd2, h, w)
            frac2 = self._pairs.fail_fraction(fb2)
            self.stats["track_recoveries"] += 1
            if frac2 < fail_frac:
                self.stats["track_recovered"] += 1
                best = (fwd2, bwd2, tf2, wf2, fb2, frac2)
                fail_frac = frac2
        return best

    def tracked(self, ref_index: int, index: int, fwd: np.ndarray, bwd: np.ndarray, ok: np.ndarray) -> None:
        """Frame ``index`` tracked against ``ref_index`` with flows ``fwd`` / ``bwd`` (``ok [H, W]``: the pixels that
        pass the forward-backward check): it may start the next frame, and the predictor observes it (on a flow
        worker)."""
        self._last = (ref_index, index, fwd, bwd)
        if TRACK_PREDICT_RECOVER or TRACK_PREDICT_INIT:
            self._observing = self._pairs.lanes.submit(self.predictor().observe, ref_index, index, fwd, ok)

    def predictor(self) -> MotionPredictor:
        """The motion predictor once its last observation (on a flow worker) has finished: the same state as with the
        observation made in place, in the same order."""
        if self._observing is not None:
            fut, self._observing = self._observing, None
            fut.result()
        return self._predictor

    # ------------------------------------------------------------------------------------------- starts --
    def _predicted_start(self, g0: np.ndarray, g1: np.ndarray, ref_index: int, index: int, fwd: np.ndarray,
                         bwd: np.ndarray, predictor: Callable[[], MotionPredictor], flows: Callable,
                         counts: dict) -> tuple[np.ndarray, np.ndarray]:
        """The flows ``(fwd, bwd)`` found from zero, or those found from the motion predicted at constant rate when
        that motion is at least ``TRACK_INIT_MIN_FLOW`` BA px and they fail the forward-backward check on fewer
        pixels.  Why: the first frame after a keyframe has no velocity init, and in a fast pan DIS from zero finds
        part of the motion while most pixels still pass the check, under the recovery's threshold."""
        pred = predictor().flows(ref_index, index, *g0.shape)
        if pred is None:
            return fwd, bwd
        if self._mean_flow_ba(pred[0]) < TRACK_INIT_MIN_FLOW:
            return fwd, bwd
        counts["track_predicted_starts"] += 1
        fwd2, bwd2 = flows(self._pairs.pair_calls(g0, g1, pred[0], pred[1], kind="track"))
        sigma, fail = self._pairs.sigma, self._pairs.fail_fraction
        if fail(F.fb_consistency(fwd2, bwd2, sigma)[1]) < fail(F.fb_consistency(fwd, bwd, sigma)[1]):
            counts["track_predicted_used"] += 1
            return fwd2, bwd2
        return fwd, bwd

    def _mean_flow_ba(self, flow: np.ndarray) -> float:
        """Mean length of a flow-resolution flow ``[H, W, 2]``, in BA px."""
        return float(np.sqrt((flow * flow).sum(-1)).mean()) / self._pairs.scale / self._ba_downsample

    def _velocity_init(self, p: Optional[Tracked], ref_index: int,
                       index: int) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        """Initial flows (reference -> frame, frame -> reference) predicted from the previous frame's tracking
        against the same reference at constant velocity: its flows scaled by the ratio of the frame gaps.  None when
        there is no such track (first frame after a keyframe, a failure, a gap in the stream) or the predicted
        motion is small (``TRACK_INIT_MIN_FLOW``)."""
        if not TRACK_VELOCITY_INIT or p is None or p[1] != index - 1 or p[0] != ref_index:
            return None, None
        gap, gap_p = index - ref_index, p[1] - p[0]
        if gap <= 0 or gap_p <= 0:
            return None, None
        s = min(gap / gap_p, 3.0)
        init_f = p[2] * s
        # a small predicted motion is what DIS finds from zero anyway; there the prediction only adds the previous
        # flow's noise (on a small video it lowered the forward-backward consistency)
        if self._mean_flow_ba(init_f) < TRACK_INIT_MIN_FLOW:
            return None, None
        return init_f, p[3] * s
