"""The classical ``flow`` frontend: OpenCV DIS optical flow with forward-backward, photometric and texture confidence.

Per keyframe it keeps only a grayscale image at the flow resolution (19 KB at 320x240 with the default ``dis.scale``
0.5) and, for the dynamic masks, its panoptic ids at the BA resolution (~10 KB).  Per edge it caches the
BA-resolution target and confidence (computed once: a classical method answers once), keyed by the graph's **stable
keyframe ids**; the graph tells when a keyframe goes or an edge retires (``on_keyframe_removed`` /
``on_edges_retired``) and the cached state goes with it, so the cache stays bounded by the active edges.

Confidence (:mod:`.pair_flow`): forward-backward consistency x local photometric residual x texture of the source
image (Shi-Tomasi: DIS's flow on weak texture such as the near road at speed is consistently wrong in both directions
and photometrically plausible, so only the texture itself tells), pooled over each BA block.

Long-baseline edges: when the graph's current estimate predicts a mean flow above ``INIT_MIN_FLOW``, DIS starts from
that prediction (older keyframe reprojected into the newer; the reverse by inverting that field), which makes large
displacements work; far edges (index gap >= ``INIT_COMPARE_MIN_GAP``: proximity and loop edges, where the estimate
may be off) also run from zero and keep the more consistent result.

Motion filter (``track``): DIS from the last keyframe to the frame, whose result is reused for the new keyframe's
edges to the last keyframe; where it starts (the previous frame's motion, a predicted motion) and its recovery after
a fast turn (the homography of LK-tracked corners): :mod:`.track_starts`.  Keyframe when the mean flow exceeds
``keyframes.flow_thresh`` BA px or fewer than ``keyframes.min_coverage`` of the pixels are still tracked; tracking
failure on a blank frame (intensity std) or when more than ``MAX_FB_FAIL_FRACTION`` of the pixels fail the
forward-backward check (a sudden jump).  A repeated frame is not a failure (zero flow, no keyframe).

Road plane (``road.enabled``, default; :mod:`.road_prior`, :mod:`.road_plane`): the ground ahead of a car camera
takes the flow of its homography, found by a direct search, where DIS cannot follow the near road at speed; once the
map's road depth and its motion agree on a camera height, the road pixels' inverse depth and the distance between
consecutive keyframes get BA priors at that height (the scale of a car camera's map cannot drift).  Without a road
(indoors) the search finds no plane and nothing changes.

Dynamic masking (``dynamic.enabled``; :mod:`.dynamic_masking`): on an edge's first ``observe`` the weight is the
confidence only; from the next on, pixels whose target disagrees with the reprojection under the current estimate
are dynamic (grouped into regions, voted over movable segments), and the weight follows PV-SLAM eq. 4 with the paper
convention (static -> c, dynamic -> ~ c e^-eta; :mod:`pvslam_core.slam.confidence`).  This also rejects outlier flow
on static scenes.  ``rounds`` observe -> BA rounds per new keyframe (default 1).

Independent DIS calls (a frame's two tracking flows, a new keyframe's edge pairs with their forward-backward checks)
run on ``dis.threads`` threads (:mod:`.lanes`; OpenCV releases the GIL), with results bit-equal to one thread.  With
two or more, the next frame's tracking flows begin on a thread of their own while this frame's keyframe work runs
(:meth:`FlowFrontend.prefetch`, :mod:`.prefetch`), with the same results.

``initial_depth(graph, id)``: a constant map equal to the median inverse depth of the newest keyframe, as DROID-SLAM
does; a median is robust to the few near/far outliers that would pull a mean.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional, Union

import numpy as np
import torch

from pvslam_core.adapt import ba_px_scale
from pvslam_core.geometry.projective import reproject as _reproject
from pvslam_core.interfaces import Frontend
from pvslam_core.slam.graph import median_disp_map
from pvslam_core.types import DepthPrior, DistancePrior, EdgeObservations, Frame, PanopticSegmentation, TrackResult

from . import flow_ops as F
from .config import FlowFrontendConfig
from .dynamic_masking import DynamicMasking, segment_info
from .pair_flow import FlowPairs, Plane
from .prefetch import Ahead
from .road_prior import RoadMotion, RoadPrior
from .track_starts import TrackStarts

LOG = logging.getLogger("pvslam.frontend.flow")

MIN_TEXTURE_STD = 2.0  # tracking failure when a frame's gray intensity std is below this (a black or blank frame)
MAX_FB_FAIL_FRACTION = 0.8  # tracking failure (a sudden jump) when more pixels fail the forward-backward check
# reuse the flow that tracked a frame becoming a keyframe for its edges to the previous keyframe (one flow pair less)
REUSE_TRACK_FLOW = True
# start the DIS of an edge from the flow the graph's estimate predicts (reprojection) when its mean exceeds
# INIT_MIN_FLOW BA px; edges INIT_COMPARE_MIN_GAP keyframes apart or more also run from zero and keep the result with
# the higher mean confidence (docs/decisions.md: USE_REPROJECTION_INIT)
USE_REPROJECTION_INIT = True
INIT_MIN_FLOW = 1.0
INIT_COMPARE_MIN_GAP = 4


def _no_texture(gray: np.ndarray) -> Optional[str]:
    """Why a frame cannot be tracked for want of texture (a black or blank frame), or None."""
    std = float(gray.std())
    return None if np.isfinite(std) and std >= MIN_TEXTURE_STD else \
        f"no texture: intensity std {std:.2f} < {MIN_TEXTURE_STD}"


@dataclass
class _Keyframe:
    gray: np.ndarray  # uint8 [Hf, Wf] at the flow resolution
    frame_index: int


@dataclass
class _Edge:
    target: torch.Tensor  # float32 [2, h, w] (u, v) in the target keyframe, BA px
    conf: torch.Tensor  # float32 [h, w] confidence pooled to the BA resolution
    requested: bool = False  # asked for by observe() (else only computed alongside its reverse)


@dataclass
class _Tracked:
    """The last tracked frame, for :meth:`FlowFrontend.add_keyframe` when it becomes a keyframe."""

    frame_index: int
    gray: np.ndarray  # uint8 [Hf, Wf]
    last_sid: Optional[int] = None  # the keyframe it was tracked against (None: the first keyframe)
    fwd: Optional[tuple[np.ndarray, np.ndarray]] = None  # BA target [2, h, w] and confidence [h, w], last -> frame
    flows: Optional[tuple[np.ndarray, np.ndarray]] = None  # the DIS flows (fwd, bwd) [Hf, Wf, 2]
    ba_shape: Optional[tuple[int, int]] = None
    road: Optional[RoadMotion] = None  # the road plane's motion (RoadPrior.track)
    # the road plane's pixels in the frame (the backward direction; as RoadPrior.track returns them, a function:
    # their verification runs only if the frame becomes a keyframe)
    plane: Union[Plane, Callable[[], Plane]] = None


class FlowFrontend(Frontend):
    """DIS optical-flow frontend (see the module docstring): the keyframes' images and the edge cache, composed of
    :class:`.pair_flow.FlowPairs` (DIS, confidences), :class:`.track_starts.TrackStarts`,
    :class:`.road_prior.RoadPrior` (None when ``road.enabled`` is off) and :class:`.dynamic_masking.DynamicMasking`
    (None when ``dynamic.enabled`` is off)."""

    def __init__(self, config: Optional[FlowFrontendConfig] = None, device: Any = "cpu",
                 reproject_fn: Optional[Callable] = None, ba_downsample: int = 8):
        self.cfg = config or FlowFrontendConfig()
        self.device = torch.device(device)
        self.ba_downsample = int(ba_downsample)
        self.rounds = self.cfg.rounds
        self._reproject = reproject_fn or _reproject
        self.pairs = FlowPairs(self.cfg.dis)
        self.starts = TrackStarts(self.pairs, self.ba_downsample)
        self.road = RoadPrior(self.cfg.road, self.pairs) if self.cfg.road.enabled else None
        self.masking = DynamicMasking(self.cfg.dynamic, self._reproject) if self.cfg.dynamic.enabled else None
        self._kfs: dict[int, _Keyframe] = {}  # stable keyframe id -> keyframe (insertion order = time order)
        self._edges: dict[tuple[int, int], _Edge] = {}  # (source id, target id) -> cached edge
        self._pending: Optional[_Tracked] = None
        self._graph = None  # the last graph seen in observe (BA resolution, tracking weights, predicted rotation)
        self._counts = {"track_calls": 0, "track_s": 0.0, "edges_computed": 0, "reprojection_init_used": 0,
                        "prefetched": 0}
        self._ahead = Ahead()  # the next frame's gray and tracking flows, started by prefetch()

    # ----------------------------------------------------------------------------------------- helpers --
    @property
    def stats(self) -> dict:
        """Counts and seconds: tracking, DIS calls, edges computed, reprojection inits, tracking recoveries."""
        c = self._counts
        return {"track_calls": c["track_calls"], "track_s": c["track_s"], "track_prefetched": c["prefetched"],
                **self.pairs.stats,
                "edges_computed": c["edges_computed"], "reprojection_init_used": c["reprojection_init_used"],
                **self.starts.stats}

    @property
    def num_keyframes(self) -> int:
        return len(self._kfs)

    def _last_id(self) -> Optional[int]:
        return next(reversed(self._kfs)) if self._kfs else None

    def cached_edges(self) -> list[tuple[int, int]]:
        """Cached edges as stable-id pairs (for tests and diagnostics)."""
        return sorted(self._edges)

    def memory_bytes(self) -> int:
        """Approximate bytes held (keyframe images + segment maps + cached edges and masks)."""
        n = sum(kf.gray.nbytes for kf in self._kfs.values()) + self.pairs.nbytes()
        n += sum((e.target.numel() + e.conf.numel()) * 4 for e in self._edges.values())
        return n + (self.masking.nbytes() if self.masking is not None else 0)

    def _seg_info(self, seg: Optional[PanopticSegmentation], h: int, w: int):
        """:func:`.dynamic_masking.segment_info` (kept for callers of the method)."""
        return segment_info(seg, h, w)

    def _ba_shape_for(self, frame: Frame) -> tuple[int, int]:
        if self._graph is not None:  # the graph's BA resolution wins once one has been seen
            h, w = self._graph.ba_shape
            return int(h), int(w)
        s = self.ba_downsample
        return max(1, frame.height // s), max(1, frame.width // s)

    def _put_edge(self, key: tuple[int, int], target: np.ndarray, conf: np.ndarray) -> None:
        """Cache edge ``key`` (a new one, or afresh); the masking follows the cache."""
        e = self._edges[key] = _Edge(torch.from_numpy(target), torch.from_numpy(conf))
        if self.masking is not None:
            self.masking.edge_added(key, e.target)

    def _drop_edge(self, key: tuple[int, int]) -> None:
        if self._edges.pop(key, None) is not None and self.masking is not None:
            self.masking.edge_dropped(key)

    # ------------------------------------------------------------------------------------------- track --
    def track(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> TrackResult:
        t0 = time.perf_counter()
        try:
            return self._track(frame)
        finally:
            self._counts["track_calls"] += 1
            self._counts["track_s"] += time.perf_counter() - t0

    def prefetch(self, frame: Frame) -> None:
        """Start the next frame's gray image and tracking flows against the newest keyframe on another thread
        (:class:`.prefetch.Ahead`); :meth:`track` takes them when it tracks that frame against that keyframe from
        the same previous frame, else it computes its own."""
        sid = self._last_id()
        if sid is None or self.pairs.lanes.threads < 2:  # one DIS thread: nothing runs beside this one
            return
        ref = self._kfs[sid]
        prev, job = self.starts.ahead(ref.gray, ref.frame_index)
        self._ahead.start(frame, (sid, prev), lambda: self._prefetch_job(frame, ref.gray, job))

    def _prefetch_job(self, frame: Frame, g_ref: np.ndarray, job) -> tuple:
        """On the prefetch thread: ``(gray, started)`` (started None where :meth:`_track` stops before its flows)."""
        gray = self.pairs.gray(frame.image)
        if _no_texture(gray) or gray.shape != g_ref.shape:
            return gray, None
        return gray, job(gray, frame.index)

    def _track(self, frame: Frame) -> TrackResult:
        self._pending = None
        self.starts.new_frame()
        last_sid = self._last_id()
        gray, ahead = self._ahead.take(frame, (last_sid, self.starts.previous))
        if gray is None:
            gray = self.pairs.gray(frame.image)
        blank = _no_texture(gray)
        if blank:
            return TrackResult(is_keyframe=False, mean_flow=0.0, failed=True, message=blank)
        if last_sid is None:
            self._pending = _Tracked(frame.index, gray)
            return TrackResult(is_keyframe=True, mean_flow=0.0, message="first keyframe")
        last = self._kfs[last_sid]
        if last.gray.shape != gray.shape:
            return TrackResult(is_keyframe=False, mean_flow=0.0, failed=True,
                               message=f"frame size {gray.shape} differs from the keyframes' {last.gray.shape}")
        h, w = self._ba_shape_for(frame)
        # both flows (the forward-backward check needs them), but the backward target and confidence only if this
        # frame becomes a keyframe (add_keyframe): most frames do not
        self._counts["prefetched"] += ahead is not None
        fwd, bwd = self.starts.start(last.gray, gray, last.frame_index, frame.index, ahead)
        road, plane = None, (None, None)
        if self.road is not None:
            fwd, bwd, road, plane = self.road.track(last_sid, last.gray, last.frame_index, gray, frame, fwd, bwd,
                                                    self._graph)
        tf, wf, fb_f = self.pairs.direction(last.gray, gray, fwd, bwd, h, w, plane[0])
        fail_frac = self.pairs.fail_fraction(fb_f)
        found = self.starts.recover(last.gray, gray, last.frame_index, frame.index, h, w, fail_frac)  # a fast turn
        if found is not None:
            fwd, bwd, tf, wf, fb_f, fail_frac = found
            plane = (None, None)
        xs, ys = F.pixel_grid_np(h, w)
        mean_flow = float(np.sqrt((tf[0] - xs) ** 2 + (tf[1] - ys) ** 2).mean())
        target = torch.from_numpy(tf)
        weight = torch.from_numpy(np.stack([wf, wf], 0))
        if self.masking is not None:  # the reference keyframe's moving regions through eq. 4, as on its edges
            self.masking.track_weights(last_sid, weight, self._graph)
        if fail_frac > MAX_FB_FAIL_FRACTION:
            return TrackResult(is_keyframe=False, mean_flow=mean_flow, target=target, weight=weight, failed=True,
                               message=f"flow inconsistent: {fail_frac:.0%} of pixels fail the forward-backward "
                                       f"check (> {MAX_FB_FAIL_FRACTION:.0%}); sudden jump or cut?")
        self.starts.tracked(last.frame_index, frame.index, fwd, bwd, fb_f <= self.pairs.fail_px)
        coverage = 1.0 - fail_frac
        kf = self.cfg.keyframes
        # flow_thresh is an angle of view in reference BA px (adapt.ba_px_scale)
        is_kf = mean_flow > kf.flow_thresh * ba_px_scale(frame.intrinsics, self.ba_downsample) \
            or coverage < kf.min_coverage
        self._pending = _Tracked(frame.index, gray, last_sid, (tf, wf), (fwd, bwd), (h, w), road, plane[1])
        return TrackResult(is_keyframe=is_kf, mean_flow=mean_flow, target=target, weight=weight,
                           message=f"tracked {coverage:.0%} of the last keyframe's pixels")

    # ------------------------------------------------------------------------------------- keyframes --
    def add_keyframe(self, kf_id: int, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        if kf_id in self._kfs:
            raise ValueError(f"add_keyframe: keyframe id {kf_id} was added before")
        pend = self._pending if (self._pending is not None and self._pending.frame_index == frame.index) else None
        # a frame that was not tracked just before (the first keyframe, a keyframe forced by the mapper) has no
        # reference keyframe, tracked flow or road motion
        p = pend if pend is not None else _Tracked(frame.index, self.pairs.gray(frame.image))
        h, w = self._ba_shape_for(frame)
        sid = int(kf_id)
        plane = p.plane() if callable(p.plane) else p.plane
        if p.last_sid is not None and REUSE_TRACK_FLOW and p.last_sid == self._last_id():
            a = p.last_sid
            (tf, wf), (fwd, bwd) = p.fwd, p.flows
            tb, wb, _ = self.pairs.direction(p.gray, self._kfs[a].gray, bwd, fwd, *p.ba_shape, plane)
            self._put_edge((a, sid), tf, wf)
            self._put_edge((sid, a), tb, wb)
        self._kfs[sid] = _Keyframe(gray=p.gray, frame_index=frame.index)
        if self.road is not None:
            self.road.add_keyframe(sid, frame.index, p.last_sid, p.road, plane, p.ba_shape)
            self.road.extend_back(sid, p.last_sid, lambda k: self._kfs[k].gray, self._graph)
        if self.masking is not None:
            self.masking.add_keyframe(sid, seg, h, w, p.last_sid, None if p.fwd is None else p.fwd[0])
        self._pending = None

    # -------------------------------------------------------------------------------- graph listener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        self._kfs.pop(kf_id, None)
        if self.road is not None:
            self.road.remove_keyframe(kf_id)
        if self.masking is not None:
            self.masking.remove_keyframe(kf_id)
        for key in [e for e in self._edges if kf_id in e]:
            self._drop_edge(key)

    def on_edges_retired(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        for a, b in zip(src_ids.tolist(), dst_ids.tolist()):
            self._drop_edge((a, b))
            rev = self._edges.get((b, a))
            if rev is not None and not rev.requested:  # computed only alongside the retired direction
                self._drop_edge((b, a))

    def discard_pairs(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        # both directions: a pair's flows are computed together, from the poses of the moment (reprojection init,
        # the road plane's rotation); observed before the map existed they would stay cached that way
        for a, b in zip(src_ids.tolist(), dst_ids.tolist()):
            self._drop_edge((a, b))
            self._drop_edge((b, a))

    def initial_depth(self, graph, kf_id: int) -> Optional[torch.Tensor]:
        """The newest keyframe's median inverse depth everywhere (:func:`pvslam_core.slam.graph.median_disp_map`)."""
        return median_disp_map(graph)

    def depth_prior(self, graph, idx: torch.Tensor) -> Optional[DepthPrior]:
        """The road's inverse depth at the camera height (:meth:`.road_prior.RoadPrior.depth_prior`), or None."""
        return None if self.road is None else self.road.depth_prior(graph, idx)

    def distance_prior(self, graph, idx: torch.Tensor) -> Optional[DistancePrior]:
        """The road's distance between keyframes (:meth:`.road_prior.RoadPrior.distance_prior`), or None."""
        return None if self.road is None else self.road.distance_prior(graph, idx)

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
        missing = [e for e, key in enumerate(keys)
                   if key not in self._edges or tuple(self._edges[key].target.shape[-2:]) != (h, w)]
        if missing:
            self._compute_edges(graph, ids, [ii_l[e] for e in missing], [jj_l[e] for e in missing], h, w)
        entries = [self._edges[key] for key in keys]
        E = len(entries)
        if E == 0:
            z = torch.zeros(0, 2, h, w, dtype=torch.float32, device=dev)
            return EdgeObservations(ii, jj, z, z.clone(), torch.zeros(0, h, w, dtype=torch.float32, device=dev))
        target = torch.stack([en.target for en in entries]).to(dev)
        conf = torch.stack([en.conf for en in entries]).to(dev)
        if self.masking is not None:
            dyn, weight = self.masking.observe(graph, ii, jj, keys, target, conf)
        else:
            dyn = torch.zeros(E, h, w, dtype=torch.float32, device=dev)
            weight = conf
        for en in entries:
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
        if USE_REPROJECTION_INIT and plist:
            inits = self._reprojection_inits(graph, plist, h, w)
        # the road plane's inputs per pair (road_prior.py), or Nones
        none = [None] * len(plist)
        rots, priors = self.road.pair_inputs(graph, ids, plist) if self.road is not None else (none, none)
        # one job per pair and initialisation (independent: on dis.threads threads, lanes.py), then the choices:
        # (a, b, initialised), (gray a, gray b, (init_f, init_b) or None, rotation a -> b, prior plane motion)
        keys, jobs = [], []
        for p, (a, b) in enumerate(plist):
            ga, gb = self._kfs[ids[a]].gray, self._kfs[ids[b]].gray
            init = inits.get((a, b))
            if init is not None:
                keys.append((a, b, True))
                jobs.append((ga, gb, init, rots[p], priors[p]))
            if init is None or b - a >= INIT_COMPARE_MIN_GAP:
                keys.append((a, b, False))
                jobs.append((ga, gb, None, rots[p], priors[p]))
        results = self.pairs.map(lambda job: self._pair_job(*job, h, w), jobs)
        self.pairs.count(2 * len(jobs), sum(r[2] for r in results))
        done = {key: r[:2] for key, r in zip(keys, results)}
        for (a, b) in plist:
            if (a, b, True) in done:
                fwd, bwd = done[(a, b, True)]
                use = True
                if (a, b, False) in done:
                    fwd0, bwd0 = done[(a, b, False)]
                    use = float(fwd[1].mean() + bwd[1].mean()) >= float(fwd0[1].mean() + bwd0[1].mean())
                    if not use:
                        fwd, bwd = fwd0, bwd0
                if use:
                    self._counts["reprojection_init_used"] += 1
            else:
                fwd, bwd = done[(a, b, False)]
            self._put_edge((ids[a], ids[b]), fwd[0], fwd[1])
            self._put_edge((ids[b], ids[a]), bwd[0], bwd[1])
            self._counts["edges_computed"] += 2

    def _pair_job(self, ga: np.ndarray, gb: np.ndarray, init, R: Optional[np.ndarray], prior: Optional[np.ndarray],
                  h: int, w: int):
        """Both flows of a pair (from ``init = (init_f, init_b)`` or zero; with the road plane's where ``R``, the
        rotation a -> b, is given, searched from ``prior``) and both directions' BA targets, confidences and FB
        errors, on the calling thread's DIS objects: ``(fwd, bwd, dis seconds)``."""
        p = self.pairs
        (f, s0), (b, s1) = (p.lane_flow(c) for c in p.pair_calls(ga, gb, *(init or (None, None))))
        plane_f = plane_b = None
        if self.road is not None:
            f, b, _, plane_f, plane_b = self.road.merge(ga, gb, f, b, R, prior)
        return p.direction(ga, gb, f, b, h, w, plane_f), p.direction(gb, ga, b, f, h, w, plane_b), s0 + s1

    def _reprojection_inits(self, graph, plist, h, w):
        """Initial flows (flow resolution, both directions) for pairs ``(a < b)`` whose predicted mean flow is
        large: ``a -> b`` from the graph's reprojection of the older keyframe ``a`` (whose depth has been
        optimised), ``b -> a`` by inverting that field (the newer keyframe's depth may still be a guess)."""
        out = {}
        a = torch.tensor([p[0] for p in plist], dtype=torch.int64)
        b = torch.tensor([p[1] for p in plist], dtype=torch.int64)
        dev = graph.disps.device
        try:
            coords, valid = self._reproject(graph.poses, graph.disps, graph.intrinsics, a.to(dev), b.to(dev))[:2]
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
            if float(mag.mean()) <= INIT_MIN_FLOW:
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
