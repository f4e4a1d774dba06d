"""The flow frontend's dynamic masks and their PV-SLAM eq. 4 weights, without learned weights.

Per edge: from its second observation on (after at least one BA round), the observed target against the
reprojection under the current estimate gives residual candidates (:func:`.dynamic.residual_candidates`), grouped
into coherent regions (:func:`.dynamic.group_regions`) and, with a segmenter, voted over the source keyframe's
movable thing segments (:func:`pvslam_core.slam.confidence.segment_vote`); re-estimated on ``DYNAMIC_UPDATES``
observations, then kept.  Per keyframe: a vote over its edges' masks (:func:`.dynamic.keyframe_vote`), used where an
edge has no mask of its own yet and for the tracking weights of the frames placed against that keyframe; a new
keyframe starts from its reference's mask moved along the tracked flow.  The tracking weights also take out the
reference keyframe's movable thing segments, judged or not (PV-SLAM's eq. 4 with a trusted segmenter): the BA's
edges release a parked car once the geometry says it is static, the tracking does not lean on it.  Every mask reaches
the weights through eq. 4 with the paper convention: static pixels keep their confidence, dynamic ones get about
``c e^-eta``.

:class:`DynamicMasking` owns the masks, keyed by the graph's stable keyframe ids like the frontend's edge cache.  It
keeps its own record of the cached edges (their targets and how often each was observed), told by the frontend
whenever an edge is computed or dropped, so that it walks them in the frontend's order.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from pvslam_core.slam.confidence import observed_flow_weight, segment_vote
from pvslam_core.slam.dynamic_config import DynamicMaskingConfig
from pvslam_core.types import PanopticSegmentation

from . import dynamic as D
from . import flow_ops as F

LOG = logging.getLogger("pvslam.frontend.flow")

DYNAMIC_UPDATES = 3  # an edge's mask is re-estimated on this many observations after its first, then kept
# the residual threshold is also at least this multiple of the edge's median residual (robust to an estimate that
# has not converged yet); 0 would use the absolute threshold alone (docs/decisions.md: DYNAMIC_REL_THRESH)
DYNAMIC_REL_THRESH = 2.0
# group the candidates into coherent regions: a moving vehicle is a region, isolated pixels are left to the BA's
# robust kernel
DYNAMIC_REGIONS = True
DYNAMIC_MIN_AREA = 4  # smallest region kept (BA px)
DYNAMIC_GROW = 1  # regions (and masks moved to a new keyframe) are dilated by this many BA px
DYNAMIC_TRACK = True  # the reference keyframe's mask also weighs the tracking flow that places a non-keyframe
# ... and so do its movable thing segments, judged or not: a vehicle that grows to fill the view drags the tracked
# pose, and masks judged against that pose then let it go (docs/decisions.md: TRACK_THINGS)
TRACK_THINGS = True
THINGS_ONLY = True  # only movable thing segments vote, each keyframe's own (ids are unique within a frame only)
# with a segmenter, also keep every raw candidate outside the voted segments (PVO's segm_filter); false: voted
# segments (over their judged pixels) or regions, the evidence of a run without one (docs/decisions.md:
# VOTE_KEEPS_CANDIDATES)
VOTE_KEEPS_CANDIDATES = True
MIN_JUDGED = 8  # an edge with fewer judgeable pixels keeps its previous mask


@dataclass
class _KeyframeMask:
    seg_ba: Optional[torch.Tensor] = None  # int64 [h, w] panoptic ids at the BA resolution (block centres)
    thing_ids: Optional[torch.Tensor] = None  # int64 [K] ids of its movable thing segments
    dyn: Optional[torch.Tensor] = None  # float32 [h, w] the keyframe's mask, 1 = moving
    dyn_judged: bool = False  # dyn comes from this keyframe's own edges (else: moved from its reference's)
    things: Optional[torch.Tensor] = None  # float32 [h, w] its movable thing segments (1), None without any


@dataclass
class _EdgeMask:
    target: torch.Tensor  # float32 [2, h, w] the edge's observed target (the frontend's cached tensor)
    dynamic: Optional[torch.Tensor] = None  # float32 [h, w] latest mask
    rounds: int = 0  # how many times the edge was observed


def segment_info(seg: Optional[PanopticSegmentation], h: int, w: int):
    """``(ids int64 [h, w], movable thing ids int64 [K])`` of a segmentation at the BA resolution, or Nones.  A
    segmentation that found nothing (no segments: all void) is no segmentation."""
    if seg is None or seg.ids is None or not seg.segments:
        return None, None
    ids = F.downsample_ids(seg.ids.to(torch.int64).cpu(), h, w)
    # only segments of categories that can move vote (Segment.movable: a segmenter's movable-class list)
    things = torch.tensor([s.id for s in seg.segments if s.isthing and s.movable], dtype=torch.int64)
    return ids, things


class DynamicMasking:
    """Per-edge and per-keyframe dynamic masks and their eq. 4 weights (module docstring).

    ``reproject(poses, disps, intrinsics, ii, jj) -> (coords [N, h, w, 2], valid [N, h, w], ...)``: the graph's
    reprojection (:func:`pvslam_core.geometry.projective.reproject`)."""

    def __init__(self, cfg: DynamicMaskingConfig, reproject: Callable):
        self.cfg = cfg
        self._reproject = reproject
        self._kfs: dict[int, _KeyframeMask] = {}  # stable keyframe id -> masks (insertion order = time order)
        self._edges: dict[tuple[int, int], _EdgeMask] = {}  # (source id, target id), in the frontend's cache order

    # ------------------------------------------------------------------------------- keyframes, edges --
    def add_keyframe(self, sid: int, seg: Optional[PanopticSegmentation], h: int, w: int,
                     ref_sid: Optional[int] = None, tracked: Optional[np.ndarray] = None) -> None:
        """Keyframe ``sid`` with its segmentation; ``tracked`` float32 ``[2, h, w]``: where its reference ``ref_sid``'s
        pixels went in it (the tracked flow's targets), along which it inherits the reference's mask."""
        seg_ba, things = segment_info(seg, h, w)
        kf = self._kfs[sid] = _KeyframeMask(seg_ba=seg_ba, thing_ids=things)
        if seg_ba is not None and things is not None and things.numel():
            mask = torch.isin(seg_ba, things)
            kf.things = mask.float() if bool(mask.any()) else None
        ref = self._kfs.get(ref_sid) if ref_sid is not None else None
        if ref is not None and tracked is not None:
            m = ref.dyn
            if m is not None and tuple(m.shape) == tuple(tracked.shape[-2:]) and bool((m > 0).any()):
                kf.dyn = D.warp_mask(m, torch.from_numpy(tracked), DYNAMIC_GROW)

    def keyframe(self, sid: int) -> Optional[_KeyframeMask]:
        """Keyframe ``sid``'s segment ids and masks (``seg_ba``, ``thing_ids``, ``dyn``, ``dyn_judged``), or None."""
        return self._kfs.get(sid)

    def remove_keyframe(self, sid: int) -> None:
        self._kfs.pop(sid, None)

    def edge_added(self, key: tuple[int, int], target: torch.Tensor) -> None:
        """The frontend cached (or replaced) edge ``key`` with ``target [2, h, w]``: a new edge, no mask yet."""
        self._edges[key] = _EdgeMask(target)

    def edge_dropped(self, key: tuple[int, int]) -> None:
        self._edges.pop(key, None)

    def edge_mask(self, key: tuple[int, int]) -> Optional[torch.Tensor]:
        """Edge ``key``'s latest mask ``[h, w]`` (None: not judged, or no mask)."""
        e = self._edges.get(key)
        return None if e is None else e.dynamic

    def nbytes(self) -> int:
        n = sum(kf.seg_ba.numel() * kf.seg_ba.element_size() for kf in self._kfs.values() if kf.seg_ba is not None)
        n += sum(kf.things.numel() * 4 for kf in self._kfs.values() if kf.things is not None)
        return n + sum(e.dynamic.numel() * 4 for e in self._edges.values() if e.dynamic is not None)

    # ------------------------------------------------------------------------------------------ weights --
    def observe(self, graph, ii: torch.Tensor, jj: torch.Tensor, keys: list[tuple[int, int]], target: torch.Tensor,
                conf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Masks ``dyn [E, h, w]`` and eq. 4 weights ``[E, h, w]`` of observed edges ``ii -> jj`` (graph indices;
        stable ids ``keys``; ``target [E, 2, h, w]`` and confidence ``conf [E, h, w]`` on the graph's device)."""
        h, w = (int(v) for v in graph.ba_shape)
        dev = conf.device
        entries = [self._edges[key] for key in keys]
        need = [e for e, en in enumerate(entries) if 1 <= en.rounds <= DYNAMIC_UPDATES]
        if need:
            self._update(graph, ii, jj, need, entries, target)
        zeros = torch.zeros(h, w)
        # an edge not judged yet (first observation) takes its source keyframe's mask
        kf_dyn = [self._kfs[k[0]].dyn for k in keys]
        dyn = torch.stack([en.dynamic if en.dynamic is not None else (kd if kd is not None else zeros)
                           for en, kd in zip(entries, kf_dyn)]).to(dev)
        c = self.cfg
        if c.convention == "paper":
            # eq. 4 only changes dynamic pixels; static ones keep exactly their confidence (no 0.99 cap)
            weight = conf.clone()
            m = dyn > 0
            if bool(m.any()):
                weight[m] = observed_flow_weight(conf[m], dyn[m], offset=c.panoptic_offset, convention="paper")
        else:
            weight = observed_flow_weight(conf, dyn, offset=c.panoptic_offset, convention=c.convention)
        for en in entries:
            en.rounds += 1
        return dyn, weight

    def track_weights(self, sid: int, weight: torch.Tensor, graph) -> None:
        """Apply keyframe ``sid``'s mask and its movable thing segments (``TRACK_THINGS``) through eq. 4 to the weights
        ``[2, h, w]`` (in place) of a frame tracked against it: the mapper's motion-only BA places the frame (and a
        new keyframe's first pose) from these.  ``graph``: the last one observed."""
        if not DYNAMIC_TRACK:
            return
        dyn = self._keyframe_dynamic(sid, graph)
        kf = self._kfs.get(sid)
        if TRACK_THINGS and kf is not None and kf.things is not None:
            dyn = kf.things if dyn is None else torch.maximum(dyn, kf.things)
        if dyn is not None and tuple(dyn.shape) == tuple(weight.shape[-2:]) and bool((dyn > 0).any()):
            m = dyn > 0
            weight[:, m] = observed_flow_weight(weight[:, m], dyn[m].expand(2, -1), offset=self.cfg.panoptic_offset,
                                                convention=self.cfg.convention)

    # ------------------------------------------------------------------------------------------- masks --
    def masks(self, graph, ii: torch.Tensor, jj: torch.Tensor, target: torch.Tensor):
        """Masks of edges ``ii -> jj`` (graph indices) from their observed ``target [N, 2, h, w]`` against the
        reprojection under the current estimate: ``(dyn bool [N, h, w], fraction [N], valid pixel count [N])``, or
        None when the reprojection fails."""
        dev = graph.disps.device
        try:
            coords, valid = self._reproject(graph.poses, graph.disps, graph.intrinsics, ii.to(dev), jj.to(dev))[:2]
        except Exception as exc:
            LOG.warning("reprojection for dynamic masking failed (%s); masks kept", exc)
            return None
        tgt = target.to(device=dev, dtype=coords.dtype)  # [N, 2, h, w]
        d = tgt - coords.permute(0, 3, 1, 2)
        res = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).sqrt()  # [N, h, w]
        h, w = res.shape[-2:]
        u, v = coords[..., 0], coords[..., 1]
        # only pixels that stay in view can be judged (the others have no flow to compare)
        valid = valid & torch.isfinite(res) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        # an edge whose two keyframes have the same pose has no motion estimate to judge against (a fragment before
        # its initialisation: every keyframe sits at the fragment's start); there the "residual" is the whole flow,
        # and masks judged on it would mark the entire view dynamic and keep a turning camera from initialising
        P = graph.poses.to(dev)
        same = (P[ii.to(dev)] == P[jj.to(dev)]).all(-1)
        valid = valid & ~same[:, None, None]
        dyn = D.residual_candidates(res, valid, self.cfg.thresh, DYNAMIC_REL_THRESH)
        regions = D.group_regions(dyn, DYNAMIC_MIN_AREA, DYNAMIC_GROW) if DYNAMIC_REGIONS else None
        srcs = [self._kfs[int(graph.ids[int(i)])] for i in ii.tolist()]
        if any(s_.seg_ba is not None for s_ in srcs):
            dyn = self._vote(dyn, regions, valid, srcs, h, w)
        elif regions is not None:
            dyn = regions.to(dyn.device)
        return dyn, dyn.float().mean(dim=(1, 2)).tolist(), valid.sum(dim=(1, 2)).tolist()

    def _vote(self, dyn: torch.Tensor, regions: Optional[torch.Tensor], valid: torch.Tensor, srcs: list,
              h: int, w: int) -> torch.Tensor:
        """Candidates ``dyn bool [N, h, w]`` with the segment vote of each edge's source keyframe ``srcs[n]``."""
        zero = torch.zeros(h, w, dtype=torch.int64)
        seg = torch.stack([s_.seg_ba if s_.seg_ba is not None else zero for s_ in srcs]).to(dyn.device)
        # each source votes with its own movable ids (ids are unique only within one frame: segment_vote)
        things = [s_.thing_ids for s_ in srcs] if THINGS_ONLY else None
        vote = self.cfg.vote_thresh
        if regions is not None and not VOTE_KEEPS_CANDIDATES:
            # the segment-free evidence plus the vote: a movable thing segment is dynamic when the geometry inside it
            # says it moves (more than vote_thresh of its judged pixels are candidates), elsewhere the regions
            return segment_vote(dyn, seg, thresh=vote, batch_things=things, valid=valid,
                                keep_pixels=False) | regions.to(dyn.device)
        out = segment_vote(dyn, seg, thresh=vote, batch_things=things)
        return out if regions is None else out | regions.to(out.device)  # a voted segment or a coherent region

    def _update(self, graph, ii, jj, need: list[int], entries: list[_EdgeMask], target: torch.Tensor) -> None:
        """Residual of observed targets against the current reprojection -> masks of edges ``need`` (positions in
        ``ii`` / ``jj`` / ``entries`` / ``target``); their source keyframes vote again."""
        idx = torch.tensor(need, dtype=torch.int64)
        out = self.masks(graph, ii[idx], jj[idx], target[idx.to(target.device)])
        if out is None:
            return
        dyn, frac, nvalid = out
        dyn_f = dyn.float().cpu()
        ids = graph.ids
        touched = set()
        for n, e in enumerate(need):
            en = entries[e]
            if nvalid[n] < MIN_JUDGED:
                continue  # nothing to judge with: keep the previous mask
            # too much "dynamic": the estimate, not the scene, is off -> no mask on this edge
            en.dynamic = None if frac[n] > self.cfg.max_fraction else dyn_f[n]
            touched.add(int(ids[int(ii[e])]))
        for sid in touched:  # the keyframe's own mask follows its edges' newest masks
            masks = [en.dynamic for (a, _), en in self._edges.items() if a == sid and en.dynamic is not None]
            kf = self._kfs.get(sid)
            if kf is not None and masks:
                kf.dyn, kf.dyn_judged = D.keyframe_vote(masks), True

    def _keyframe_dynamic(self, sid: int, graph) -> Optional[torch.Tensor]:
        """The mask ``[h, w]`` of keyframe ``sid`` for tracking against it: judged from its edges that the BA has used
        (once, the first time it is asked for after that), else the mask moved from its reference."""
        kf = self._kfs.get(sid)
        if kf is None or kf.dyn_judged:
            return None if kf is None else kf.dyn
        if graph is None or not graph.has_id(sid):
            return kf.dyn
        keys = [key for key, en in self._edges.items() if key[0] == sid and en.rounds >= 1 and graph.has_id(key[1])]
        if not keys:
            return kf.dyn
        ii = torch.tensor([graph.index_of(a) for a, _ in keys], dtype=torch.int64)
        jj = torch.tensor([graph.index_of(b) for _, b in keys], dtype=torch.int64)
        out = self.masks(graph, ii, jj, torch.stack([self._edges[key].target for key in keys]))
        if out is None:
            return kf.dyn
        dyn, frac, nvalid = out
        masks = [dyn[n].float().cpu() for n in range(len(keys))
                 if nvalid[n] >= MIN_JUDGED and frac[n] <= self.cfg.max_fraction]
        kf.dyn_judged = True
        if masks:
            kf.dyn = D.keyframe_vote(masks)
        return kf.dyn
