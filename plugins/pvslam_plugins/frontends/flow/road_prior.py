"""The road plane in the flow frontend (``road.enabled``, default): its flow on the near road, and the BA priors it
gives (the search and the merge: :mod:`.road_plane`).

Where the plane's flow goes in: the tracking flow of every frame (rotation predicted at the rate of the last two
keyframes, the plane motion started from the last frame's at constant velocity, else searched from scratch; after
``ROAD_BACKOFF_AFTER`` misses in a row, as indoors, only on every few frames), and the edge flows of keyframe pairs
at most ``ROAD_MAX_GAP`` frames apart (the map's rotation; pairs further apart than two frames start from the chain
of tracked plane motions, :class:`~.road_plane.RoadChain`).  A plane pixel's confidence is its verification weight
``exp(-r^2 / 2 sigma^2)`` (``r``: DIS's residual between the views aligned by the merged flow; ``sigma`` as the
forward-backward check's) in place of the texture term: the plane's two directions come from one homography, so the
forward-backward check passes them all, and the texture term was made for DIS's mistakes on weak texture - the
road's own.

The road's depth (``road.depth_weight``): a keyframe's verified plane pixels (those of its tracking flow) lie on the
road, whose inverse depth at BA row ``y`` is ``(y - cy) / (fy h)`` for a camera ``h`` above it.  The camera height of
a car camera does not change, so one ``h`` in map units gives every keyframe an inverse-depth prior
(:meth:`RoadPrior.depth_prior`, DROID-SLAM's sensor-depth term) at one scale: on a straight road, where the flow
hardly constrains the scale, it cannot drift.  ``h`` is measured once, when the map's road depth and the map's motion
over the road's (in camera heights) tell the same height; until then there is no prior.  When the distance prior below
already holds the map at its own height, the depth prior takes that one (its gate still decides when it starts): two
priors at two heights would hold the map's first stretch and the rest at two scales.  The prior's weight is
relative, ``alpha0 (d - d_prior)^2 / d_prior^2``: the flow's depth curvature grows with the squared baseline, so an
absolute weight would be strong or negligible by the map's scale.  The plane's normal is taken as the camera's y
axis, as the search does.

The road's distance (``road.distance_weight``): consecutive keyframes whose tracking chained plane motions between
them are ``h |v|`` apart (``v``: the road's translation in camera heights; ``h`` here measured once from the map's
motion over the road's alone), a BA prior on the distance between their camera centres
(:meth:`RoadPrior.distance_prior`).  On a highway the keyframes are several metres apart and the near road, whose
flow tells the speed, has left the view by the next keyframe: no keyframe edge holds the scale there, and the road
depth never agrees with the motion (the gate above stays closed), but the frame-to-frame plane motions do.  The
keyframes tracked before the road was first found join its chain backwards, each searched from the chain's velocity
(:meth:`RoadPrior.extend_back`), so the map's first stretch does not keep the initialisation's scale.

:class:`RoadPrior` owns the search's state across frames (the plane velocity, the back-off, the chain of road poses),
the keyframes' road pixels and the measured camera heights.  Gray images and flows are at the flow resolution.
"""
from __future__ import annotations

import logging
from collections import deque
from typing import Callable, Optional

import cv2
import numpy as np
import torch

from pvslam_core.geometry.projective import edge_transforms
from pvslam_core.types import DepthPrior, DistancePrior, Frame

from .config import RoadConfig
from .pair_flow import FlowPairs, Plane
from .road_plane import RoadChain, RoadPlane, flow_intrinsics

LOG = logging.getLogger("pvslam")

ROAD_REGION = 0.15  # a search from scratch covers the rows from this fraction of the image height below cy
ROAD_MARGIN = 1.1  # a pixel takes the plane's flow where its 5x5 brightness residual is below this x DIS's
# keyframe pairs further apart (frames) keep DIS's flow: far apart the ground left in view is a thin band near the
# horizon where sidewalks and building bases pass for road
ROAD_MAX_GAP = 5
# weigh the plane's pixels by DIS's residual between the views aligned by the merged flow (two more DIS calls a pair)
# instead of the texture term; the depth prior needs it (docs/decisions.md: ROAD_VERIFY)
ROAD_VERIFY = True
ROAD_H_KEYFRAMES = 3  # consecutive keyframes whose road and motion measure the camera height (_camera_height)
ROAD_H_SETTLE = 2  # ... the newest of them at least this many keyframes older than the newest keyframe
ROAD_H_AGREE = 1.25  # the largest ratio between the two measurements that counts as agreement
# The distance prior: its camera height only from three pairs whose heights (map translation / road translation)
# agree within this ratio, and a pair only while its road distance and the map's agree within this
ROAD_DIST_CONSISTENT = 1.5
ROAD_DIST_AGREE = 2.0
ROAD_DIST_LOOKBACK = 64  # ... its three pairs among this many newest keyframes (no road: not a walk of the whole map)
# Without a road (indoors) the search from scratch never finds a plane, at about a fifth of the frame's CPU: after
# this many consecutive misses the tracking search skips 1, 2, 4, ... frames between tries (a found plane resets it;
# docs/decisions.md: ROAD_BACKOFF_AFTER)
ROAD_BACKOFF_AFTER = 8
ROAD_BACKOFF_MAX = 8  # ... at most this many: a road coming into view is found within 9 frames (0.3 s at 30 Hz)
# when the tracking's first plane motion begins a chain, the keyframes before it that have none (the plane from
# scratch lost to DIS's flow, as on a highway's first frames) are searched backwards from its velocity, so the distance
# prior holds the map's first stretch too (docs/decisions.md: ROAD_BACKWARD)
ROAD_BACKWARD = True

RoadMotion = tuple[Optional[np.ndarray], Optional[np.ndarray]]  # (rotation [3, 3], plane motion v [3]) of a frame


class RoadPrior:
    """The road plane's flows and BA priors for :class:`~.frontend.FlowFrontend` (module docstring).  ``pairs``:
    the frontend's DIS flows (the verification's DIS calls and the forward-backward scale)."""

    def __init__(self, cfg: RoadConfig, pairs: FlowPairs):
        self.cfg = cfg
        self._pairs = pairs
        self._plane = RoadPlane(ROAD_REGION, ROAD_MARGIN)
        self._frames: dict[int, int] = {}  # kf id -> frame index (insertion order = time order, as the frontend's)
        self._chain = RoadChain()  # the keyframes' poses relative to the road (priors of pairs far apart)
        self._vel: Optional[tuple[int, np.ndarray]] = None  # (frame index, plane motion per frame) last tracked
        self._K_flow: Optional[np.ndarray] = None  # K at the flow resolution, from the first tracked frame
        self._rotation = _MapRotation()  # the tracking's predicted rotation reads it every frame
        self._weights: dict[int, torch.Tensor] = {}  # kf id -> float32 [h, w] weight of its road pixels (BA res)
        self.height: Optional[float] = None  # the camera height in map units for the depth prior, once measured
        # the depth prior's gate: its measurements (keyframes, by motion, by depth), the newest 64; how many there were
        self.height_tries: deque[tuple[int, float, float]] = deque(maxlen=64)
        self._height_n = 0
        # the camera height in map units from the map's motion over the road's alone, measured once (distance prior)
        self.height_motion: Optional[float] = None
        self._misses = 0  # consecutive tracking searches from scratch without a plane
        self._skip = 0  # frames whose tracking search is still to be skipped (the back-off)

    @property
    def stats(self) -> dict:
        """The search's counts (:class:`~.road_plane.RoadPlane`; ``backed_off``: frames not searched)."""
        return self._plane.stats

    def has_road_pixels(self, kf_id: int) -> bool:
        return kf_id in self._weights

    # ------------------------------------------------------------------------------------------ flows --
    def merge(self, g0: np.ndarray, g1: np.ndarray, fwd: np.ndarray, bwd: np.ndarray, R: Optional[np.ndarray],
              prior: Optional[np.ndarray] = None, lanes: bool = False, defer_backward: bool = False):
        """A pair's DIS flows with the road plane's flow merged in: ``(fwd, bwd, v, plane_f, plane_b)``, ``v`` the
        plane motion and per direction the plane's pixels for :meth:`.FlowPairs.direction`; unchanged and Nones
        without a rotation ``R`` or an accepted plane.  ``lanes``: the verification's two DIS calls run on both
        lanes (only from the pipeline thread: an edge job already runs on a lane, and a nested map there would wait
        on the worker it occupies); each lane's DIS objects give the same flow, so the result does not depend on
        it.  ``defer_backward``: ``plane_b`` is a function that computes it (its verification runs when called)."""
        if self._K_flow is None or R is None:
            return fwd, bwd, None, None, None
        verify = None
        if ROAD_VERIFY:
            def verify(pairs):
                calls = [("edge", a, c, None) for a, c in pairs]
                p = self._pairs
                out = p.map(p.lane_flow, calls) if lanes else [p.lane_flow(c) for c in calls]
                return [f for f, _ in out]
        f, b, use_f, use_b, v, res_f, res_b = self._plane.apply(g0, g1, fwd, bwd, self._K_flow, R, prior, verify,
                                                                defer_backward)
        if v is None or res_f is None:  # (without verification the texture term weighs the plane's pixels too)
            return f, b, v, None, None
        s2 = 2.0 * self._pairs.sigma ** 2

        def weight(res: np.ndarray) -> np.ndarray:
            return np.exp(-res ** 2 / s2).astype(np.float32)

        if defer_backward:
            return f, b, v, (use_f, weight(res_f)), lambda: (use_b, weight(res_b()))
        return f, b, v, (use_f, weight(res_f)), (use_b, weight(res_b))

    def track(self, ref_sid: int, g_ref: np.ndarray, ref_index: int, gray: np.ndarray, frame: Frame, fwd: np.ndarray,
              bwd: np.ndarray, graph) -> tuple[np.ndarray, np.ndarray, RoadMotion, tuple[Plane, Plane]]:
        """The tracking flows of ``frame`` (gray ``gray``) against keyframe ``ref_sid`` (gray ``g_ref``, frame
        ``ref_index``) with the road's: ``(fwd, bwd, road, plane)``; ``road = (R, v)`` for the keyframe chain,
        ``plane`` the directions' road pixels or Nones, the backward one as a function that computes them (its
        verification is needed only if the frame becomes a keyframe).  ``graph``: the last one observed (the
        predicted rotation)."""
        if self._K_flow is None:
            i = frame.intrinsics
            self._K_flow = flow_intrinsics(i.fx, i.fy, i.cx, i.cy, gray.shape[1] / frame.width,
                                           gray.shape[0] / frame.height)
        vel = self._vel if self._vel is not None and self._vel[0] == frame.index - 1 else None
        if vel is None and self._skip > 0:  # backing off: no road for a while, this frame is not searched
            self._skip -= 1
            self._plane.stats["backed_off"] += 1
            return fwd, bwd, (None, None), (None, None)  # no plane motion: the keyframe chain starts anew
        R = self._predicted_rotation(graph, ref_sid, frame.index)
        gap = frame.index - ref_index
        fwd, bwd, v, *plane = self.merge(g_ref, gray, fwd, bwd, R, None if vel is None else vel[1] * gap, lanes=True,
                                         defer_backward=True)
        if v is None and vel is not None:  # the velocity's start did not hold: search from scratch
            fwd, bwd, v, *plane = self.merge(g_ref, gray, fwd, bwd, R, lanes=True, defer_backward=True)
        self._misses = 0 if v is not None else self._misses + 1
        if self._misses >= ROAD_BACKOFF_AFTER:
            self._skip = min(2 ** (self._misses - ROAD_BACKOFF_AFTER), ROAD_BACKOFF_MAX)
        self._vel = None if v is None or gap <= 0 else (frame.index, v / gap)
        # the chain of road poses (RoadChain) bridges a frame without a plane with the velocity's motion
        return fwd, bwd, (R, v if v is not None or vel is None else vel[1] * gap), tuple(plane)

    def pair_inputs(self, graph, ids: list[int], plist: list[tuple[int, int]]) -> tuple[list, list]:
        """Per keyframe pair ``(a, b)`` (graph indices; ``ids`` the graph's stable ids) the map's rotation a -> b
        and the chain's prior plane motion, or None: pairs more than ``ROAD_MAX_GAP`` frames apart get no rotation
        (no plane), and without a prior only pairs a few frames apart share ground rows for a search from scratch."""
        none = [None] * len(plist)
        if self._K_flow is None or not plist:
            return none, none
        a = torch.tensor([p[0] for p in plist], dtype=torch.int64)
        b = torch.tensor([p[1] for p in plist], dtype=torch.int64)
        rots = list(edge_transforms(graph.poses.detach().double().cpu(), a, b)[0].numpy())
        priors = [self._chain.prior(ids[i], ids[j]) for i, j in plist]
        gaps = [abs(self._frames[ids[j]] - self._frames[ids[i]]) for i, j in plist]
        rots = [R if g <= ROAD_MAX_GAP and (pr is not None or g <= 2) else None
                for R, pr, g in zip(rots, priors, gaps)]
        return rots, priors

    # -------------------------------------------------------------------------------------- keyframes --
    def add_keyframe(self, sid: int, frame_index: int, ref_sid: Optional[int] = None,
                     road: Optional[RoadMotion] = None, plane: Plane = None,
                     ba_shape: Optional[tuple[int, int]] = None) -> None:
        """Keyframe ``sid`` joins the chain of road poses through the plane motion ``road`` its tracking against
        ``ref_sid`` found (None: not tracked), and keeps its road pixels ``plane`` (in its own pixels, from the
        tracking's backward direction) pooled to the BA resolution ``ba_shape``."""
        self._frames[sid] = int(frame_index)
        self._chain.add(sid, ref_sid if road is not None else None, *(road or (None, None)))
        if self.cfg.depth_weight > 0 and plane is not None and plane[0] is not None:
            h, w = ba_shape  # block means as the BA targets' (flow_ops.pool_to_ba)
            frac = cv2.resize(plane[0].astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
            wsum = cv2.resize(np.where(plane[0], plane[1], 0).astype(np.float32), (w, h),
                              interpolation=cv2.INTER_AREA)
            keep = frac >= 0.5  # BA pixels mostly road
            if keep.any():
                self._weights[sid] = torch.from_numpy(np.where(keep, wsum / np.maximum(frac, 1e-6), 0.0)
                                                      .astype(np.float32))

    def extend_back(self, sid: int, ref: Optional[int], gray_of: Callable[[int], np.ndarray], graph) -> int:
        """``ROAD_BACKWARD``: when keyframe ``sid`` has just joined its tracking reference ``ref``, the first of a new
        chain, the consecutive keyframes before ``ref`` that begin chains of their own (at most ``ROAD_MAX_GAP``
        frames apart) join it, newest first, each through a search from the chain's velocity with the map's rotation
        (kept only near that prior, as a tracking search from the velocity).  ``gray_of(kf id)``: a keyframe's gray
        image; ``graph``: the map the rotations come from.  Returns how many joined."""
        if not ROAD_BACKWARD or self._vel is None or graph is None or self._K_flow is None:
            return 0
        if ref is None or not (self._chain.first(ref) and self._chain.same(ref, sid)):
            return 0
        order = list(self._frames)  # kf ids in time order
        joined = 0
        for p in reversed(order[:order.index(ref)]):
            gap = self._frames[ref] - self._frames[p]
            if not (0 < gap <= ROAD_MAX_GAP and self._chain.first(p)) or self._chain.same(p, ref):
                break
            try:
                R = self._rotation(graph, graph.index_of(p), graph.index_of(ref))
            except KeyError:  # not in the map (anymore)
                break
            prior = self._vel[1] * gap
            found = self._plane.search(gray_of(p), gray_of(ref), self._K_flow, R, prior)
            if found is None or not self._plane.near_prior(found[0], prior):
                break
            self._chain.prepend(p, ref, R, found[0])
            joined, ref = joined + 1, p
        if joined:
            LOG.info("road plane: %d earlier keyframes joined the road's chain backwards", joined)
        return joined

    def remove_keyframe(self, kf_id: int) -> None:
        self._frames.pop(kf_id, None)
        self._chain.remove(kf_id)
        self._weights.pop(kf_id, None)

    # ----------------------------------------------------------------------------------------- priors --
    def depth_prior(self, graph, idx: torch.Tensor) -> Optional[DepthPrior]:
        """:meth:`Frontend.depth_prior`: the road's inverse depth ``(y - cy) / (fy h)`` and its weight
        ``alpha0 w / dp^2`` (``w``: the road pixels' verification weight) for graph keyframes ``idx``, once the
        camera height ``h`` is known (measured here, :meth:`_camera_height`); None before, or with no road pixels
        among ``idx``."""
        if self.cfg.depth_weight <= 0 or not self._weights:
            return None
        ids = graph.ids.tolist()
        h, w = (int(v) for v in graph.ba_shape)
        fx, fy, cx, cy = (float(v) for v in graph.intrinsics.cpu())
        ray = ((torch.arange(h, dtype=torch.float32) - cy) / fy)[:, None].expand(h, w)  # (y - cy) / fy
        if self.height is None:
            self.height = self._camera_height(graph, ids, ray)
            if self.height is None:
                return None
        road = [self._weights.get(ids[k]) for k in idx.tolist()]
        if all(r is None for r in road):
            return None
        dp = ray.clamp(min=0.0) / self.height  # [h, w] the road's inverse depth
        # alpha0 (d - dp)^2 / dp^2: a relative error, so the weight against the flow's terms does not depend on the
        # map's scale (the flow's depth curvature grows with the squared baseline)
        rel = torch.where(ray > 0, self.cfg.depth_weight / dp.clamp(min=1e-6) ** 2, torch.zeros_like(dp))
        zero = torch.zeros(h, w)
        alpha = torch.stack([zero if r is None else rel * r for r in road])
        dev = graph.disps.device
        return DepthPrior(idx, dp.expand(len(road), h, w).contiguous().to(dev), alpha.to(dev))

    def distance_prior(self, graph, idx: torch.Tensor) -> Optional[DistancePrior]:
        """:meth:`Frontend.distance_prior`: consecutive keyframes among ``idx`` tracked over the road get the
        distance ``h |v|`` (``v``: the road's translation between them in camera heights, chained from the
        tracking's plane motions; ``h``: the camera height in map units from the map's motion over the road's,
        measured once, :meth:`_road_motion`) with weight ``road.distance_weight``.  On a highway the near road,
        whose flow tells the speed, has left the view by the next keyframe: the BA's edges cannot hold the scale
        there, the frame-to-frame plane motions can (pvslam_core/geometry/ba_distance.py)."""
        if self.cfg.distance_weight <= 0:
            return None
        ids = graph.ids.tolist()
        if self.height_motion is None:
            got = self._road_motion(graph, ids, road_pixels=False, lookback=ROAD_DIST_LOOKBACK)
            if got is None:
                return None
            ratio = got[1] / np.maximum(got[2], 1e-12)  # each pair's height: map translation / road translation
            if not (np.isfinite(ratio).all() and ratio.min() > 0) or ratio.max() / ratio.min() > ROAD_DIST_CONSISTENT:
                return None  # the three pairs do not tell one height (a turn on the spot, a wrong plane): not yet
            self.height_motion = float(got[1].sum() / got[2].sum())
            LOG.info("road plane: distance prior at a camera height of %.4g map units (keyframes %s)",
                     self.height_motion, got[0])
        ks = sorted(set(idx.tolist()))
        pairs, dist = [], []
        for a, b in zip(ks[:-1], ks[1:]):
            v = self._chain.prior(ids[a], ids[b]) if b == a + 1 else None
            size = 0.0 if v is None else float(np.linalg.norm(v))  # camera heights
            if size > 1e-9:
                pairs.append((a, b))
                dist.append(self.height_motion * size)
        if not pairs:
            return None
        ii = torch.tensor([p[0] for p in pairs], dtype=torch.int64)
        jj = torch.tensor([p[1] for p in pairs], dtype=torch.int64)
        L = torch.tensor(dist, dtype=torch.float64)
        # a pair whose road distance and the map's current one disagree beyond ROAD_DIST_AGREE is left out: the
        # plane's motion is wrong there (a head camera's floor during a fast turn), not the map by that much
        c = graph.poses.detach()[torch.cat([ii, jj]).to(graph.poses.device), :3].double().cpu()  # camera centres
        now = (c[: len(pairs)] - c[len(pairs):]).norm(dim=-1)
        keep = (now > 0) & ((now / L).log().abs() <= float(np.log(ROAD_DIST_AGREE)))
        if not bool(keep.any()):
            return None
        L = L[keep]
        return DistancePrior(ii[keep], jj[keep], L, torch.full_like(L, self.cfg.distance_weight))

    def _camera_height(self, graph, ids: list[int], ray: torch.Tensor) -> Optional[float]:
        """The camera height in map units, or None while the map cannot tell it: over the newest ``ROAD_H_KEYFRAMES``
        keyframes with road pixels and a plane motion from the keyframe before them that are at least
        ``ROAD_H_SETTLE`` keyframes older than the newest, measured twice - from their road pixels' inverse depth
        (``(y - cy) / (fy d)``) and from the map's translation over the road's (in camera heights) between them -
        and accepted only when the two agree within ``ROAD_H_AGREE``: where DIS misjudges the near road, the map's
        road depth and its motion disagree, and a prior at either height would pull the map apart.  Accepted, the
        height is their geometric mean, or the distance prior's height when that one was measured first."""
        got = self._road_motion(graph, ids, road_pixels=True)
        if got is None:
            return None
        ks, t, v = got
        by_depth = []
        for k in ks:
            m = (self._weights[ids[k]] > 0.5) & (ray > 0)
            d = graph.disps[k].detach().float().cpu()[m]
            ok = torch.isfinite(d) & (d > 0)
            if int(ok.sum()) >= 8:
                by_depth.append(float((ray[m][ok] / d[ok]).median()))
        if len(by_depth) < len(ks) or not (np.isfinite(t).all() and np.isfinite(v).all()) or t.sum() <= 0 \
                or v.sum() <= 0:
            return None
        h_motion, h_depth = float(t.sum() / v.sum()), float(np.median(by_depth))
        self.height_tries.append((len(ids), h_motion, h_depth))
        self._height_n += 1
        if not abs(np.log(h_motion / h_depth)) <= np.log(ROAD_H_AGREE):
            return None
        # one camera height per map: the distance prior's when it was measured first (module docstring)
        hgt = float(np.sqrt(h_motion * h_depth)) if self.height_motion is None else self.height_motion
        LOG.info("road plane: camera height %.4g map units (%s; keyframes %s: %.4g from the motion, %.4g from the "
                 "road depth; %d tries)", hgt, "the mean" if self.height_motion is None else "the distance prior's",
                 ks, h_motion, h_depth, self._height_n)
        return hgt

    def _road_motion(self, graph, ids: list[int], road_pixels: bool,
                     lookback: Optional[int] = None) -> Optional[tuple[list[int], np.ndarray, np.ndarray]]:
        """The newest ``ROAD_H_KEYFRAMES`` keyframes ``k`` (graph indices, at least ``ROAD_H_SETTLE`` older than the
        newest, and with ``lookback`` among that many newest; with ``road_pixels`` only those with verified road
        pixels) with a plane motion from keyframe ``k - 1``: ``(ks, |t| [m] the map's translation k-1 -> k, |v| [m]
        the road's in camera heights)``, or None while there are not that many."""
        n = len(ids)
        # from the newest settled keyframe back: this runs on every BA call while unmeasured, so it does not walk
        # the whole map
        motion: dict[int, np.ndarray] = {}
        stop = 0 if lookback is None else max(0, n - lookback)
        for k in range(n - ROAD_H_SETTLE - 1, stop, -1):
            if not road_pixels or ids[k] in self._weights:
                mk = self._chain.prior(ids[k - 1], ids[k])
                if mk is not None:
                    motion[k] = mk
                    if len(motion) == ROAD_H_KEYFRAMES:
                        break
        if len(motion) < ROAD_H_KEYFRAMES:
            return None
        ks = sorted(motion)
        pairs = graph.poses[[k - 1 for k in ks] + ks].detach().double().cpu()  # only these (not every pose)
        m = len(ks)
        t = edge_transforms(pairs, torch.arange(m), torch.arange(m, 2 * m))[1].norm(dim=-1).numpy()
        v = np.array([np.linalg.norm(motion[k]) for k in ks])
        return ks, t, v

    def _predicted_rotation(self, graph, last_sid: int, index: int) -> np.ndarray:
        """Rotation ``[3, 3]`` from the last keyframe's camera to frame ``index``'s, predicted at the rate between
        the last two keyframes of the graph (identity before there are two)."""
        known: list[tuple[int, int]] = []  # the newest two keyframes still in the graph: (id, graph index)
        for s in (reversed(self._frames) if graph is not None else ()):
            try:
                known.append((s, graph.index_of(s)))
            except KeyError:
                continue
            if len(known) == 2:
                break
        if len(known) < 2 or known[0][0] != last_sid:
            return np.eye(3)
        (b, ib), (a, ia) = known
        gap = self._frames[b] - self._frames[a]
        if gap <= 0:
            return np.eye(3)
        rvec = cv2.Rodrigues(self._rotation(graph, ia, ib))[0] * ((index - self._frames[b]) / gap)
        return cv2.Rodrigues(rvec)[0]


class _MapRotation:
    """The map's rotation ``[3, 3]`` from keyframe ``ia``'s camera to ``ib``'s (graph indices; only these two poses are
    copied: a copy of every pose would cost O(N) a frame), recomputed only when the two poses differ from the last
    call's (between keyframes the map does not move); the array it returns is shared: read-only."""

    def __init__(self) -> None:
        self._last: Optional[tuple[bytes, np.ndarray]] = None

    def __call__(self, graph, ia: int, ib: int) -> np.ndarray:
        two = graph.poses[[ia, ib]].detach().cpu()
        key = two.numpy().tobytes()
        if self._last is None or self._last[0] != key:
            rot = edge_transforms(two.double(), torch.tensor([0]), torch.tensor([1]))[0][0].numpy()
            rot.setflags(write=False)
            self._last = (key, rot)
        return self._last[1]
