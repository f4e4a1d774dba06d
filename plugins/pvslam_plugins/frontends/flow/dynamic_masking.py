"""The flow frontend's dynamic masks (PV-SLAM eq. 4 without learned weights): per edge, the observed target
against the reprojection under the current estimate, as residual candidates grouped into coherent regions
(:mod:`.dynamic`) and/or voted over the keyframe's thing segments; per keyframe, a vote over its edges' masks.
With ``epipolar_cue``, each keyframe also keeps the map-independent epipolar cue (:mod:`.epipolar_cue`) of its
tracked flow and of its first edges, OR-ed into every judgement of its edges (:meth:`DynamicMasking._cue_mask`,
:meth:`~DynamicMasking._epipolar_cue`, :meth:`~DynamicMasking._edge_cues`).

A mixin of :class:`.frontend.FlowFrontend`: it reads the frontend's ``cfg``, ``_kfs`` (keyframe state by stable
id), ``_edges`` (edge state by ``(src_id, dst_id)``), ``_graph`` and ``_reproject``.
"""
from __future__ import annotations

import logging
import time
from typing import Optional

import torch

from pvslam_core.slam.confidence import segment_vote

from . import dynamic as D
from . import epipolar_cue as E

LOG = logging.getLogger("pvslam.frontend.flow")


class DynamicMasking:
    def _dynamic_masks(self, graph, ii: torch.Tensor, jj: torch.Tensor, target: torch.Tensor):
        """Masks of edges ``ii -> jj`` (graph indices) from their observed ``target [N, 2, h, w]`` against the
        reprojection under the current estimate (:mod:`.dynamic`): ``(dyn bool [N, h, w], fraction [N], valid
        pixel count [N])``, or None when the reprojection is not available."""
        try:
            reproject = self._reproject()
        except ImportError:
            return None
        dev = graph.disps.device
        try:
            coords, valid = reproject(graph.poses, graph.disps, graph.intrinsics, ii.to(dev), jj.to(dev))[:2]
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
        # an edge whose two keyframes have the same pose has no motion estimate to judge against (a fragment
        # before its initialisation: every keyframe sits at the fragment's start); there the "residual" is the
        # whole flow, and masks judged on it marked the entire view dynamic and kept a hand-held room from ever
        # initialising (every pair "0 confident correspondences")
        P = graph.poses.to(dev)
        same = (P[ii.to(dev)] == P[jj.to(dev)]).all(-1)
        valid = valid & ~same[:, None, None]
        dyn = D.residual_candidates(res, valid, self.cfg.dynamic_thresh, self.cfg.dynamic_rel_thresh)
        if self.cfg.depth_check > 0:
            # the second geometric cue: depths that disagree across the two keyframes (dynamic.py)
            from pvslam_core.geometry.projective import edge_transforms

            R, t = edge_transforms(P, ii.to(dev), jj.to(dev))
            dd = graph.disps.to(dev)
            dyn = dyn | D.depth_candidates(R, t, dd[ii.to(dev)], dd[jj.to(dev)], coords, valid,
                                           graph.intrinsics, self.cfg.depth_check)
        regions = D.group_regions(dyn, self.cfg.dynamic_min_area, self.cfg.dynamic_grow) \
            if self.cfg.dynamic_regions else None
        ids = graph.ids
        srcs = [self._kfs[int(ids[int(i)])] for i in ii.tolist()]
        if any(s_.seg_ba is not None for s_ in srcs):
            zero = torch.zeros(h, w, dtype=torch.int64)
            seg = torch.stack([s_.seg_ba if s_.seg_ba is not None else zero for s_ in srcs]).to(dev)
            # each source votes with its own movable ids (ids are unique only within one frame: segment_vote)
            things = [s_.thing_ids for s_ in srcs] if self.cfg.things_only else None
            if regions is not None and not self.cfg.vote_keeps_candidates:
                # the segment-free evidence plus the vote: a movable thing segment is dynamic when the geometry
                # inside it says it moves (more than vote_thresh of its judged pixels are candidates), elsewhere
                # the coherent regions, exactly as without a segmenter.  Not the default: on the moving-vehicles
                # tune seeds it did worse than also keeping the raw candidates (config.py, vote_keeps_candidates)
                dyn = segment_vote(dyn, seg, thresh=self.cfg.vote_thresh, batch_things=things, valid=valid,
                                   keep_pixels=False) | regions.to(dyn.device)
            else:
                dyn = segment_vote(dyn, seg, thresh=self.cfg.vote_thresh, batch_things=things)
                if regions is not None:  # both cues: a segment that voted or a coherent region
                    dyn = dyn | regions.to(dyn.device)
        elif self.cfg.epipolar_cue and self.cfg.epipolar_replaces_residual:
            # without a segmenter the epipolar cue (OR-ed below) judges alone: the residual test against the current
            # estimate flags the static scene as often as the movers once a mover has dragged that estimate
            dyn = torch.zeros_like(dyn)
        elif regions is not None:
            dyn = regions.to(dyn.device)
        if self.cfg.dynamic_persist:
            dyn = dyn | self._persisted(srcs, h, w).to(dyn.device)
        if self.cfg.epipolar_cue:  # the map-independent cue of the source keyframe (epipolar_cue.py)
            dyn = dyn | self._persisted(srcs, h, w, "cue").to(dyn.device)
        return dyn, dyn.float().mean(dim=(1, 2)).tolist(), valid.sum(dim=(1, 2)).tolist()

    @staticmethod
    def _persisted(srcs: list, h: int, w: int, attr: str = "dyn_prior") -> torch.Tensor:
        """bool ``[N, h, w]``: a mask each source keyframe keeps for its whole life: ``dyn_prior``, the one it
        inherited from its reference (moved along the tracked flow when it was added; ``dynamic_persist``: a vehicle
        seen moving once stays masked while it is tracked, also on the edges where it happens to be
        epipolar-consistent), or ``cue``, the epipolar cue's (``epipolar_cue``, :meth:`_epipolar_cue`)."""
        out = torch.zeros(len(srcs), h, w, dtype=torch.bool)
        for n, kf in enumerate(srcs):
            m = getattr(kf, attr, None)
            if m is not None and tuple(m.shape) == (h, w):
                out[n] = m
        return out

    def _cue_mask(self, target, weight, frame) -> tuple[Optional[torch.Tensor], Optional[tuple]]:
        """The epipolar cue (:mod:`.epipolar_cue`) of one tracked flow out of the last keyframe: ``(mask, motion)``,
        the mask bool ``[h, w]`` in the keyframe's pixels (None: no judgement possible) and the fitted relative motion
        (None: no fit).  ``target [2, h, w]`` / ``weight [h, w]``: the positions in ``frame`` of the keyframe's
        pixels and their confidence (BA px; numpy or torch)."""
        t0 = time.thread_time()
        c = self.cfg
        target, weight = torch.as_tensor(target), torch.as_tensor(weight)
        h, w = weight.shape[-2:]
        k = frame.intrinsics.scaled(w / frame.width, h / frame.height)  # the BA resolution's intrinsics
        intr = (k.fx, k.fy, k.cx, k.cy)
        # the sign of the translation follows the previous fit (the direction of travel does not flip between two
        # keyframes); not the map's estimate, which is what a mover drags (epipolar_cue.fit_motion)
        motion = E.fit_motion(target, weight, intr, min_conf=c.epipolar_min_conf, ransac_px=c.epipolar_ransac_px,
                              prior=self._cue_t)
        mask = None
        if motion is not None:
            self._cue_t = motion[1]
            mask = self._judged_regions(target, weight, intr, motion)
        self.stats["epipolar_cue_s"] = self.stats.get("epipolar_cue_s", 0.0) + time.thread_time() - t0
        self.stats["epipolar_cue_calls"] = self.stats.get("epipolar_cue_calls", 0) + 1
        return mask, (None if motion is None else (motion, intr))

    def _edge_cues(self, graph, keys: list) -> None:
        """The epipolar cue on the newest keyframe's freshly computed edges to its ``epipolar_edges`` nearest older
        keyframes (``keys``: the ``(source id, target id)`` pairs just computed): each pair's flow is fitted on its
        own and judged in both directions, the masks OR-ed into both keyframes' ``cue`` and ``dyn``.  Longer
        baselines than the tracked flow (often one frame, when the tracking reference was a provisional keyframe
        removed as redundant) show more of a mover's motion across its epipolar line."""
        c = self.cfg
        if c.epipolar_edges <= 0 or not keys or not self._cue_on(self._last_id()):
            return
        t0 = time.thread_time()
        new = self._last_id()
        other = {b for a, b in keys if a == new} | {a for a, b in keys if b == new}
        older = sorted((b for b in other if b in self._kfs and (b, new) in self._edges and (new, b) in self._edges),
                       key=lambda b: -self._kfs[b].frame_index)[: c.epipolar_edges]
        intr = tuple(float(v) for v in graph.intrinsics.reshape(-1)[:4])
        prior = self._cue_t
        for b in older:
            fwd, bwd = self._edges[(new, b)], self._edges[(b, new)]
            # the edge runs new -> older: against the direction of travel of the tracked pair (_cue_mask)
            motion = E.fit_motion(fwd.target, fwd.conf, intr, min_conf=c.epipolar_min_conf,
                                  ransac_px=c.epipolar_ransac_px, prior=None if prior is None else -prior)
            if motion is None:
                continue
            for key, en, mot in ((new, fwd, motion), (b, bwd, E.invert(motion))):
                self._keep_cue(self._kfs[key], self._judged_regions(en.target, en.conf, intr, mot))
        self.stats["epipolar_cue_s"] = self.stats.get("epipolar_cue_s", 0.0) + time.thread_time() - t0

    def _judged_regions(self, target, conf, intr, motion) -> Optional[torch.Tensor]:
        """The epipolar cue's mask bool ``[h, w]`` of one flow ``target [2, h, w]`` (confidence ``conf [h, w]``)
        under ``motion`` (:func:`.epipolar_cue.judge`, grouped by :func:`.epipolar_cue.regions` with the residual
        cue's region settings); None when the pair cannot be judged."""
        c = self.cfg
        cand = E.judge(target, conf, intr, motion, min_conf=c.epipolar_min_conf, inlier_px=c.epipolar_ransac_px,
                       thresh=c.epipolar_thresh, rel=c.epipolar_rel, back=c.epipolar_back,
                       min_parallax=c.epipolar_min_parallax)
        return E.regions(cand, min_area=c.dynamic_min_area, grow=c.dynamic_grow, max_fraction=c.max_dynamic_fraction)

    @staticmethod
    def _keep_cue(kf, m: Optional[torch.Tensor]) -> None:
        """OR a cue mask ``m`` bool ``[h, w]`` into keyframe ``kf``'s lifelong ``cue`` and its ``dyn`` (nothing for no
        keyframe, no mask or an empty one)."""
        if kf is None or m is None or not bool(m.any()):
            return
        kf.cue = m if kf.cue is None else (kf.cue | m)
        kf.dyn = m.float() if kf.dyn is None else torch.maximum(kf.dyn, m.float())

    def _cue_on(self, sid: int) -> bool:
        """Whether keyframe ``sid`` gets the epipolar cue (the one gate of every cue call: the keyframe's, its edges',
        tracking's): with ``dynamic_masking`` and ``epipolar_cue``, always without a segmenter; with one (its
        segments at the BA resolution) only with ``epipolar_with_segmenter``."""
        c = self.cfg
        kf = self._kfs.get(sid)
        return (c.dynamic_masking and c.epipolar_cue and kf is not None
                and (c.epipolar_with_segmenter or kf.seg_ba is None))

    def _keyframe_cue(self, pend: dict, sid: int, frame) -> None:
        """The epipolar cue of a new keyframe ``sid`` from its tracked flow (``pend``: the frontend's pending track:
        ``fwd`` = (target, weight) out of the reference ``last_sid``, and ``cue`` when tracking judged it already)."""
        if not self._cue_on(sid):
            return
        cue = pend["cue"] if "cue" in pend else self._cue_mask(*pend["fwd"], frame)
        self._epipolar_cue(pend["last_sid"], sid, *cue, pend["fwd"][0])

    def _epipolar_cue(self, ref_sid: int, sid: int, mask: Optional[torch.Tensor], fit: Optional[tuple],
                      target) -> None:
        """Keep the epipolar cue of the tracked flow ``target [2, h, w]`` from the tracking reference ``ref_sid`` to
        the new keyframe ``sid`` (:meth:`_cue_mask`: ``mask`` in ``ref_sid``'s pixels, ``fit`` = (motion, BA
        intrinsics)) on both keyframes: ``sid`` judges its own pixels, the flow of its edge back to ``ref_sid`` under
        the same (inverted) motion, or without that edge (the reference was a provisional keyframe, removed as
        redundant just before ``sid`` came: about every other keyframe) takes ``mask`` moved along the flow.  Each
        ORs its mask into its ``cue`` (kept for its life, OR-ed into every judgement of its edges) and its ``dyn``
        (first observations and tracking).  The map is not consulted: the mask is right when a vehicle first
        appears, before it can drag the estimate."""
        c = self.cfg
        back = self._edges.get((sid, ref_sid))
        if fit is not None and back is not None:
            m_new = self._judged_regions(back.target, back.conf, fit[1], E.invert(fit[0]))
        else:
            m_new = None if mask is None else D.warp_mask(mask.float(), torch.as_tensor(target), c.dynamic_grow) > 0.5
        for key, m in ((ref_sid, mask), (sid, m_new)):
            self._keep_cue(self._kfs.get(key), m)

    def _update_dynamic(self, graph, ii, jj, need: list[int], entries: list, target: torch.Tensor) -> None:
        """Residual of observed targets against the current reprojection -> dynamic masks for edges ``need``."""
        idx = torch.tensor(need, dtype=torch.int64)
        out = self._dynamic_masks(graph, ii[idx], jj[idx], target[idx.to(target.device)])
        if out is None:
            return
        dyn, frac, nvalid = out
        dyn_f = dyn.float().cpu()
        ids = graph.ids
        touched = set()
        for n, e in enumerate(need):
            en = entries[e]
            if nvalid[n] < 8:
                continue  # nothing to judge with: keep the previous mask
            # too much "dynamic": the estimate, not the scene, is off -> no mask on this edge
            en.dynamic = None if frac[n] > self.cfg.max_dynamic_fraction else dyn_f[n]
            touched.add(int(ids[int(ii[e])]))
        for sid in touched:  # the keyframe's own mask follows its edges' newest masks
            masks = [en.dynamic for (a, _), en in self._edges.items() if a == sid and en.dynamic is not None]
            kf = self._kfs.get(sid)
            if kf is not None and masks:
                kf.dyn, kf.dyn_judged = D.keyframe_vote(masks), True

    def _keyframe_dynamic(self, sid: int) -> Optional[torch.Tensor]:
        """The dynamic mask ``[h, w]`` of keyframe ``sid`` for tracking against it: judged from its edges that the
        BA has used (once, the first time it is asked for after that), else the mask moved from its reference."""
        kf = self._kfs.get(sid)
        if kf is None or kf.dyn_judged or not self.cfg.dynamic_masking:
            return None if kf is None else kf.dyn
        g = self._graph
        if g is None or not g.has_id(sid):
            return kf.dyn
        keys = [key for key, en in self._edges.items() if key[0] == sid and en.rounds >= 1 and g.has_id(key[1])]
        if not keys:
            return kf.dyn
        ii = torch.tensor([g.index_of(a) for a, _ in keys], dtype=torch.int64)
        jj = torch.tensor([g.index_of(b) for _, b in keys], dtype=torch.int64)
        out = self._dynamic_masks(g, ii, jj, torch.stack([self._edges[key].target for key in keys]))
        if out is None:
            return kf.dyn
        dyn, frac, nvalid = out
        masks = [dyn[n].float().cpu() for n in range(len(keys))
                 if nvalid[n] >= 8 and frac[n] <= self.cfg.max_dynamic_fraction]
        kf.dyn_judged = True
        if masks:
            kf.dyn = D.keyframe_vote(masks)
        return kf.dyn
