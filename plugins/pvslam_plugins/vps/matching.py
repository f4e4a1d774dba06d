"""Instance matching shared by the VPS heads (``warp_iou``, ``fusion``): the id layout, warping the previous
frame's tracked ids into the current frame, greedy same-category overlap matching (PVO's tools/1_tracking.py),
a short memory of lost tracks (a car hidden behind a bus for a few frames gets its id back), and the relabelling
of a segmentation with the resulting ids.

Id layout: stuff = ``category_id * ID_STRIDE``; the c-th new instance of a thing category (c = 1, 2, ...) gets
``category_id * ID_STRIDE + c % ID_STRIDE + (c // ID_STRIDE) * ID_OVERFLOW`` (= ``category_id * 1000 + c`` while
c < 1000; later instances stay unique without colliding with another category's ids).  Ids are never reused
within a run (:class:`IdAllocator`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional

import cv2
import numpy as np
import torch

from pvslam_core.id_lookup import lut, unique_ids  # noqa: F401 - part of this module's API (__all__)
from pvslam_core.interfaces import MotionCue, VPSState
from pvslam_core.types import PanopticSegmentation, Segment

ID_STRIDE = 1000
ID_OVERFLOW = 10_000_000
#: id for stuff of a category id <= 0 (cannot be written as category_id * 1000, which would be void)
STUFF_ID_NONPOSITIVE = 9_999_000

__all__ = ["ID_STRIDE", "ID_OVERFLOW", "STUFF_ID_NONPOSITIVE", "compose_id", "decompose_id", "stuff_id", "lut",
           "unique_ids", "subsample", "IdAllocator", "match_segments", "warp_previous_ids",
           "relabel", "WarpOptions", "TrackMemory", "segment_velocities"]


def compose_id(category_id: int, counter: int) -> int:
    return category_id * ID_STRIDE + counter % ID_STRIDE + (counter // ID_STRIDE) * ID_OVERFLOW


def decompose_id(sid: int) -> tuple[int, int]:
    """Inverse of :func:`compose_id`: ``(category_id, counter)``."""
    hi, rem = divmod(int(sid), ID_OVERFLOW)
    return rem // ID_STRIDE, hi * ID_STRIDE + rem % ID_STRIDE


def stuff_id(category_id: int) -> int:
    return category_id * ID_STRIDE if category_id > 0 else STUFF_ID_NONPOSITIVE


def subsample(ids: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest (pixel-centre) resampling of an id map ``[H, W]`` to ``[h, w]`` (exact for any ids)."""
    H, W = ids.shape
    if (H, W) == (h, w):
        return ids
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    return ids[rows[:, None], cols[None, :]]


class IdAllocator:
    """Per-category counters that only grow, so an id that disappeared is never handed out again."""

    def __init__(self) -> None:
        self.counters: dict[int, int] = {}

    def reset(self) -> None:
        self.counters.clear()

    def new_id(self, category_id: int) -> int:
        c = self.counters.get(category_id, 0) + 1
        self.counters[category_id] = c
        return compose_id(category_id, c)

    def reserve(self, segments: list[Segment]) -> None:
        """Advance the counters past ids seen in a previous state."""
        for s in segments:
            if s.isthing:
                cat, c = decompose_id(s.id)
                if cat == s.category_id and c > self.counters.get(cat, 0):
                    self.counters[cat] = c


def match_segments(
    ids: np.ndarray,
    warped: np.ndarray,
    cur_things: list[int],
    cur_cat: dict[int, int],
    prev_cat: dict[int, int],
    score: Literal["overlap", "iou"] = "overlap",
    min_score: float = 0.0,
) -> list[tuple[int, int, float]]:
    """Greedy one-to-one same-category assignment of current thing segments ``g`` (ids in ``ids``) to warped
    previous segments ``p`` (ids in ``warped``, same shape), best score first, above ``min_score``.

    score: 'overlap' = |g & p| / |p| (PVO), 'iou' = |g & p| / |g | p|.  Ties: larger intersection, then lower ids.
    Returns ``(g, p, score)`` triples."""
    prev_ids = sorted(set(unique_ids(warped).tolist()) & set(prev_cat))
    if not prev_ids or not cur_things:
        return []
    g_keys = np.array(cur_things, dtype=np.int64)
    p_keys = np.array(prev_ids, dtype=np.int64)
    gi = lut(g_keys, np.arange(len(g_keys), dtype=np.int64), ids.reshape(-1), -1)
    pi = lut(p_keys, np.arange(len(p_keys), dtype=np.int64), warped.reshape(-1), -1)
    G, P = len(g_keys), len(p_keys)
    area_g = np.bincount(gi[gi >= 0], minlength=G)
    area_p = np.bincount(pi[pi >= 0], minlength=P)
    both = (gi >= 0) & (pi >= 0)
    inter = np.bincount(gi[both] * P + pi[both], minlength=G * P).reshape(G, P)
    if score == "iou":
        union = area_g[:, None] + area_p[None, :] - inter
        sc = inter / np.maximum(union, 1)
    else:
        sc = inter / np.maximum(area_p[None, :], 1)
    return _greedy(g_keys, p_keys, sc, inter, cur_cat, prev_cat, min_score)


def _greedy(g_keys, p_keys, sc, inter, cur_cat, prev_cat, min_score) -> list[tuple[int, int, float]]:
    cat_g = np.array([cur_cat[int(g)] for g in g_keys])
    cat_p = np.array([prev_cat[int(p)] for p in p_keys])
    ok = (cat_g[:, None] == cat_p[None, :]) & (inter > 0) & (sc >= min_score)
    cand = np.argwhere(ok)
    if len(cand) == 0:
        return []
    s = sc[cand[:, 0], cand[:, 1]]
    n = inter[cand[:, 0], cand[:, 1]]
    order = np.lexsort((cand[:, 1], cand[:, 0], -n, -s))
    used_g, used_p, out = set(), set(), []
    for r in order:  # at most (#current things x #previous things) candidates: a few dozen
        a, b = int(cand[r, 0]), int(cand[r, 1])
        if a in used_g or b in used_p:
            continue
        used_g.add(a)
        used_p.add(b)
        out.append((int(g_keys[a]), int(p_keys[b]), float(s[r])))
    return out


# ------------------------------------------------------------------------------------------------------------
# warping the previous ids
# ------------------------------------------------------------------------------------------------------------
#: OpenCV DIS preset of the flow between the two images when the motion cue carries none: the cheapest, and no
#: fewer id switches with the slower ones (docs/decisions.md: vps.flow_preset)
FLOW_PRESET = "ultrafast"
#: that DIS flow is computed on images reduced to at most this many pixels on the longer side
FLOW_MAX_SIDE = 320
#: stuff follows the rigid flow of depth + camera poses when the cue has them (things always follow the flow)
RIGID_STUFF = True
#: forward-warp splatting: all four neighbours of the target pixel (fewer holes than the rounded pixel alone)
SPLAT = "bilinear"


@dataclass
class WarpOptions:
    flow_preset: str = FLOW_PRESET
    flow_max_side: int = FLOW_MAX_SIDE
    rigid_stuff: bool = RIGID_STUFF
    splat: str = SPLAT


def resized_intrinsics(k: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """fx fy cx cy of an image scaled by ``(sx, sy)`` (pixel-centre convention)."""
    k = np.asarray(k, np.float64)[:4].copy()
    k[0] *= sx
    k[1] *= sy
    k[2] = (k[2] + 0.5) * sx - 0.5
    k[3] = (k[3] + 0.5) * sy - 0.5
    return k


def previous_flow(prev: VPSState, image: torch.Tensor, cue: MotionCue, h: int, w: int,
                  opts: WarpOptions) -> np.ndarray:
    """float32 ``[2, h, w]``: the flow from the previous frame to the current one at ``(h, w)`` (VO flow from the
    cue; OpenCV DIS between the two images when the cue has none; zero without either)."""
    from .warp_iou.warp import dis_flow, resize_flow

    if cue.flow is not None:
        return resize_flow(cue.flow.detach().cpu().numpy().astype(np.float32), h, w)
    if prev.image is not None:
        return resize_flow(dis_flow(prev.image, image, opts.flow_preset, opts.flow_max_side), h, w)
    return np.zeros((2, h, w), np.float32)


def warp_previous_ids(prev: VPSState, image: torch.Tensor, cue: MotionCue, h: int, w: int,
                      opts: WarpOptions, flow: Optional[np.ndarray] = None) -> np.ndarray:
    """The previous frame's tracked ids forward-warped into the current frame, int64 ``[h, w]``.

    Things follow the flow; with depth, both poses and intrinsics in the cue (and ``rigid_stuff``) stuff follows
    the rigid flow of the camera motion instead, and writes are z-ordered by depth (near wins).  Without depth only
    things are warped (no z-order to let stuff hide them)."""
    from .warp_iou.warp import forward_warp, rigid_flow

    pids = subsample(prev.panoptic.ids.detach().cpu().numpy().astype(np.int64), h, w)
    if flow is None:
        flow = previous_flow(prev, image, cue, h, w, opts)
    prev_thing = np.array(sorted(s.id for s in prev.panoptic.segments if s.isthing), dtype=np.int64)
    is_thing = np.isin(pids, prev_thing)
    depth = None
    mask = is_thing
    if cue.depth_prev is not None:
        depth = cue.depth_prev.detach().cpu().numpy().astype(np.float32)
        sx, sy = w / depth.shape[1], h / depth.shape[0]
        if depth.shape != (h, w):
            depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
        if opts.rigid_stuff and cue.pose_prev is not None and cue.pose_cur is not None and cue.intrinsics is not None:
            k = resized_intrinsics(cue.intrinsics.detach().cpu().double().numpy(), sx, sy)
            rflow, _, valid = rigid_flow(depth, cue.pose_prev.detach().cpu().double().numpy(),
                                         cue.pose_cur.detach().cpu().double().numpy(), k)
            use = valid & ~is_thing & (pids != 0)
            flow = np.where(use[None], rflow, flow)
        mask = None  # depth orders the writes, so occluding stuff may hide things
    return forward_warp(pids, flow, depth, mask, splat=opts.splat)


# ------------------------------------------------------------------------------------------------------------
# track memory (re-identification after an occlusion)
# ------------------------------------------------------------------------------------------------------------
@dataclass
class _Track:
    category_id: int
    max_area: float  # reference area (px): the largest seen, decaying per frame
    ys: np.ndarray  # int64 [n]: the template, the track's pixels in frame ``template_frame``
    xs: np.ndarray
    template_frame: int
    velocity: tuple[float, float]  # px per frame (x, y): the mean flow of its pixels, last time it was measured
    last_seen: int  # frame index


def segment_velocities(prev_ids: np.ndarray, flow: np.ndarray, keys: list[int]) -> dict[int, tuple[float, float]]:
    """Mean flow ``[2, H, W]`` over the pixels of each id in ``keys`` of ``prev_ids [H, W]`` (absent ids left out)."""
    if not keys:
        return {}
    k = np.array(sorted(keys), dtype=np.int64)
    idx = lut(k, np.arange(len(k), dtype=np.int64), prev_ids.reshape(-1), -1)
    ok = idx >= 0
    n = np.bincount(idx[ok], minlength=len(k))
    vx = np.bincount(idx[ok], weights=flow[0].reshape(-1)[ok], minlength=len(k))
    vy = np.bincount(idx[ok], weights=flow[1].reshape(-1)[ok], minlength=len(k))
    return {int(k[i]): (float(vx[i] / n[i]), float(vy[i] / n[i])) for i in range(len(k)) if n[i] > 0}


class TrackMemory:
    """Thing tracks remembered while absent for up to ``max_age`` frames, to give a reappearing instance
    its id back (a car that drove on behind a bus).

    Each track keeps a *template*: its pixels the last time it was seen at least ``full_fraction`` of its reference
    area (the largest area seen, decaying by ``area_decay`` per frame so that a car driving away, which shrinks,
    keeps refreshing it): a car that is being covered leaves its whole shape, not the last sliver.  And its image
    velocity (the mean VO flow over its pixels, frozen once it is hidden: the flow at hidden pixels is the
    occluder's).
    A lost track is predicted at ``template + velocity * (frames since the template)``.  A current thing segment
    that the regular matching left unmatched takes the id of the same-category lost track whose prediction
    covers it best, ``|g & pred| / |g| >= min_score`` (a reappearing car shows a sliver first: the fraction of the
    *current* segment inside the prediction is what stays high)."""

    def __init__(self, max_age: int = 10, min_score: float = 0.5, full_fraction: float = 0.9,
                 area_decay: float = 0.9) -> None:
        self.max_age = max_age
        self.area_decay = area_decay
        self.min_score = min_score
        self.full_fraction = full_fraction
        self.tracks: dict[int, _Track] = {}

    def reset(self) -> None:
        self.tracks.clear()

    def set_velocities(self, velocities: dict[int, tuple[float, float]]) -> None:
        for tid, v in velocities.items():
            t = self.tracks.get(tid)
            if t is not None:
                t.velocity = v

    def observe(self, ids: np.ndarray, things: dict[int, int], frame_index: int) -> None:
        """Record the output ids ``[H, W]`` of frame ``frame_index``; ``things`` = ``{thing id: category}``."""
        if things:
            keys = np.array(sorted(things), dtype=np.int64)
            flat = ids.reshape(-1)
            idx = lut(keys, np.arange(len(keys), dtype=np.int64), flat, -1)
            pix = np.nonzero(idx >= 0)[0]
            owner = idx[pix]
            order = np.argsort(owner, kind="stable")
            pix, owner = pix[order], owner[order]
            bounds = np.searchsorted(owner, np.arange(len(keys) + 1))
            w = ids.shape[1]
            for k, tid in enumerate(keys.tolist()):
                sel = pix[bounds[k]:bounds[k + 1]]
                if len(sel) == 0:
                    continue
                t = self.tracks.get(tid)
                if t is None:
                    t = self.tracks[tid] = _Track(int(things[tid]), 0, sel[:0], sel[:0], frame_index, (0.0, 0.0),
                                                  frame_index)
                t.last_seen = frame_index
                if len(sel) >= self.full_fraction * t.max_area:
                    t.ys, t.xs = np.divmod(sel, w)
                    t.template_frame = frame_index
                t.max_area = max(len(sel), self.area_decay * t.max_area)
        # absent for at most max_age frames: still matchable in frame last_seen + max_age + 1
        self.tracks = {k: t for k, t in self.tracks.items() if frame_index - t.last_seen <= self.max_age}

    def match(self, ids: np.ndarray, candidates: list[int], cur_cat: dict[int, int], taken: set[int],
              frame_index: int) -> list[tuple[int, int, float]]:
        """Greedy same-category assignment of unmatched current things ``candidates`` (ids in ``ids``) to
        remembered tracks not in ``taken`` (ids already given out in this frame)."""
        live = sorted(k for k, t in self.tracks.items()
                      if k not in taken and 0 < frame_index - t.last_seen <= self.max_age + 1)
        if not live or not candidates:
            return []
        h, w = ids.shape
        t_keys = np.array(live, dtype=np.int64)
        g_keys = np.array(sorted(candidates), dtype=np.int64)
        pix, owner = [], []
        for k, tid in enumerate(live):
            t = self.tracks[tid]
            age = frame_index - t.template_frame
            px = np.rint(t.xs + t.velocity[0] * age).astype(np.int64)
            py = np.rint(t.ys + t.velocity[1] * age).astype(np.int64)
            inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
            pix.append(py[inside] * w + px[inside])
            owner.append(np.full(int(inside.sum()), k, dtype=np.int64))
        pix, owner = np.concatenate(pix), np.concatenate(owner)
        T, G = len(t_keys), len(g_keys)
        gflat = lut(g_keys, np.arange(G, dtype=np.int64), ids.reshape(-1), -1)
        area_g = np.bincount(gflat[gflat >= 0], minlength=G)
        # a pixel may lie in several predictions: count each (segment, track) pair once per pixel
        gi = gflat[pix]
        hit = gi >= 0
        inter = np.bincount(gi[hit] * T + owner[hit], minlength=G * T).reshape(G, T)
        sc = inter / np.maximum(area_g[:, None], 1)
        prev_cat = {int(k): self.tracks[int(k)].category_id for k in t_keys}
        return _greedy(g_keys, t_keys, sc, inter, cur_cat, prev_cat, self.min_score)


def relabel(seg: PanopticSegmentation, ids: np.ndarray, cur_segments: dict[int, Segment], cur_things: list[int],
            present: set[int], assign: dict[int, int], alloc: IdAllocator) -> PanopticSegmentation:
    """``seg`` with its thing segments renamed by ``assign`` (current id -> output id; unassigned things get new ids
    in ascending segment-id order) and stuff as ``stuff_id(category)``; pixels without a segment become void."""
    out_segments: dict[int, Segment] = {}
    assign = dict(assign)
    for sid in cur_things:  # ascending segment id: deterministic new ids
        s = cur_segments[sid]
        oid = assign.get(sid)
        if oid is None:
            oid = alloc.new_id(s.category_id)
            assign[sid] = oid
        out_segments[oid] = Segment(oid, s.category_id, True, s.score, movable=s.movable)
    for sid in sorted(present):
        s = cur_segments.get(sid)
        if s is None or s.isthing:
            continue
        oid = stuff_id(s.category_id)
        assign[sid] = oid
        old = out_segments.get(oid)
        score = s.score if old is None else max(old.score, s.score)
        out_segments[oid] = Segment(oid, s.category_id, False, score)
    h, w = ids.shape
    keys = np.array(list(assign.keys()), dtype=np.int64)
    vals = np.array(list(assign.values()), dtype=np.int64)
    out_ids = lut(keys, vals, ids.reshape(-1), 0).reshape(h, w)
    return PanopticSegmentation(ids=torch.from_numpy(np.ascontiguousarray(out_ids, dtype=np.int64)),
                                segments=[out_segments[k] for k in sorted(out_segments)], features=seg.features)
