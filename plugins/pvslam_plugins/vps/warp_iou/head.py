"""The ``warp_iou`` VPS head: forward-warp the previous panoptic ids into the current frame and re-label the
current thing segments by greedy same-category matching (PVO's tracking step, tools/1_tracking.py)."""
from __future__ import annotations

from typing import Any, Optional

import numpy as np

from pvslam_core.interfaces import MotionCue, VPSHead, VPSState
from pvslam_core.types import Frame, PanopticSegmentation

from ..matching import (  # noqa: F401 - the id layout is re-exported for callers of this module
    ID_OVERFLOW,
    ID_STRIDE,
    STUFF_ID_NONPOSITIVE,
    IdAllocator,
    WarpOptions,
    compose_id,
    decompose_id,
    match_segments,
    relabel,
    stuff_id,
    subsample,
    unique_ids,
    warp_previous_ids,
)
from .config import WarpIoUConfig


class WarpIoUHead(VPSHead):
    """Temporally consistent instance ids by warping + greedy same-category overlap matching.

    New thing instances get ids ``category_id * 1000 + counter`` with a per-category counter that only grows,
    so an id that disappeared is never reused within the run (call :meth:`reset` between sequences).
    ``last_matches`` holds ``(current segment id, previous id, score)`` of the last update, for diagnostics.
    """

    def __init__(self, config: Optional[WarpIoUConfig] = None) -> None:
        self.config = config or WarpIoUConfig()
        self._ids = IdAllocator()
        self.last_matches: list[tuple[int, int, float]] = []
        self.last_warped: Optional[np.ndarray] = None  # the warped previous ids of the last update (int64 [H, W])
        self.warp_options = WarpOptions()  # the warping settings (constants of ..matching)

    def reset(self) -> None:
        self._ids.reset()

    # ------------------------------------------------------------------------------------------------------
    def update(
        self, prev: Optional[VPSState], frame: Frame, seg: PanopticSegmentation, cue: Optional[MotionCue] = None
    ) -> VPSState:
        c = self.config
        cue = cue or MotionCue()
        ids = seg.ids.detach().cpu().numpy().astype(np.int64)
        h, w = ids.shape
        cur_segments = {s.id: s for s in seg.segments if s.id != 0}
        present = set(unique_ids(ids).tolist()) - {0}
        cur_things = sorted(sid for sid in present if sid in cur_segments and cur_segments[sid].isthing)

        warped = None
        if prev is not None:
            self._ids.reserve(prev.panoptic.segments)
            if cur_things:
                warped = warp_previous_ids(prev, frame.image, cue, h, w, self.warp_options)
        self.last_warped = warped

        assign: dict[int, int] = {}  # current segment id -> output id
        self.last_matches = []
        if warped is not None:
            prev_cat = {s.id: s.category_id for s in prev.panoptic.segments if s.isthing}
            cur_cat = {g: cur_segments[g].category_id for g in cur_things}
            for g, p, score in match_segments(ids, warped, cur_things, cur_cat, prev_cat, c.match, c.min_score):
                assign[g] = p
                self.last_matches.append((g, p, score))
        panoptic = relabel(seg, ids, cur_segments, cur_things, present, assign, self._ids)
        return VPSState(frame_index=int(frame.index), panoptic=panoptic, image=frame.image)


def make_vps_head(config: WarpIoUConfig, context: Any = None) -> WarpIoUHead:
    return WarpIoUHead(config)
