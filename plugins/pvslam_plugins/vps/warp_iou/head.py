"""The ``warp_iou`` VPS head: forward-warp the previous panoptic ids into the current frame and re-label the
current thing segments by greedy same-category matching (PVO's tracking step, tools/1_tracking.py)."""
from __future__ import annotations

from typing import Any, Optional

import cv2
import numpy as np
import torch

from pvslam_core.interfaces import MotionCue, VPSHead, VPSState
from pvslam_core.types import Frame, PanopticSegmentation, Segment

from .config import WarpIoUConfig
from .warp import dis_flow, forward_warp, resize_flow, rigid_flow

#: id layout: stuff = category_id * ID_STRIDE; the c-th new instance of a thing category (c = 1, 2, ...) gets
#: ``category_id * ID_STRIDE + c % ID_STRIDE + (c // ID_STRIDE) * ID_OVERFLOW`` (= category_id * 1000 + c while
#: c < 1000; later instances stay unique without colliding with another category's ids)
ID_STRIDE = 1000
ID_OVERFLOW = 10_000_000
#: id for stuff of a category id <= 0 (cannot be written as category_id * 1000, which would be void)
STUFF_ID_NONPOSITIVE = 9_999_000


def compose_id(category_id: int, counter: int) -> int:
    return category_id * ID_STRIDE + counter % ID_STRIDE + (counter // ID_STRIDE) * ID_OVERFLOW


def decompose_id(sid: int) -> tuple[int, int]:
    """Inverse of :func:`compose_id`: ``(category_id, counter)``."""
    hi, rem = divmod(int(sid), ID_OVERFLOW)
    return rem // ID_STRIDE, hi * ID_STRIDE + rem % ID_STRIDE


def stuff_id(category_id: int) -> int:
    return category_id * ID_STRIDE if category_id > 0 else STUFF_ID_NONPOSITIVE


def _lut(keys: np.ndarray, values: np.ndarray, query: np.ndarray, default: int) -> np.ndarray:
    """values[keys == q] for each q in ``query`` (``default`` where absent)."""
    if len(keys) == 0:
        return np.full(query.shape, default, dtype=values.dtype if len(values) else np.int64)
    order = np.argsort(keys)
    k, v = keys[order], values[order]
    pos = np.searchsorted(k, query).clip(max=len(k) - 1)
    return np.where(k[pos] == query, v[pos], default)


def _working_shape(h: int, w: int, max_side: Optional[int]) -> tuple[int, int]:
    if max_side is None or max(h, w) <= max_side:
        return h, w
    s = max_side / float(max(h, w))
    return max(1, int(round(h * s))), max(1, int(round(w * s)))


def _subsample(ids: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest (pixel-centre) resampling of an id map ``[H, W]`` to ``[h, w]`` (exact for any ids)."""
    H, W = ids.shape
    if (H, W) == (h, w):
        return ids
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    return ids[rows[:, None], cols[None, :]]


class WarpIoUHead(VPSHead):
    """Temporally consistent instance ids by warping + greedy same-category overlap matching.

    New thing instances get ids ``category_id * 1000 + counter`` with a per-category counter that only grows,
    so an id that disappeared is never reused within the run (call :meth:`reset` between sequences).
    ``last_matches`` holds ``(current segment id, previous id, score)`` of the last update, for diagnostics.
    """

    def __init__(self, config: Optional[WarpIoUConfig] = None) -> None:
        self.config = config or WarpIoUConfig()
        self._counters: dict[int, int] = {}
        self.last_matches: list[tuple[int, int, float]] = []
        self._last_warped: Optional[np.ndarray] = None  # at the working resolution
        self._full_shape: tuple[int, int] = (0, 0)

    @property
    def last_warped(self) -> Optional[np.ndarray]:
        """The warped previous ids of the last update (int64 ``[H, W]``, nearest-upsampled from the working
        resolution), for diagnostics."""
        if self._last_warped is None:
            return None
        return _subsample(self._last_warped, *self._full_shape)

    def reset(self) -> None:
        self._counters.clear()

    def _new_id(self, category_id: int) -> int:
        c = self._counters.get(category_id, 0) + 1
        self._counters[category_id] = c
        return compose_id(category_id, c)

    def _reserve(self, segments: list[Segment]) -> None:
        """Advance the counters past ids seen in a previous state (so they are never handed out again)."""
        for s in segments:
            if s.isthing:
                cat, c = decompose_id(s.id)
                if cat == s.category_id and c > self._counters.get(cat, 0):
                    self._counters[cat] = c

    # ------------------------------------------------------------------------------------------------------
    def update(
        self, prev: Optional[VPSState], frame: Frame, seg: PanopticSegmentation, cue: Optional[MotionCue] = None
    ) -> VPSState:
        cue = cue or MotionCue()
        ids = seg.ids.detach().cpu().numpy().astype(np.int64)
        h, w = ids.shape
        cur_segments = {s.id: s for s in seg.segments if s.id != 0}
        present = set(np.unique(ids).tolist()) - {0}
        cur_things = sorted(sid for sid in present if sid in cur_segments and cur_segments[sid].isthing)

        # warping and matching at the working resolution (see WarpIoUConfig.warp_max_side)
        hs, ws = _working_shape(h, w, self.config.warp_max_side)
        warped = None
        if prev is not None and cur_things:
            self._reserve(prev.panoptic.segments)
            warped = self._warp_previous(prev, frame, cue, hs, ws)
        elif prev is not None:
            self._reserve(prev.panoptic.segments)
        self._last_warped, self._full_shape = warped, (h, w)

        assign: dict[int, int] = {}  # current segment id -> output id
        self.last_matches = []
        if warped is not None:
            prev_cat = {s.id: s.category_id for s in prev.panoptic.segments if s.isthing}
            for g, p, score in self._match(_subsample(ids, hs, ws), warped, cur_things, cur_segments, prev_cat):
                assign[g] = p
                self.last_matches.append((g, p, score))

        out_segments: dict[int, Segment] = {}
        for sid in cur_things:  # ascending segment id: deterministic new ids
            s = cur_segments[sid]
            oid = assign.get(sid)
            if oid is None:
                oid = self._new_id(s.category_id)
                assign[sid] = oid
            out_segments[oid] = Segment(oid, s.category_id, True, s.score)
        for sid in sorted(present):
            s = cur_segments.get(sid)
            if s is None or s.isthing:
                continue
            oid = stuff_id(s.category_id)
            assign[sid] = oid
            old = out_segments.get(oid)
            score = s.score if old is None else max(old.score, s.score)
            out_segments[oid] = Segment(oid, s.category_id, False, score)

        keys = np.array(list(assign.keys()), dtype=np.int64)
        vals = np.array(list(assign.values()), dtype=np.int64)
        out_ids = _lut(keys, vals, ids.reshape(-1), 0).reshape(h, w)  # ids without a segment -> void
        panoptic = PanopticSegmentation(
            ids=torch.from_numpy(np.ascontiguousarray(out_ids, dtype=np.int64)),
            segments=[out_segments[k] for k in sorted(out_segments)],
            features=seg.features,
        )
        return VPSState(frame_index=int(frame.index), panoptic=panoptic, image=frame.image)

    # ------------------------------------------------------------------------------------------------------
    def _warp_previous(self, prev: VPSState, frame: Frame, cue: MotionCue, h: int, w: int) -> np.ndarray:
        c = self.config
        pids = _subsample(prev.panoptic.ids.detach().cpu().numpy().astype(np.int64), h, w)
        if cue.flow is not None:
            flow = resize_flow(cue.flow.detach().cpu().numpy().astype(np.float32), h, w)
        elif prev.image is not None:
            flow = dis_flow(prev.image, frame.image, c.flow_preset, c.flow_max_side)
            flow = resize_flow(flow, h, w)
        else:
            flow = np.zeros((2, h, w), np.float32)

        depth = None
        if cue.depth_prev is not None:
            depth = cue.depth_prev.detach().cpu().numpy().astype(np.float32)
            if depth.shape != (h, w):
                sx, sy = w / depth.shape[1], h / depth.shape[0]
                depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
            else:
                sx = sy = 1.0
            if (c.rigid_stuff and cue.pose_prev is not None and cue.pose_cur is not None
                    and cue.intrinsics is not None):
                k = cue.intrinsics.detach().cpu().double().numpy()[:4].copy()
                k[0] *= sx
                k[1] *= sy
                k[2] = (k[2] + 0.5) * sx - 0.5
                k[3] = (k[3] + 0.5) * sy - 0.5
                rflow, _, valid = rigid_flow(depth, cue.pose_prev.detach().cpu().double().numpy(),
                                             cue.pose_cur.detach().cpu().double().numpy(), k)
                prev_thing = {s.id for s in prev.panoptic.segments if s.isthing}
                is_thing = np.isin(pids, np.array(sorted(prev_thing), dtype=np.int64))
                use = valid & ~is_thing & (pids != 0)
                flow = np.where(use[None], rflow, flow)
            mask = None  # depth orders the writes, so occluding stuff may hide things
        else:
            prev_thing = np.array(sorted(s.id for s in prev.panoptic.segments if s.isthing), dtype=np.int64)
            mask = np.isin(pids, prev_thing)  # without depth, only things are warped (no z-order for stuff)
        return forward_warp(pids, flow, depth, mask, splat=c.splat)

    def _match(
        self,
        ids: np.ndarray,
        warped: np.ndarray,
        cur_things: list[int],
        cur_segments: dict[int, Segment],
        prev_cat: dict[int, int],
    ) -> list[tuple[int, int, float]]:
        """Greedy one-to-one same-category assignment by score (best first) above ``min_score``."""
        c = self.config
        prev_ids = sorted(set(np.unique(warped).tolist()) & set(prev_cat))
        if not prev_ids or not cur_things:
            return []
        g_keys = np.array(cur_things, dtype=np.int64)
        p_keys = np.array(prev_ids, dtype=np.int64)
        gi = _lut(g_keys, np.arange(len(g_keys), dtype=np.int64), ids.reshape(-1), -1)
        pi = _lut(p_keys, np.arange(len(p_keys), dtype=np.int64), warped.reshape(-1), -1)
        G, P = len(g_keys), len(p_keys)
        area_g = np.bincount(gi[gi >= 0], minlength=G)
        area_p = np.bincount(pi[pi >= 0], minlength=P)
        both = (gi >= 0) & (pi >= 0)
        inter = np.bincount(gi[both] * P + pi[both], minlength=G * P).reshape(G, P)
        if c.match == "iou":
            union = area_g[:, None] + area_p[None, :] - inter
            score = inter / np.maximum(union, 1)
        else:
            score = inter / np.maximum(area_p[None, :], 1)
        cat_g = np.array([cur_segments[int(g)].category_id for g in g_keys])
        cat_p = np.array([prev_cat[int(p)] for p in p_keys])
        ok = (cat_g[:, None] == cat_p[None, :]) & (inter > 0) & (score >= c.min_score)
        cand = np.argwhere(ok)
        if len(cand) == 0:
            return []
        s = score[cand[:, 0], cand[:, 1]]
        n = inter[cand[:, 0], cand[:, 1]]
        order = np.lexsort((cand[:, 1], cand[:, 0], -n, -s))
        used_g, used_p, out = set(), set(), []
        for r in order:
            a, b = int(cand[r, 0]), int(cand[r, 1])
            if a in used_g or b in used_p:
                continue
            used_g.add(a)
            used_p.add(b)
            out.append((int(g_keys[a]), int(p_keys[b]), float(s[r])))
        return out


def make_vps_head(config: WarpIoUConfig, context: Any = None) -> WarpIoUHead:
    return WarpIoUHead(config)
