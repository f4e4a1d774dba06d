"""The flow frontend's dynamic masks (PV-SLAM eq. 4 without learned weights): per edge, the observed target
against the reprojection under the current estimate, as residual candidates grouped into coherent regions
(:mod:`.dynamic`) and/or voted over the keyframe's thing segments; per keyframe, a vote over its edges' masks.

A mixin of :class:`.frontend.FlowFrontend`: it reads the frontend's ``cfg``, ``_kfs`` (keyframe state by stable
id), ``_edges`` (edge state by ``(src_id, dst_id)``), ``_graph`` and ``_reproject``.
"""
from __future__ import annotations

import logging
from typing import Optional

import torch

from pvslam_core.slam.confidence import segment_vote

from . import dynamic as D

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
            things = None
            if self.cfg.things_only:
                tid = [s_.thing_ids for s_ in srcs if s_.thing_ids is not None and s_.thing_ids.numel()]
                things = torch.unique(torch.cat(tid)) if tid else torch.zeros(0, dtype=torch.int64)
            if regions is not None and not self.cfg.vote_keeps_candidates:
                # the segment-free evidence plus the vote: a movable thing segment is dynamic when the geometry
                # inside it says it moves (more than vote_thresh of its judged pixels are candidates), elsewhere
                # the coherent regions, exactly as without a segmenter.  Not the default: on the moving-vehicles
                # tune seeds it did worse than also keeping the raw candidates (config.py, vote_keeps_candidates)
                dyn = segment_vote(dyn, seg, thresh=self.cfg.vote_thresh, thing_mask=things, valid=valid,
                                   keep_pixels=False) | regions.to(dyn.device)
            else:
                dyn = segment_vote(dyn, seg, thresh=self.cfg.vote_thresh, thing_mask=things)
                if regions is not None:  # both cues: a segment that voted or a coherent region
                    dyn = dyn | regions.to(dyn.device)
        elif regions is not None:
            dyn = regions.to(dyn.device)
        if self.cfg.dynamic_persist:
            dyn = dyn | self._persisted(srcs, h, w).to(dyn.device)
        return dyn, dyn.float().mean(dim=(1, 2)).tolist(), valid.sum(dim=(1, 2)).tolist()

    @staticmethod
    def _persisted(srcs: list, h: int, w: int) -> torch.Tensor:
        """bool ``[N, h, w]``: the mask each source keyframe inherited from its reference (moved along the tracked
        flow when it was added, ``_Keyframe.dyn_prior``), kept for the keyframe's whole life (``dynamic_persist``):
        a vehicle seen moving once stays masked while it is tracked, also on the edges where it happens to be
        epipolar-consistent."""
        out = torch.zeros(len(srcs), h, w, dtype=torch.bool)
        for n, kf in enumerate(srcs):
            if kf.dyn_prior is not None and tuple(kf.dyn_prior.shape) == (h, w):
                out[n] = kf.dyn_prior
        return out

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
