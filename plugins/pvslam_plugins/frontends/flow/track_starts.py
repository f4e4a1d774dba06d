"""Where the ``flow`` frontend's tracking DIS starts (a mixin of :class:`~.frontend.FlowFrontend`).

DIS from zero finds a few tens of flow px at most (its coarsest level); a frame's motion against its keyframe can be
more.  So a frame's tracking DIS starts from, in order of need:

* the previous frame's flows at constant velocity (``track_velocity_init``, :meth:`TrackStarts._velocity_init`),
  when the previous frame tracked against the same keyframe and the motion is large enough;
* else, for the first frame after a keyframe, the motion predicted at constant rate (``track_predict_init``,
  :meth:`TrackStarts._predicted_start`), kept when more consistent than DIS from zero;
* when too many pixels still fail the forward-backward check (a fast turn), the homography of LK-tracked corners and
  then the predicted motion again (``track_recover_fail_fraction``, ``track_predict_recover``,
  :meth:`TrackStarts._recover`; the homography and the predictor: :mod:`.recover`).

It reads ``cfg``, ``stats``, ``ba_downsample``, ``_predictor``, ``_observing``, ``_flows``, ``_pair_calls``,
``_direction`` and ``_sigma`` of the frontend.  Flows are at the flow resolution, ``float32 [H, W, 2]``.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from . import flow_ops as F
from .recover import MotionPredictor, homography_flow


class TrackStarts:
    """The tracking starts of the flow frontend (see the module docstring)."""

    def _recover(self, g0: np.ndarray, g1: np.ndarray, ref_index: int, index: int, h: int, w: int,
                 fail_frac: float) -> Optional[tuple]:
        """A fast turn (more than ``track_recover_fail_fraction`` of the pixels fail the forward-backward check):
        DIS again from the homography of LK-tracked corners (:mod:`.recover`), and if that does not bring the
        failures under the threshold, from the motion predicted at constant rate (``track_predict_recover``).
        Returns the best flows that fail on fewer pixels than ``fail_frac``, ``(fwd, bwd, target, weight, fb,
        fail fraction)`` as :meth:`_direction` gives them, or None."""
        starts = [lambda: homography_flow(g0, g1)]
        if self.cfg.track_predict_recover:
            starts.append(lambda: self._predictor_ready().flows(ref_index, index, *g1.shape))
        best = None
        for start in starts:
            if fail_frac <= self.cfg.track_recover_fail_fraction:
                break
            hf = start()
            if hf is None:
                continue
            fwd2, bwd2 = self._flows(self._pair_calls(g0, g1, hf[0], hf[1], kind="track"))
            tf2, wf2, fb2 = self._direction(g0, g1, fwd2, bwd2, h, w)
            frac2 = self._fail_fraction(fb2)
            self.stats["track_recoveries"] += 1
            if frac2 < fail_frac:
                self.stats["track_recovered"] += 1
                best = (fwd2, bwd2, tf2, wf2, fb2, frac2)
                fail_frac = frac2
        return best

    def _predicted_start(self, g0: np.ndarray, g1: np.ndarray, ref_index: int, index: int, fwd: np.ndarray,
                         bwd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The flows ``(fwd, bwd)`` found from zero, or those found from the motion predicted at constant rate when
        that motion is at least ``track_init_min_flow`` BA px and they fail the forward-backward check on fewer
        pixels.  Why: the first frame after a keyframe has no velocity init, and in a fast pan DIS from zero finds
        part of the motion while most pixels still pass the check (handheld_fast/82, a 280 deg/s pan: half the
        motion, 36 % failing, under the recovery's 50 %; that keyframe's pose came out 14 deg off and the run
        11.3 %)."""
        pred = self._predictor_ready().flows(ref_index, index, *g0.shape)
        if pred is None:
            return fwd, bwd
        if self._mean_flow_ba(pred[0]) < self.cfg.track_init_min_flow:
            return fwd, bwd
        self.stats["track_predicted_starts"] += 1
        fwd2, bwd2 = self._flows(self._pair_calls(g0, g1, pred[0], pred[1], kind="track"))
        sigma = self._sigma()
        if (self._fail_fraction(F.fb_consistency(fwd2, bwd2, sigma)[1])
                < self._fail_fraction(F.fb_consistency(fwd, bwd, sigma)[1])):
            self.stats["track_predicted_used"] += 1
            return fwd2, bwd2
        return fwd, bwd

    def _fail_fraction(self, fb: np.ndarray) -> float:
        """Fraction of the pixels whose forward-backward error ``fb`` exceeds ``fb_fail_px`` (inf: left the image,
        failed too)."""
        return float(np.mean(~(fb <= self.cfg.fb_fail_px * self.cfg.flow_scale)))

    def _mean_flow_ba(self, flow: np.ndarray) -> float:
        """Mean length of a flow-resolution flow ``[H, W, 2]``, in BA px."""
        return float(np.sqrt((flow * flow).sum(-1)).mean()) / self.cfg.flow_scale / self.ba_downsample

    def _predictor_ready(self) -> MotionPredictor:
        """The motion predictor once its last observation (on a flow worker) has finished: the same state as with the
        observation made in place, in the same order."""
        if self._observing is not None:
            fut, self._observing = self._observing, None
            fut.result()
        return self._predictor

    def _velocity_init(self, p: Optional[tuple], ref_index: int,
                       index: int) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        """Initial flows (reference -> frame, frame -> reference) predicted from the previous frame's tracking
        against the same reference at constant velocity: its flows scaled by the ratio of the frame gaps.  ``p``: the
        previous track's ``(reference index, frame index, fwd, bwd)``.  None when there is no such track (first frame
        after a keyframe, a failure, a gap in the stream) or the predicted motion is small (track_init_min_flow)."""
        if not self.cfg.track_velocity_init or p is None or p[1] != index - 1 or p[0] != ref_index:
            return None, None
        gap, gap_p = index - ref_index, p[1] - p[0]
        if gap <= 0 or gap_p <= 0:
            return None, None
        s = min(gap / gap_p, 3.0)
        init_f = p[2] * s
        # a small predicted motion is what DIS finds from zero anyway; there the prediction only adds the previous
        # flow's noise (on a 160x120 video it lowered the forward-backward consistency)
        if self._mean_flow_ba(init_f) < self.cfg.track_init_min_flow:
            return None, None
        return init_f, p[3] * s
