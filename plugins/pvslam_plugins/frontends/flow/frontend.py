"""The classical ``flow`` frontend: OpenCV DIS optical flow with forward-backward and photometric confidence.

Per keyframe it keeps only a grayscale image at the flow resolution (19 KB at 320x240 with the default
``flow_scale`` 0.5, 77 KB at full resolution) and its panoptic ids at the BA resolution (~10 KB).  Per edge it
caches the BA-resolution target and confidence (computed once: a classical method answers once) plus the latest
dynamic mask, keyed by the graph's **stable keyframe ids**; the graph tells when a keyframe goes or an edge retires
(``on_keyframe_removed`` / ``on_edges_retired``) and the cached state goes with it, so the cache stays bounded by
the active edges.

Confidence of a pixel = ``exp(-fb^2 / 2 sigma^2)`` (forward-backward consistency, 0 where ``x + f(x)`` leaves
the image) x ``exp(-r^2 / 2 sigma_p^2)`` (local photometric residual) x ``lam / (lam + tau)`` (texture of the source
image, Shi-Tomasi: DIS's flow on weak texture such as the near road at speed is consistently wrong in both directions
and photometrically plausible, so only the texture itself tells), pooled over each BA block.

Long-baseline edges: when the graph's current estimate predicts a mean flow above ``init_min_flow``, DIS starts
from that prediction (older keyframe reprojected into the newer; the reverse by inverting that field), which
turns 0.8 -> 0.28 BA px median error on 4-frame gaps of the synthetic driving loop.  Far edges (index gap >=
``init_compare_min_gap``: proximity/loop) also run from zero and keep the more consistent result.

Motion filter (``track``): DIS from the last keyframe to the frame (``track_*`` settings, by default the edge
settings, whose result is then reused for the new keyframe's edges to the last keyframe), started from the previous
frame's flows at constant velocity once the motion is large enough (``track_velocity_init``); keyframe when the mean
flow exceeds ``keyframe_thresh`` BA px or fewer than ``keyframe_min_coverage`` of the pixels are still tracked;
tracking failure on a blank frame (intensity std) or when more than ``max_fb_fail_fraction`` of the pixels fail
the forward-backward check (sudden jump).  A repeated frame is not a failure (zero flow, no keyframe).  When more
than ``track_recover_fail_fraction`` of the pixels fail, DIS runs again from the homography of LK-tracked corners
(:mod:`.recover`: a fast turn moves the image beyond DIS's coarsest level) and the more consistent flow is kept;
on the synthetic head camera (``handheld_fast``, tune seeds 1-2) this took 8-15 lost frames and 2-3 map
re-initialisations per sequence to none.  Where DIS starts and the recovery: :mod:`.track_starts`.

With ``road_plane`` (default; :mod:`.road_frontend`, :mod:`.road_plane`) the ground ahead
of a car camera takes the flow of its homography, found by a direct search, where DIS cannot follow the near road at
speed (tracking flows and keyframe pairs up to ``road_max_gap`` frames apart), and once the map's road depth and its
motion agree on a camera height, the road pixels' inverse depth gets a BA prior at that height
(``road_depth_weight``: the scale of a car camera's map cannot drift). Without a road (indoors) the search finds no
plane and nothing changes (and after a few misses in a row it is tried only every few frames).

Rounds per new keyframe (``rounds``, default 1).  On an edge's first ``observe`` the weight is the
confidence only; on its next ``dynamic_updates`` calls (after at least one BA round) pixels whose observed target
disagrees with the reprojection under the current estimate by more than ``dynamic_thresh`` BA px (and 3x the
edge's median residual) are dynamic, the mask is voted over (thing) segments, and the weight follows PV-SLAM
eq. 4 with the paper convention (static -> c, dynamic -> ~ c e^-eta; see :mod:`pvslam_core.slam.confidence`).  This
also rejects outlier flow on static scenes.  With ``epipolar_cue`` (off by default), a keyframe without a
segmentation also gets the map-independent epipolar cue of its tracked flow and first edges (:mod:`.epipolar_cue`),
kept for its life.

Independent DIS calls (a frame's two tracking flows, a new keyframe's edge pairs with their forward-backward checks)
run on ``flow_threads`` threads (:mod:`.lanes`; OpenCV releases the GIL), with results bit-equal to one thread.

``initial_depth(graph, id)``: a constant map equal to the median inverse depth of the newest keyframe, as DROID-SLAM
2025 does; a median is robust to the few near/far outliers that would pull a mean.  (The mapper prefers the
previous keyframe's depth moved into the new pose once the map is initialised.)
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch

from pvslam_core.slam.confidence import observed_flow_weight
from pvslam_core.interfaces import Frontend
from pvslam_core.types import EdgeObservations, Frame, PanopticSegmentation, TrackResult
from pvslam_core.slam.graph import median_disp_map

from . import dynamic as D
from .dynamic_masking import DynamicMasking
from .recover import MotionPredictor
from .track_starts import TrackStarts
from .road_frontend import RoadFlows
from . import flow_ops as F
from .lanes import DisLanes
from .config import FlowFrontendConfig

LOG = logging.getLogger("pvslam.frontend.flow")


@dataclass
class _Keyframe:
    gray: np.ndarray  # uint8 [Hf, Wf] at the flow resolution
    frame_index: int
    seg_ba: Optional[torch.Tensor] = None  # int64 [h, w] panoptic ids at the BA resolution (block centres)
    thing_ids: Optional[torch.Tensor] = None  # int64 [K] ids of thing segments
    dyn: Optional[torch.Tensor] = None  # float32 [h, w] geometric dynamic mask (dynamic.py), 1 = moving
    dyn_judged: bool = False  # dyn comes from this keyframe's own edges (else: moved from its reference's)
    dyn_prior: Optional[torch.Tensor] = None  # bool [h, w] the mask moved from its reference (dynamic_persist)
    cue: Optional[torch.Tensor] = None  # bool [h, w] the epipolar cue's mask (epipolar_cue, dynamic_masking.py)


@dataclass
class _Edge:
    target: torch.Tensor  # float32 [2, h, w] (u, v) in the target keyframe, BA px
    conf: torch.Tensor  # float32 [h, w] FB confidence pooled to the BA resolution
    dynamic: Optional[torch.Tensor] = None  # float32 [h, w] latest dynamic mask
    rounds: int = 0  # how many times observe() returned this edge
    requested: bool = False  # asked for by observe() (else only computed alongside its reverse)


def _default_reproject():
    from pvslam_core.geometry.projective import reproject  # written by the geometry owner

    return reproject


class FlowFrontend(TrackStarts, DynamicMasking, RoadFlows, Frontend):
    """DIS optical-flow frontend (see the module docstring)."""

    def __init__(self, config: Optional[FlowFrontendConfig] = None, device: Any = "cpu", reproject_fn=None,
                 ba_downsample: int = 8):
        self.cfg = config or FlowFrontendConfig()
        self.device = torch.device(device)
        self.ba_downsample = int(ba_downsample)
        self.rounds = self.cfg.rounds
        tp = self.cfg.track_preset or self.cfg.preset
        tfs = self.cfg.track_finest_scale if self.cfg.track_finest_scale is not None else self.cfg.finest_scale
        settings = {"edge": (self.cfg.preset, self.cfg.finest_scale), "track": (tp, tfs)}
        # Calls with an initial flow get their own DIS object: after such a call, OpenCV's DIS keeps using that
        # initial flow in later calls without one (verified with OpenCV 4.x/5.0), so the zero-init flows (tracking,
        # close edges) depended on whichever edge was initialised last.  lanes.py keeps one object per kind of call
        # and thread, and runs independent calls on `flow_threads` threads.
        self._lanes = DisLanes(lambda kind: F.create_dis(settings[kind.split("_")[0]][0],
                                                         finest_scale=settings[kind.split("_")[0]][1]),
                               threads=self.cfg.flow_threads)
        self._last_track: Optional[tuple] = None  # (reference frame index, frame index, fwd, bwd) of the last track
        self._predictor = MotionPredictor()  # per-frame homographies for tracking recovery (recover.py)
        # the predictor's last observation, running on a flow worker: its RANSAC homography (~1 ms a frame) is needed
        # only when a later frame fails to track, so the pipeline thread does not wait for it (_predictor_ready)
        self._observing = None
        self._reproject_fn = reproject_fn
        self._kfs: dict[int, _Keyframe] = {}  # stable keyframe id -> keyframe (insertion order = time order)
        self._edges: dict[tuple[int, int], _Edge] = {}  # (source id, target id) -> cached edge
        self._pending: Optional[dict] = None  # the last tracked frame's gray and flow to the last keyframe
        self._cue_t: Optional[torch.Tensor] = None  # the epipolar cue's last translation direction (its sign prior)
        self._graph = None  # last graph seen in observe (for initial_depth)
        self._texture = F.TextureTerm(self.cfg.texture_tau, self.cfg.texture_quantile)  # per source image
        self._road_setup()  # the road plane's flow (road_frontend.py, opt-in)
        self.stats = {"track_calls": 0, "track_s": 0.0, "dis_calls": 0, "dis_s": 0.0, "edges_computed": 0,
                      "reprojection_init_used": 0, "track_recoveries": 0, "track_recovered": 0,
                      "track_predicted_starts": 0, "track_predicted_used": 0}

    # ----------------------------------------------------------------------------------------- helpers --
    @property
    def num_keyframes(self) -> int:
        return len(self._kfs)

    def _last_id(self) -> Optional[int]:
        return next(reversed(self._kfs)) if self._kfs else None

    def cached_edges(self) -> list[tuple[int, int]]:
        """Cached edges as stable-id pairs (for tests and diagnostics)."""
        return sorted(self._edges)

    def memory_bytes(self) -> int:
        """Approximate bytes held (keyframe images + segment maps + cached edges)."""
        n = 0
        for kf in self._kfs.values():
            n += kf.gray.nbytes
            if kf.seg_ba is not None:
                n += kf.seg_ba.numel() * kf.seg_ba.element_size()
        n += self._texture.nbytes()
        for e in self._edges.values():
            n += (e.target.numel() + e.conf.numel() + (e.dynamic.numel() if e.dynamic is not None else 0)) * 4
        return n

    def _reproject(self):
        if self._reproject_fn is None:
            self._reproject_fn = _default_reproject()
        return self._reproject_fn

    def _gray(self, frame: Frame) -> np.ndarray:
        return F.to_gray(frame.image, self.cfg.flow_scale)

    def _ba_shape_for(self, frame: Frame) -> tuple[int, int]:
        if self._graph is not None:  # the graph's BA resolution wins once one has been seen
            h, w = self._graph.ba_shape
            return int(h), int(w)
        s = self.ba_downsample
        return max(1, frame.height // s), max(1, frame.width // s)

    def _sigma(self) -> float:
        return self.cfg.fb_sigma * self.cfg.flow_scale

    def _flows(self, calls: list) -> list[np.ndarray]:
        """DIS flows of independent ``(kind, i0, i1, init)`` calls (lanes.py: on ``flow_threads`` threads)."""
        flows, seconds = self._lanes.run(calls)
        self.stats["dis_calls"] += len(calls)
        self.stats["dis_s"] += seconds
        return flows

    def _flow(self, kind: str, i0: np.ndarray, i1: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
        return self._flows([(kind, i0, i1, init)])[0]

    def _pair_calls(self, g0: np.ndarray, g1: np.ndarray, init_f: Optional[np.ndarray] = None,
                    init_b: Optional[np.ndarray] = None, kind: str = "edge") -> list:
        """The forward and backward DIS calls between two grays (with initial flows: ``kind + "_init"``)."""
        k = kind + ("_init" if init_f is not None else "")
        return [(k, g0, g1, init_f), (k, g1, g0, init_b)]


    def _direction(self, g0: np.ndarray, g1: np.ndarray, fwd: np.ndarray, bwd: np.ndarray, h: int, w: int,
                   plane: Optional[tuple] = None):
        """BA target, confidence and FB error of the flow ``g0 -> g1`` (``fwd``), checked against ``bwd``.
        ``plane = (mask, weight)``: pixels whose flow is the road plane's and their verification weight
        (``road_verify``, :meth:`_road_flows`), which stands in for the texture term there: that term is for DIS's
        mistakes on weak texture, and the road's texture is weak."""
        conf, fb = F.fb_consistency(fwd, bwd, self._sigma())
        if self.cfg.photo_sigma > 0:
            conf = conf * F.photometric_confidence(g0, g1, fwd, self.cfg.photo_sigma)
        if self.cfg.texture_tau > 0:
            tex = self._texture(g0)
            conf = conf * (tex if plane is None else np.where(plane[0], plane[1], tex))
        elif plane is not None:
            conf = conf * np.where(plane[0], plane[1], np.float32(1.0))
        t, wgt = F.pool_to_ba(fwd, conf, h, w, self.cfg.weighted_pooling)
        return t, wgt, fb

    def _seg_info(self, seg: Optional[PanopticSegmentation], h: int, w: int):
        # a segmentation that found nothing (no segments: all void) is no segmentation: the keyframe is treated as
        # with segmenter "none"
        if seg is None or seg.ids is None or not seg.segments:
            return None, None
        ids = F.downsample_ids(seg.ids.to(torch.int64).cpu(), h, w)
        # only segments of categories that can move vote (Segment.movable: a segmenter's movable-class list)
        things = torch.tensor([s.id for s in seg.segments if s.isthing and s.movable], dtype=torch.int64)
        return ids, things

    # ------------------------------------------------------------------------------------------- track --
    def track(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> TrackResult:
        t0 = time.perf_counter()
        try:
            return self._track(frame)
        finally:
            self.stats["track_calls"] += 1
            self.stats["track_s"] += time.perf_counter() - t0

    def _track(self, frame: Frame) -> TrackResult:
        self._pending = None
        last_track, self._last_track = self._last_track, None  # set again below when this frame tracks
        gray = self._gray(frame)
        std = float(gray.std())
        if not np.isfinite(std) or std < self.cfg.min_texture_std:
            return TrackResult(is_keyframe=False, mean_flow=0.0, failed=True,
                               message=f"no texture: intensity std {std:.2f} < min_texture_std "
                                       f"{self.cfg.min_texture_std}")
        last_sid = self._last_id()
        if last_sid is None:
            self._pending = {"frame_index": frame.index, "gray": gray, "last_sid": None}
            return TrackResult(is_keyframe=True, mean_flow=0.0, message="first keyframe")
        last = self._kfs[last_sid]
        if last.gray.shape != gray.shape:
            return TrackResult(is_keyframe=False, mean_flow=0.0, failed=True,
                               message=f"frame size {gray.shape} differs from the keyframes' {last.gray.shape}")
        h, w = self._ba_shape_for(frame)
        # both flows (the forward-backward check needs them), but the backward target and confidence only if this
        # frame becomes a keyframe (add_keyframe): most frames do not
        init_f, init_b = self._velocity_init(last_track, last.frame_index, frame.index)
        fwd, bwd = self._flows(self._pair_calls(last.gray, gray, init_f, init_b, kind="track"))
        if init_f is None and self.cfg.track_predict_init:  # no velocity init (e.g. the first frame after a keyframe)
            fwd, bwd = self._predicted_start(last.gray, gray, last.frame_index, frame.index, fwd, bwd)
        fwd, bwd, road, plane = self._road_track(last_sid, last.gray, last.frame_index, gray, frame, fwd, bwd)
        tf, wf, fb_f = self._direction(last.gray, gray, fwd, bwd, h, w, plane[0])
        fail_px = self.cfg.fb_fail_px * self.cfg.flow_scale
        fail_frac = self._fail_fraction(fb_f)
        if fail_frac > self.cfg.track_recover_fail_fraction:  # a fast turn (track_starts.py)
            found = self._recover(last.gray, gray, last.frame_index, frame.index, h, w, fail_frac)
            if found is not None:
                fwd, bwd, tf, wf, fb_f, fail_frac = found
                plane = (None, None)
        xs, ys = F.pixel_grid_np(h, w)
        mean_flow = float(np.sqrt((tf[0] - xs) ** 2 + (tf[1] - ys) ** 2).mean())
        target = torch.from_numpy(tf)
        weight = torch.from_numpy(np.stack([wf, wf], 0))
        # per-frame epipolar cue: with the keyframe cue only, and on the keyframes it runs on (_cue_on)
        cue = self._cue_mask(tf, wf, frame) if self.cfg.epipolar_track and self._cue_on(last_sid) else None
        if self.cfg.dynamic_masking and self.cfg.dynamic_track:
            # the reference keyframe's moving regions (dynamic.py) through eq. 4, as on its edges: the mapper's
            # motion-only BA places this frame from these weights
            dyn = self._keyframe_dynamic(last_sid)
            if cue is not None and cue[0] is not None:  # and this flow's own epipolar outliers (dynamic_masking.py)
                dyn = cue[0].float() if dyn is None else torch.maximum(dyn, cue[0].float())
            if dyn is not None and tuple(dyn.shape) == (h, w) and bool((dyn > 0).any()):
                m = dyn > 0
                weight[:, m] = observed_flow_weight(weight[:, m], dyn[m].expand(2, -1),
                                                    offset=self.cfg.panoptic_offset, convention=self.cfg.convention)
        if fail_frac > self.cfg.max_fb_fail_fraction:
            return TrackResult(is_keyframe=False, mean_flow=mean_flow, target=target, weight=weight, failed=True,
                               message=f"flow inconsistent: {fail_frac:.0%} of pixels fail the forward-backward "
                                       f"check (> {self.cfg.max_fb_fail_fraction:.0%}); sudden jump or cut?")
        self._last_track = (last.frame_index, frame.index, fwd, bwd)
        if self.cfg.track_predict_recover or self.cfg.track_predict_init:
            self._observing = self._lanes.submit(self._predictor_ready().observe, last.frame_index, frame.index, fwd,
                                                 fb_f <= fail_px)
        coverage = 1.0 - fail_frac
        is_kf = mean_flow > self.cfg.keyframe_thresh or coverage < self.cfg.keyframe_min_coverage
        self._pending = {"frame_index": frame.index, "gray": gray, "last_sid": last_sid,
                         "fwd": (tf, wf), "flows": (fwd, bwd), "ba_shape": (h, w), "road": road, "plane": plane[1],
                         **({} if cue is None else {"cue": cue})}
        return TrackResult(is_keyframe=is_kf, mean_flow=mean_flow, target=target, weight=weight,
                           message=f"tracked {coverage:.0%} of the last keyframe's pixels")

    # ------------------------------------------------------------------------------------- keyframes --
    def add_keyframe(self, kf_id: int, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        if kf_id in self._kfs:
            raise ValueError(f"add_keyframe: keyframe id {kf_id} was added before")
        pend = self._pending if (self._pending and self._pending["frame_index"] == frame.index) else None
        gray = pend["gray"] if pend is not None else self._gray(frame)
        h, w = self._ba_shape_for(frame)
        seg_ba, things = self._seg_info(seg, h, w)
        sid = int(kf_id)
        if (pend is not None and self.cfg.reuse_track_flow and pend.get("last_sid") is not None
                and pend["last_sid"] == self._last_id()):
            a = pend["last_sid"]
            (tf, wf), (fwd, bwd) = pend["fwd"], pend["flows"]
            tb, wb, _ = self._direction(gray, self._kfs[a].gray, bwd, fwd, *pend["ba_shape"], pend.get("plane"))
            self._edges[(a, sid)] = _Edge(torch.from_numpy(tf), torch.from_numpy(wf))
            self._edges[(sid, a)] = _Edge(torch.from_numpy(tb), torch.from_numpy(wb))
        self._kfs[sid] = _Keyframe(gray=gray, frame_index=frame.index, seg_ba=seg_ba, thing_ids=things)
        self._road_keyframe(sid, pend)
        if pend is not None and pend.get("last_sid") in self._kfs and self.cfg.dynamic_masking:
            ref = self._kfs[pend["last_sid"]].dyn  # its moving regions, moved along the tracked flow
            if ref is not None and tuple(ref.shape) == tuple(pend["fwd"][0].shape[-2:]) and bool((ref > 0).any()):
                self._kfs[sid].dyn = D.warp_mask(ref, torch.from_numpy(pend["fwd"][0]), self.cfg.dynamic_grow)
                if self.cfg.dynamic_persist:
                    self._kfs[sid].dyn_prior = (self._kfs[sid].dyn > 0).cpu()
        if pend is not None and "fwd" in pend:  # the map-independent cue of the tracked flow (dynamic_masking.py)
            self._keyframe_cue(pend, sid, frame)
        self._pending = None

    # -------------------------------------------------------------------------------- graph listener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        self._kfs.pop(kf_id, None)
        self._road_removed(kf_id)  # (road_frontend.py)
        for key in [e for e in self._edges if kf_id in e]:
            del self._edges[key]

    def on_edges_retired(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        for a, b in zip(src_ids.tolist(), dst_ids.tolist()):
            self._edges.pop((a, b), None)
            rev = self._edges.get((b, a))
            if rev is not None and not rev.requested:  # computed only alongside the retired direction
                del self._edges[(b, a)]

    def discard_pairs(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        # both directions: a pair's flows are computed together, from the poses of the moment (reprojection init,
        # the road plane's rotation); observed before the map existed they would stay cached that way
        for a, b in zip(src_ids.tolist(), dst_ids.tolist()):
            self._edges.pop((a, b), None)
            self._edges.pop((b, a), None)

    def initial_depth(self, graph, kf_id: int) -> Optional[torch.Tensor]:
        """The newest keyframe's median inverse depth everywhere (:func:`pvslam_core.slam.graph.median_disp_map`)."""
        return median_disp_map(graph)

    # --------------------------------------------------------------------------------------- observe --
    def observe(self, graph, ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        self._graph = graph
        h, w = (int(v) for v in graph.ba_shape)
        dev = graph.disps.device if hasattr(graph, "disps") else self.device
        ii_l, jj_l = ii.tolist(), jj.tolist()
        n = int(graph.n)
        for i, j in zip(ii_l, jj_l):
            if not (0 <= i < n and 0 <= j < n) or i == j:
                raise IndexError(f"observe: edge ({i}, {j}) is not between two of the {n} keyframes")
        ids = graph.ids.tolist()
        keys = [(ids[i], ids[j]) for i, j in zip(ii_l, jj_l)]
        unknown = sorted({k for key in keys for k in key if k not in self._kfs})
        if unknown:
            raise KeyError(f"observe: keyframe ids {unknown} were never added to this frontend")
        missing = []
        for e, key in enumerate(keys):
            ent = self._edges.get(key)
            if ent is None or tuple(ent.target.shape[-2:]) != (h, w):
                missing.append(e)
        if missing:
            self._compute_edges(graph, ids, [ii_l[e] for e in missing], [jj_l[e] for e in missing], h, w)
            self._edge_cues(graph, [keys[e] for e in missing])  # the new edges' own epipolar cue (dynamic_masking.py)
        entries = [self._edges[key] for key in keys]
        E = len(entries)
        if E == 0:
            z = torch.zeros(0, 2, h, w, dtype=torch.float32, device=dev)
            return EdgeObservations(ii, jj, z, z.clone(), torch.zeros(0, h, w, dtype=torch.float32, device=dev))
        target = torch.stack([en.target for en in entries]).to(dev)
        conf = torch.stack([en.conf for en in entries]).to(dev)
        if self.cfg.dynamic_masking:
            need = [e for e, en in enumerate(entries) if 1 <= en.rounds <= self.cfg.dynamic_updates]
            if need:
                self._update_dynamic(graph, ii, jj, need, entries, target)
            zeros = torch.zeros(h, w)
            # an edge not judged yet (first observation) takes its source keyframe's mask (dynamic.py)
            kf_dyn = [self._kfs[k[0]].dyn for k in keys]
            dyn = torch.stack([en.dynamic if en.dynamic is not None else (kd if kd is not None else zeros)
                               for en, kd in zip(entries, kf_dyn)]).to(dev)
            if self.cfg.convention == "paper":
                # eq. 4 only changes dynamic pixels; static ones keep exactly their FB confidence (no 0.99 cap)
                weight = conf.clone()
                m = dyn > 0
                if bool(m.any()):
                    weight[m] = observed_flow_weight(conf[m], dyn[m], offset=self.cfg.panoptic_offset, convention="paper")
            else:
                weight = observed_flow_weight(conf, dyn, offset=self.cfg.panoptic_offset, convention=self.cfg.convention)
        else:
            dyn = torch.zeros(E, h, w, dtype=torch.float32, device=dev)
            weight = conf
        for en in entries:
            en.rounds += 1
            en.requested = True
        weight2 = weight[:, None].expand(E, 2, h, w).contiguous()
        return EdgeObservations(ii=ii, jj=jj, target=target.float(), weight=weight2.float(), dynamic=dyn.float())

    def _compute_edges(self, graph, ids: list[int], ii: list[int], jj: list[int], h: int, w: int) -> None:
        """Compute DIS flow for the (unordered) pairs behind the given edges; cache both directions."""
        pairs: dict[tuple[int, int], None] = {}
        for i, j in zip(ii, jj):
            pairs.setdefault((min(i, j), max(i, j)), None)
        plist = list(pairs)
        inits: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        if self.cfg.use_reprojection_init and plist:
            inits = self._reprojection_inits(graph, plist, h, w)
        # one job per pair and initialisation (independent: on flow_threads threads, lanes.py), then the choices
        rots, priors = self._road_pairs(graph, ids, plist)  # the road plane's inputs (road_frontend.py), or Nones
        # (a, b, initialised), (gray a, gray b, (init_f, init_b) or None, rotation a -> b, prior plane motion)
        keys, jobs = [], []
        for p, (a, b) in enumerate(plist):
            ga, gb = self._kfs[ids[a]].gray, self._kfs[ids[b]].gray
            init = inits.get((a, b))
            if init is not None:
                keys.append((a, b, True))
                jobs.append((ga, gb, init, rots[p], priors[p]))
            if init is None or b - a >= self.cfg.init_compare_min_gap:
                keys.append((a, b, False))
                jobs.append((ga, gb, None, rots[p], priors[p]))
        results = self._lanes.map(lambda job: self._pair_job(*job, h, w), jobs)
        self.stats["dis_calls"] += 2 * len(jobs)
        self.stats["dis_s"] += sum(r[2] for r in results)
        done = {key: r[:2] for key, r in zip(keys, results)}
        for (a, b) in plist:
            sa, sb = ids[a], ids[b]
            if (a, b, True) in done:
                fwd, bwd = done[(a, b, True)]
                use = True
                if (a, b, False) in done:
                    fwd0, bwd0 = done[(a, b, False)]
                    use = float(fwd[1].mean() + bwd[1].mean()) >= float(fwd0[1].mean() + bwd0[1].mean())
                    if not use:
                        fwd, bwd = fwd0, bwd0
                if use:
                    self.stats["reprojection_init_used"] += 1
            else:
                fwd, bwd = done[(a, b, False)]
            self._edges[(sa, sb)] = _Edge(torch.from_numpy(fwd[0]), torch.from_numpy(fwd[1]))
            self._edges[(sb, sa)] = _Edge(torch.from_numpy(bwd[0]), torch.from_numpy(bwd[1]))
            self.stats["edges_computed"] += 2

    def _pair_job(self, ga: np.ndarray, gb: np.ndarray, init, R: Optional[np.ndarray], prior: Optional[np.ndarray],
                  h: int, w: int):
        """Both flows of a pair (from ``init = (init_f, init_b)`` or zero; with the road plane's where ``R``, the
        rotation a -> b, is given, searched from ``prior``) and both directions' BA targets, confidences and FB
        errors, on the calling thread's DIS objects: ``(fwd, bwd, dis seconds)``."""
        (f, s0), (b, s1) = (self._lanes.flow(c) for c in self._pair_calls(ga, gb, *(init or (None, None))))
        f, b, _, plane_f, plane_b = self._road_flows(ga, gb, f, b, R, prior)
        return self._direction(ga, gb, f, b, h, w, plane_f), self._direction(gb, ga, b, f, h, w, plane_b), s0 + s1

    def _reprojection_inits(self, graph, plist, h, w):
        """Initial flows (flow resolution, both directions) for pairs ``(a < b)`` whose predicted mean flow is
        large: ``a -> b`` from the graph's reprojection of the older keyframe ``a`` (whose depth has been
        optimised), ``b -> a`` by inverting that field (the newer keyframe's depth may still be a guess)."""
        out = {}
        try:
            reproject = self._reproject()
        except ImportError:  # geometry not available: zero init only
            return out
        a = torch.tensor([p[0] for p in plist], dtype=torch.int64)
        b = torch.tensor([p[1] for p in plist], dtype=torch.int64)
        dev = graph.disps.device
        try:
            coords, valid = reproject(graph.poses, graph.disps, graph.intrinsics, a.to(dev), b.to(dev))[:2]
        except Exception as exc:  # never let a bad estimate break flow computation
            LOG.warning("reprojection for DIS initialisation failed (%s); using zero init", exc)
            return out
        coords = coords.detach().float().cpu().numpy()
        valid = valid.detach().cpu().numpy().astype(bool)
        xs, ys = F.pixel_grid_np(h, w)
        for p, (i, j) in enumerate(plist):
            ok_f = valid[p] & np.isfinite(coords[p]).all(-1)
            if ok_f.mean() < 0.3:
                continue
            mag = np.sqrt((coords[p, ..., 0] - xs) ** 2 + (coords[p, ..., 1] - ys) ** 2)[ok_f]
            if float(mag.mean()) <= self.cfg.init_min_flow:
                continue
            back, ok_b = F.invert_coords(coords[p], ok_f)
            g = self._kfs[int(graph.ids[i])].gray
            init_f = F.init_flow_from_coords(coords[p], ok_f, *g.shape)
            init_b = F.init_flow_from_coords(back, ok_b, *g.shape, min_valid=0.2)
            if init_f is not None and init_b is not None:
                out[(i, j)] = (init_f, init_b)
        return out


def make_frontend(config: FlowFrontendConfig, context) -> FlowFrontend:
    """Registry factory: ``make_frontend(config, BuildContext)``."""
    return FlowFrontend(config, device=getattr(context, "device", "cpu"),
                        ba_downsample=getattr(context, "ba_downsample", 8))
