"""The learned ``raft_gru`` frontend: DROID-SLAM's frontend behaviour (and PVO's dynamic module) behind the core's
:class:`~pvslam_core.interfaces.Frontend` interface.

Per frame (``track``, DROID's ``MotionFilter``): ``fnet`` of the frame, the correlation of the last keyframe's
features with it at the identity, ``track_iters`` (DROID: 1) update steps from the last keyframe's context; the frame
is a keyframe when the mean predicted flow exceeds ``keyframe_thresh`` (1/8-resolution px).  The flow and its
confidence are returned for placing the frame (``TrackResult.target/weight``).  The keyframe set is not touched.

Per keyframe (``add_keyframe``): its ``fnet`` map (reused from ``track``), ``cnet`` context (``net0 = tanh``,
``inp = relu``), panoptic ids at the BA resolution.  Features of the newest ``feature_cache`` keyframes stay in
memory; an older keyframe keeps only its image and gets its features recomputed if a loop edge asks for them.

Per edge, keyed by the graph's stable ids ``(src, dst)``: the GRU hidden state (initialised with the source's
``net0``), the last target and weight, the correlation pyramid (``corr_impl="volume"``), PVO's mask logits and
object flow.  A new edge starts, as in DROID's ``add_factors``, with the current reprojection as its target and zero
weight.  ``on_edges_retired`` / ``on_keyframe_removed`` drop that state; nothing else does.

``observe(graph, ii, jj)`` is DROID's ``FactorGraph.update`` up to the BA: ``coords1`` = reprojection under the
graph's current poses and depths, lookup, motion input, one update step, ``target = coords1 + delta``, weights;
per source keyframe the learned damping ``eta`` (kept per keyframe id and returned for every graph keyframe as
``EdgeObservations.depth_damping``; the dense BA applies DROID's ``0.2 * eta + 1e-7``) and the upsampling mask.
The mapper calls it ``rounds`` times per keyframe with a BA after each (update -> BA -> update ...), which is
DROID's ``iters1 + iters2`` loop; the BA's 2 Gauss-Newton iterations per update are the optimizer's ``iters``.

Confidence (PV-SLAM eq. 4, :mod:`pvslam_core.slam.confidence`, the project's sign convention):
* ``variant="pvo"``: the mask head's increments accumulate in per-edge static logits (eq. 6, ``raw_mask +=
  delta_m``), binarised at ``mask_thresh``, segment vote (PVO's segm_filter), then ``panoptic_aware_weight`` on the
  raw weight logits; the object flow ``delta_dy`` is kept on dynamic pixels and fed back in the motion input.
* ``variant="droid"``: the sigmoid confidence; with ``dynamic_masking`` pixels whose update still moves them after a
  BA round are dynamic (segment vote), and eq. 4 down-weights them (``observed_flow_weight``: the targets are the
  observed flow).

Full-resolution depth: :meth:`RaftGruFrontend.upsampled_disp` (convex upsampling of the graph's current inverse
depth with the keyframe's learned mask; see its docstring for keyframes whose mask was evicted).
"""
from __future__ import annotations

import contextlib
import time
from collections import OrderedDict
from typing import Any, Optional

import torch
import torch.nn.functional as F

from pvslam_core.geometry.projective import reproject
from pvslam_core.interfaces import Frontend
from pvslam_core.types import EdgeObservations, Frame, PanopticSegmentation, TrackResult
from pvslam_core.slam.graph import median_disp_map

from .config import RaftGruConfig
from .corr import CorrVolume, OnTheFlyCorr, coords_grid
from .edge_step import (droid_weight, keyframe_segments, motion_input, pvo_dynamic, pvo_weight, residual_dynamic,
                        source_segments)
from .encoders import STRIDE
from .frontend_state import (  # noqa: F401  (DAMPING_INIT, STAGES, RandomWeightsWarning: re-exported)
    DAMPING_INIT, STAGES, EdgeState, KeyframeState, RandomWeightsWarning, StageStats, effective_precision,
    load_network)
from .net import RaftGruNet
from .update import GateContext
from .upsample import upsample_disp

MIN_TEXTURE_STD = 2.0  # tracking failure when a frame's gray intensity std is below this (a black or blank frame)
# variant droid: a pixel is dynamic only above this multiple of its edge's median residual too (robust to an estimate
# that has not converged yet), as in the flow frontend
DYNAMIC_REL_THRESH = 3.0


class RaftGruFrontend(Frontend):
    """DROID-SLAM / PVO learned frontend (see the module docstring)."""

    def __init__(self, config: Optional[RaftGruConfig] = None, device: Any = "cpu", ba_downsample: int = 8,
                 model: Optional[RaftGruNet] = None):
        self.cfg = config or RaftGruConfig(weights="random")
        self.device = torch.device(device)
        if int(ba_downsample) != STRIDE:
            raise ValueError(f"raft_gru works at the network's 1/{STRIDE} feature resolution: set graph.ba_downsample "
                             f"= {STRIDE} (got {ba_downsample})")
        self.model = (model if model is not None else load_network(self.cfg, self.device)).to(self.device).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.variant = self.model.variant
        if self.cfg.variant is not None and self.cfg.variant != self.variant:
            raise ValueError(f"raft_gru: variant={self.cfg.variant!r} but the network is {self.variant!r}")
        self.rounds = int(self.cfg.resolved("rounds"))
        self.precision = effective_precision(self.cfg.resolved("precision"), self.device)
        self.update_window = int(self.cfg.resolved("update_window"))
        self.corr_impl = self.cfg.resolved("corr_impl")
        vt = self.cfg.dynamic.vote_thresh
        self.vote_thresh = vt if vt is not None else (0.8 if self.variant == "pvo" else 0.5)
        self._kfs: dict[int, KeyframeState] = {}  # stable id -> keyframe (insertion order = time order)
        self._lru: OrderedDict[int, None] = OrderedDict()  # ids whose features are in memory, least recent first
        self._edges: dict[tuple[int, int], EdgeState] = {}  # (src id, dst id) -> per-edge state
        self._pending: Optional[dict] = None  # the last tracked frame's fmap (reused when it becomes a keyframe)
        self._graph = None  # last graph seen (for initial_depth and evictions)
        self._coords0: dict[tuple[int, int], torch.Tensor] = {}
        self._zero_motion: dict = {}  # context shape -> the zero motion input's share of the GRU gates
        self.stats = StageStats()

    # ------------------------------------------------------------------------------------------- helpers --
    def _autocast(self):
        if self.precision != "bf16":
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=torch.bfloat16)

    def _grid(self, h: int, w: int) -> torch.Tensor:
        g = self._coords0.get((h, w))
        if g is None:
            g = self._coords0[(h, w)] = coords_grid(h, w, device=self.device)
        return g

    @contextlib.contextmanager
    def _timed(self, key: str):
        t, c = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            self.stats.seconds[key] = self.stats.seconds.get(key, 0.0) + time.perf_counter() - t
            self.stats.cpu[key] = self.stats.cpu.get(key, 0.0) + time.thread_time() - c

    def _images(self, image: torch.Tensor) -> torch.Tensor:
        if image.dim() != 3 or image.shape[0] != 3:
            raise ValueError(f"raft_gru: frames must be uint8 [3, H, W], got {tuple(image.shape)}")
        h, w = image.shape[-2:]
        if h % STRIDE or w % STRIDE:
            raise ValueError(f"raft_gru: image {w}x{h} is not a multiple of {STRIDE} in both sides; set the dataset's "
                             f"crop_multiple = {STRIDE} (or resize)")
        return image.to(self.device)[None, None]  # (1, 1, 3, H, W) RGB

    def _fnet(self, image: torch.Tensor) -> torch.Tensor:
        with self._timed("fnet"), torch.no_grad(), self._autocast():
            return self.model.features(self._images(image), "rgb", context=False).fmap[0, 0].float()

    def _cnet(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with self._timed("cnet"), torch.no_grad(), self._autocast():
            net, inp = self.model.context(self._images(image), "rgb")
        return net[0, 0].float(), inp[0, 0].float()

    def _touch(self, kf_id: int) -> None:
        self._lru[kf_id] = None
        self._lru.move_to_end(kf_id)

    def _shrink(self) -> None:
        """Evict the least recently used keyframes' features beyond ``feature_cache`` (called at the end of each
        public call, so that nothing a call is using goes away under it)."""
        while len(self._lru) > self.cfg.feature_cache:
            old, _ = self._lru.popitem(last=False)
            self._evict(old)

    def _evict(self, kf_id: int) -> None:
        kf = self._kfs.get(kf_id)
        if kf is None:
            return
        if kf.upmask is not None and self._graph is not None and self._graph.has_id(kf_id):
            disp = self._graph.disps[self._graph.index_of(kf_id)].float().to(self.device)
            kf.disp_up = upsample_disp(disp[None, None], self._upmask(kf)[None, None])[0, 0].half()
            kf.disp_lo = disp.clone()
        kf.fmap = kf.net0 = kf.inp = kf.upmask = kf.gates = kf.filter_gates = None

    def _features(self, kf_id: int) -> KeyframeState:
        """The keyframe with its features in memory (recomputed from its image after an eviction)."""
        kf = self._kfs[kf_id]
        if kf.fmap is None:
            with self._timed("recompute"):
                kf.fmap = self._fnet(kf.image)
                kf.net0, kf.inp = self._cnet(kf.image)
            self.stats.counts["recomputed"] += 1
        self._touch(kf_id)
        return kf

    def _upmask(self, kf: KeyframeState) -> torch.Tensor:
        """float32 ``[576, h, w]`` convex-upsampling logits of the keyframe's last update (from its stored features;
        the same numbers as computing them in the update, rounded to fp16 as they were stored before)."""
        with torch.no_grad(), self._autocast():
            return self.model.update.agg.upmask_of(kf.upmask[None, None])[0, 0].half().float()

    def _gates(self, kf: KeyframeState, motion_filter: bool = False) -> GateContext:
        """The keyframe's share of the GRU gates (:class:`.update.GateContext`), computed at its first use: its
        context ``inp`` (every edge leaving it), or for the motion filter also ``net0`` and the zero motion input.
        Same numbers as the plain update to float rounding (``tests/test_fast_paths.py``), fewer convolutions."""
        attr = "filter_gates" if motion_filter else "gates"
        g = getattr(kf, attr)
        if g is None:
            base = self._gates(kf) if motion_filter else None
            with self._timed("gates"), torch.no_grad(), self._autocast():
                upd = self.model.update
                if motion_filter:  # = gate_context(inp, net=net0, zero_motion=True) from the parts computed anyway
                    part = upd.gru.context(bias=False, net=kf.net0[None])
                    zero = self._zero_motion.get(kf.inp.shape)
                    if zero is None:  # the zero motion's features are the same constant map for every keyframe
                        h, w = kf.inp.shape[-2:]
                        flow0 = upd.flow_encoder(kf.inp.new_zeros(1, upd.motion_dim, h, w))
                        zero = self._zero_motion[kf.inp.shape] = upd.gru.context(bias=False, motion=flow0).zrq
                    g = GateContext(base.zrq + part.zrq + zero, ("net", "inp", "motion"), part.glo)
                else:
                    g = upd.gate_context(kf.inp[None])
            setattr(kf, attr, g)
        return g

    # -------------------------------------------------------------------------------------- public state --
    @property
    def num_keyframes(self) -> int:
        return len(self._kfs)

    def edge_ids(self) -> list[tuple[int, int]]:
        """Edges with state, as stable-id pairs (for tests and diagnostics)."""
        return sorted(self._edges)

    def memory_bytes(self) -> int:
        """Bytes held in tensors (keyframe images/features/masks, per-edge states and volumes)."""
        return sum(kf.nbytes() for kf in self._kfs.values()) + sum(e.nbytes() for e in self._edges.values())

    # ----------------------------------------------------------------------------------------- track --
    def track(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> TrackResult:
        self.stats.counts["track"] += 1
        try:
            with self._timed("track"):
                return self._track(frame)
        finally:
            self._shrink()

    def _track(self, frame: Frame) -> TrackResult:
        self._pending = None
        gray_std = float(frame.image.float().mean(0).std())
        if not gray_std >= MIN_TEXTURE_STD:
            return TrackResult(is_keyframe=False, mean_flow=0.0, failed=True,
                               message=f"no texture: intensity std {gray_std:.2f} < {MIN_TEXTURE_STD}")
        fmap = self._fnet(frame.image)
        self._pending = {"frame_index": frame.index, "fmap": fmap}
        if not self._kfs:
            return TrackResult(is_keyframe=True, mean_flow=0.0, message="first keyframe")
        last_id = next(reversed(self._kfs))
        last = self._features(last_id)
        if last.fmap.shape != fmap.shape:
            return TrackResult(is_keyframe=False, mean_flow=0.0, failed=True,
                               message=f"frame size {tuple(frame.image.shape[-2:])} differs from the keyframes'")
        with self._timed("filter"):
            target, weight = self._filter_flow(last, fmap)
        h, w = fmap.shape[-2:]
        mean_flow = float((target - self._grid(h, w)).norm(dim=-1).mean())
        if not torch.isfinite(target).all():
            return TrackResult(is_keyframe=False, mean_flow=0.0, failed=True, message="non-finite flow")
        return TrackResult(is_keyframe=mean_flow > self.cfg.keyframe_thresh, mean_flow=mean_flow,
                           target=target.permute(2, 0, 1).contiguous(), weight=weight.permute(2, 0, 1).contiguous(),
                           message=f"mean flow {mean_flow:.2f} px to keyframe {last_id}")

    def _filter_flow(self, last: KeyframeState, fmap: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """DROID's motion filter: ``track_iters`` update steps of the edge last keyframe -> frame from the identity
        (the first with zero motion input, as upstream).  Returns ``target, weight (h, w, 2)``."""
        h, w = fmap.shape[-2:]
        coords0 = self._grid(h, w)
        dc = self.cfg.dynamic
        with torch.no_grad(), self._autocast():
            vol = CorrVolume(last.fmap[None, None], fmap[None, None], pool="features")
            net, inp = last.net0[None, None], last.inp[None, None]
            coords1 = coords0.expand(1, 1, h, w, 2)
            target, raw_mask, delta_dy = coords1, None, None
            for it in range(self.cfg.track_iters):
                corr = vol(coords1)
                motion = None
                if it > 0:
                    motion = motion_input(self.variant, coords0, coords1, target, delta_dy, raw_mask)
                out = self.model.update(net, None, corr, motion, ctx=self._gates(last, motion_filter=it == 0))
                net = out.net
                target = coords1 + out.delta.float()
                if self.variant == "pvo":
                    raw_mask = out.delta_m.float() if raw_mask is None else raw_mask + out.delta_m.float()
                    dyn_c, _ = pvo_dynamic(raw_mask[0], dc.mask_thresh)
                    delta_dy = out.delta_dy.float() * dyn_c[None]
                    weight = pvo_weight(out.weight.float()[0], dyn_c if dc.enabled else None, dc.panoptic_offset,
                                        dc.convention)[None]
                else:
                    weight = out.weight.float()
                coords1 = target
        return target[0, 0], weight[0, 0]

    # ------------------------------------------------------------------------------------- keyframes --
    def add_keyframe(self, kf_id: int, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        kf_id = int(kf_id)
        if kf_id in self._kfs:
            raise ValueError(f"add_keyframe: keyframe id {kf_id} was added before")
        pend = self._pending if (self._pending and self._pending["frame_index"] == frame.index) else None
        fmap = pend["fmap"] if pend is not None else self._fnet(frame.image)
        net0, inp = self._cnet(frame.image)
        h, w = fmap.shape[-2:]
        seg_ids, things = keyframe_segments(seg, h, w, STRIDE, self.device)
        if self._kfs:  # only the newest keyframe is the motion filter's reference
            self._kfs[next(reversed(self._kfs))].filter_gates = None
        self._kfs[kf_id] = KeyframeState(image=frame.image.cpu(), frame_index=int(frame.index),
                                     damping=torch.full((h, w), DAMPING_INIT, device=self.device), fmap=fmap,
                                     net0=net0, inp=inp, seg=seg_ids, things=things)
        self._touch(kf_id)
        self._shrink()
        self._pending = None
        self.stats.counts["keyframes"] += 1

    # -------------------------------------------------------------------------------- graph listener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        self._kfs.pop(kf_id, None)
        self._lru.pop(kf_id, None)
        for key in [k for k in self._edges if kf_id in k]:
            del self._edges[key]

    def on_edges_retired(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        for key in zip(src_ids.tolist(), dst_ids.tolist()):
            self._edges.pop(key, None)

    def discard_pairs(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        # the same per-edge state as a retirement drops: the next observe starts these edges afresh (DROID's
        # add_factors: reprojection target, the source's net0)
        self.on_edges_retired(src_ids, dst_ids)

    def initial_depth(self, graph, kf_id: int) -> Optional[torch.Tensor]:
        """The newest keyframe's median inverse depth everywhere (:func:`pvslam_core.slam.graph.median_disp_map`)."""
        return median_disp_map(graph)

    # ------------------------------------------------------------------------------------ upsampling --
    def upsampled_disp(self, graph, kf_id: int) -> torch.Tensor:
        """Full-resolution inverse depth ``float32 [H, W]`` of keyframe ``kf_id`` (DROID's ``disps_up``).

        While the keyframe's learned upsampling mask is in memory (it is one of the newest ``feature_cache``
        keyframes): the convex upsampling of the graph's *current* inverse depth.  After its eviction: the
        upsampling made then, multiplied by the (bilinearly upsampled) ratio of the current low-resolution depth to
        the one it was made from, so later BAs (loop closure, the final global BA) still move it.  Without any
        mask (``upsample = false``): bilinear upsampling.
        """
        kf = self._kfs[int(kf_id)]
        disp = graph.disps[graph.index_of(int(kf_id))].float().to(self.device)
        h, w = disp.shape
        if kf.upmask is not None:
            return upsample_disp(disp[None, None], self._upmask(kf)[None, None])[0, 0]
        size = (STRIDE * h, STRIDE * w)
        if kf.disp_up is not None:
            ratio = disp / kf.disp_lo.clamp(min=1e-6)
            ratio = F.interpolate(ratio[None, None], size=size, mode="bilinear", align_corners=False)[0, 0]
            return kf.disp_up.float() * ratio
        return F.interpolate(disp[None, None], size=size, mode="bilinear", align_corners=False)[0, 0]

    # --------------------------------------------------------------------------------------- observe --
    def observe(self, graph, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        try:
            return self._observe(graph, ii, jj)
        finally:
            self._shrink()

    def _observe(self, graph, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        self._graph = graph
        self.stats.counts["observe"] += 1
        h, w = (int(v) for v in graph.ba_shape)
        n = int(graph.n)
        ii = ii.to(graph.device, torch.int64).reshape(-1)
        jj = jj.to(graph.device, torch.int64).reshape(-1)
        ii_l, jj_l = ii.tolist(), jj.tolist()
        for i, j in zip(ii_l, jj_l):
            if not (0 <= i < n and 0 <= j < n) or i == j:
                raise IndexError(f"observe: edge ({i}, {j}) is not between two of the {n} keyframes")
        ids = graph.ids.tolist()
        keys = [(ids[i], ids[j]) for i, j in zip(ii_l, jj_l)]
        unknown = sorted({k for key in keys for k in key if k not in self._kfs})
        if unknown:
            raise KeyError(f"observe: keyframe ids {unknown} were never added to this frontend")
        E = len(keys)
        if E == 0:
            damping = torch.stack([self._kfs[k].damping for k in ids]).to(graph.device) if n else None
            z = torch.zeros(0, 2, h, w, device=graph.device)
            return EdgeObservations(ii, jj, z, z.clone(), torch.zeros(0, h, w, device=graph.device), damping)
        fh, fw = self._features(keys[0][0]).fmap.shape[-2:]
        if (fh, fw) != (h, w):
            raise ValueError(f"raft_gru: the network's 1/{STRIDE} maps are {fh}x{fw} but the graph's BA resolution is "
                             f"{h}x{w}; set graph.ba_downsample = {STRIDE}")
        with self._timed("reproject"):
            coords1, valid = reproject(graph.poses, graph.disps.float(), graph.intrinsics, ii, jj)
            coords1 = torch.nan_to_num(coords1.float(), nan=-1e4, posinf=1e4, neginf=-1e4).clamp(-1e4, 1e4)
            coords1, valid = coords1.to(self.device), valid.to(self.device)
        for e, key in enumerate(keys):
            if key not in self._edges:  # DROID add_factors: target = reprojection, weight 0, net = source's net0
                src = self._features(key[0])
                self._edges[key] = EdgeState(
                    net=src.net0.clone(), target=coords1[e].clone(), weight=torch.zeros(h, w, 2, device=self.device),
                    raw_mask=torch.zeros(h, w, 2, device=self.device) if self.variant == "pvo" else None,
                    delta_dy=torch.zeros(h, w, 2, device=self.device) if self.variant == "pvo" else None)
        lo = n - self.update_window
        upd = [e for e, key in enumerate(keys)
               if self.update_window == 0 or self._edges[key].updates == 0 or max(ii_l[e], jj_l[e]) >= lo]
        # sorted by source (stable): the edges of one source keyframe share its gate context, added per run
        upd.sort(key=lambda e: ii_l[e])
        if upd:
            self._update([keys[e] for e in upd], ii[upd], jj[upd], coords1[upd], valid[upd], ids)
        entries = [self._edges[k] for k in keys]
        target = torch.stack([en.target for en in entries]).permute(0, 3, 1, 2)
        weight = torch.stack([en.weight for en in entries]).permute(0, 3, 1, 2)
        zeros = torch.zeros(h, w, device=self.device)
        dyn = torch.stack([en.dynamic if en.dynamic is not None else zeros for en in entries])
        damping = torch.stack([self._kfs[k].damping for k in ids]).to(graph.device)
        self.stats.counts["edges_returned"] += E
        return EdgeObservations(ii, jj, target.contiguous().to(graph.device), weight.contiguous().to(graph.device),
                                dynamic=dyn.to(graph.device), depth_damping=damping)

    def _lookup(self, keys: list[tuple[int, int]], coords1: torch.Tensor) -> torch.Tensor:
        """Correlation lookup ``(1, E, 196, h, w)`` of edges ``keys`` at ``coords1 (1, E, h, w, 2)``."""
        if self.corr_impl == "onthefly":
            uniq = sorted({k for key in keys for k in key})
            pos = {k: p for p, k in enumerate(uniq)}
            fmaps = torch.stack([self._features(k).fmap for k in uniq])[None]
            src = torch.tensor([pos[a] for a, _ in keys], device=self.device)
            dst = torch.tensor([pos[b] for _, b in keys], device=self.device)
            with self._autocast():
                return OnTheFlyCorr(fmaps, src, dst)(coords1)
        dtype = torch.bfloat16 if self.precision == "bf16" else torch.float32
        out = []
        for e, key in enumerate(keys):
            edge = self._edges[key]
            if edge.corr is None:
                a, b = self._features(key[0]).fmap, self._features(key[1]).fmap
                edge.corr = CorrVolume(a[None, None].to(dtype), b[None, None].to(dtype), pool="features")
            out.append(edge.corr(coords1[:, e:e + 1]))  # fp32 coordinates (bf16 would round to 1/4 px at 32+ px)
        return torch.cat(out, dim=1)

    def _update(self, keys, ii: torch.Tensor, jj: torch.Tensor, coords1: torch.Tensor, valid: torch.Tensor,
                ids: list[int]) -> None:
        """One GRU update of edges ``keys`` (graph indices ``ii -> jj``) at the reprojection ``coords1 (E, h, w,
        2)``."""
        E = len(keys)
        h, w = coords1.shape[1:3]
        edges = [self._edges[k] for k in keys]
        srcs = [self._features(a) for a, _ in keys]
        c1 = coords1[None]
        with torch.no_grad():
            with self._timed("corr"):
                corr = self._lookup(keys, c1)
            target0 = torch.stack([e.target for e in edges])[None]
            raw_mask = delta_dy = None
            if self.variant == "pvo":
                raw_mask = torch.stack([e.raw_mask for e in edges])
                delta_dy = torch.stack([e.delta_dy for e in edges])[None]
            motion = motion_input(self.variant, self._grid(h, w), c1, target0, delta_dy,
                                  None if raw_mask is None else raw_mask[None])
            net = torch.stack([e.net for e in edges])[None]
            srcs_run = list(dict.fromkeys(a for a, _ in keys))  # the edges are sorted by source: one run each
            if sum(1 for x, y in zip(keys, keys[1:]) if x[0] != y[0]) != len(srcs_run) - 1:
                raise RuntimeError("raft_gru: _update needs the edges grouped by source keyframe")
            gates = [self._gates(self._kfs[a]) for a in srcs_run]
            ctx = GateContext(torch.cat([g.zrq for g in gates]), gates[0].const,
                              groups=[sum(1 for a, _ in keys if a == s) for s in srcs_run])
            with self._timed("update"), self._autocast():
                out = self.model.update(net, None, corr, motion, ii.to(self.device), jj.to(self.device), ctx=ctx,
                                        upmask=False)
        self.stats.counts["edge_updates"] += E
        with self._timed("weights"):
            delta = out.delta[0].float()
            target = coords1 + delta
            seg, things = source_segments(srcs, h, w, self.cfg.dynamic.things_only, self.device)
            dc = self.cfg.dynamic
            if self.variant == "pvo":
                raw_mask = raw_mask + out.delta_m[0].float()
                dyn_c, dyn = pvo_dynamic(raw_mask, dc.mask_thresh, seg, things, self.vote_thresh)
                new_dy = out.delta_dy[0].float() * dyn_c
                weight = pvo_weight(out.weight[0].float(), dyn_c if dc.enabled else None, dc.panoptic_offset,
                                    dc.convention)
                dyn = dyn if dc.enabled else None
            else:
                conf = out.weight[0].float()
                dyn = None
                seen = torch.tensor([e.updates > 0 for e in edges], device=self.device)
                if dc.enabled and bool(seen.any()):
                    dyn = residual_dynamic(delta.norm(dim=-1), valid, dc.thresh, DYNAMIC_REL_THRESH, dc.max_fraction,
                                           seg, things, self.vote_thresh)
                    dyn = dyn * seen[:, None, None]  # an edge's first update has seen no BA yet
                weight = droid_weight(conf, dyn, dc.panoptic_offset, dc.convention)
            net_new = out.net[0].float()
            for k, edge in enumerate(edges):
                edge.net, edge.target, edge.weight = net_new[k], target[k], weight[k]
                edge.dynamic = None if dyn is None else dyn[k]
                edge.updates += 1
                if self.variant == "pvo":
                    edge.raw_mask, edge.delta_dy = raw_mask[k], new_dy[k]
            # per source keyframe (sorted unique ii): learned damping and upsampling mask
            eta = out.eta[0].float()
            for u, fr in enumerate(out.frames.tolist()):
                kf = self._kfs[ids[fr]]
                kf.damping = eta[u]
                if self.cfg.upsample:
                    kf.upmask = out.agg_features[0, u]

def make_frontend(config: RaftGruConfig, context) -> RaftGruFrontend:
    """Registry factory: ``make_frontend(config, BuildContext)``."""
    return RaftGruFrontend(config, device=getattr(context, "device", "cpu"),
                           ba_downsample=getattr(context, "ba_downsample", 8))
