"""Watching a run as it goes: the interface a live viewer implements.

The pipeline holds at most one :class:`RunObserver` and calls it directly (never through a plugin hook): every
frame, after each new keyframe (poses and depths just optimised), for each accepted loop closure, and once at
the end.  The core never imports a viewer library; the rerun viewer lives in :mod:`pvslam_core.viz.rerun_viewer`
and is loaded only when asked for (``pvslam run --viz``).

Observers must not modify what they are given and should copy what they keep: tensors are the SLAM state's own
(on the CPU).  An observer that raises is switched off with one logged error; the run goes on.
"""
from __future__ import annotations

from typing import Optional, Sequence

from .slam.map_state import KeyframeSnapshot  # noqa: F401 - what a viewer is given of the map's keyframes
from .types import Category, Frame, FrameResult, LoopClosure, PanopticSegmentation, RunResult, SequenceInfo


class RunObserver:
    """Optional callbacks of a running pipeline; every method defaults to doing nothing."""

    def on_start(self, info: SequenceInfo, categories: Sequence[Category]) -> None:
        """Before the first frame: the sequence and the categories of the panoptic output."""

    def on_frame(self, frame: Frame, result: FrameResult, panoptic: Optional[PanopticSegmentation]) -> None:
        """After each frame: the frame as read, the mapper's result (pose T_wc at this time), the frame's
        temporally consistent panoptic segmentation (None without a segmenter/VPS)."""

    def on_keyframes(self, keyframes: KeyframeSnapshot) -> None:
        """After a frame that became a keyframe, once the map is initialised (the window BA has run)."""

    def on_loop(self, loop: LoopClosure, keyframes: KeyframeSnapshot) -> None:
        """For each accepted loop closure, after its optimisation."""

    def on_finish(self, result: RunResult, keyframes: KeyframeSnapshot) -> None:
        """After the final optimisation: every frame's final pose and the final keyframes."""
