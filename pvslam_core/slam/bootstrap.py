"""Map initialisation of a fragment: which keyframe pairs are tried, and how the fragment's keyframes are placed.

The first view of a pair slides with the newest keyframe ``k``: ``a = max(first, k - INIT_WINDOW)`` and the pairs
``(a, k)``, ``((a + k) // 2, k)`` and ``(k - 2, k)`` are tried (``INIT_TRIES`` of them), the farthest first (the most
parallax), the nearest last.  A hand-held camera that turns away from where it started never overlaps the
fragment's first keyframe again, and a turning camera may share no confident flow with a keyframe a few back
(docs/decisions.md: INIT_WINDOW).  Each try goes through the model selection of
:func:`~.initializer.two_view_init_why` (homography or essential matrix).

When a pair ``(a, m)`` initialises: keyframe ``a`` gets the triangulated depth, ``m`` the two-view pose; the
keyframes after ``a`` are interpolated / extrapolated in time between ``a`` and ``m`` (the window BA that follows
refines them); those before ``a`` (the camera turned, they no longer overlap ``m``) are placed by motion-only BA
against ``a`` from their own flow to it, else left at ``a``'s pose.

Pairs are tried once ``graph.init.warmup`` keyframes are collected, or at least 3 that span ``WARMUP_SECONDS`` of
video: a slow camera over a textureless room makes keyframes rarely, while a driving camera collects the count first
(docs/decisions.md: WARMUP_SECONDS).

A pair more than one keyframe apart is checked against its links, the pairs of consecutive keyframes between it,
chained (:func:`chain_checked`, ``CHAIN_TOL``).  When its own flow keeps too few confident correspondences, the
chained links give them instead (:func:`chain_follow`, ``CHAIN_FALLBACK``): before the map exists nothing starts a
far pair's flow from the motion, and DIS from zero finds a few tens of pixels at most, while each link is fine
(docs/decisions.md: CHAIN_FALLBACK).

While it cannot initialise, the reason is printed (INFO) about once per second of video, so a user sees why (too
little parallax, no overlap, too few points in front of the cameras) while it keeps trying.  Poses are T_wc.
"""
from __future__ import annotations

import logging
from typing import Optional

import torch

from ..geometry.lie import se3_interpolate, se3_mul
from ..geometry.projective import pixel_grid
from .config import InitConfig
from .initializer import TwoViewInit, TwoViewOptions, confidence_threshold, confident_mask, two_view_init_why
from .map_state import MapState
from .observe import EdgeObserver

LOG = logging.getLogger("pvslam")

WARMUP_SECONDS = 0.65  # ... or at least 3 keyframes spanning this many seconds (docs/decisions.md: WARMUP_SECONDS)
INIT_WINDOW = 8  # the first view of a pair is at most this many keyframes before the newest
INIT_TRIES = 3  # pairs tried per new keyframe, all ending at the newest (docs/decisions.md: INIT_WINDOW)
# a chained pair keeps a correspondence only where its links' chained flows land within this many BA px of it (0: no
# chain check; docs/decisions.md: CHAIN_TOL)
CHAIN_TOL = 1.0
# a pair whose direct flow lost its pixels takes its chained links' instead (docs/decisions.md: CHAIN_FALLBACK)
CHAIN_FALLBACK = True
# a correspondence is confident relative to the pair's own high weights (initializer.confidence_threshold), not above
# a fixed 0.5 (docs/decisions.md: RELATIVE_CONFIDENCE)
RELATIVE_CONFIDENCE = True
PARALLAX_QUANTILE = 0.75  # graph.init.min_parallax_deg holds at this quantile (docs/decisions.md: PARALLAX_QUANTILE)
AMBIGUITY_RATIO = 3.0  # two_view_init_why's ambiguity_ratio (docs/decisions.md: AMBIGUITY_RATIO)
TIE_RATIO = 1.25  # two_view_init_why's tie_ratio (docs/decisions.md: TIE_RATIO)
INIT_MIN_INLIERS = 60  # confident correspondences a pair needs (two_view_init_why's min_inliers)
SAY_EVERY_S = 1.0  # "not initialised yet" is printed at most once per this many seconds of video


def init_pairs(first: int, k: int, window: int, tries: int) -> list[tuple[int, int]]:
    """Keyframe pairs ``(a, m)`` tried at keyframe ``k`` (see the module docstring), at most ``tries``, distinct,
    with ``a < m``."""
    a = max(first, k - window)
    cands = [(a, k), ((a + k) // 2, k), (k - 2, k), (a, k - 1), (k - 1, k)]
    out: list[tuple[int, int]] = []
    for p in cands:
        if a <= p[0] < p[1] and p not in out:
            out.append(p)
    return out[:tries]


def chain_follow(chain_target: torch.Tensor, chain_weight: torch.Tensor, relative_weight: bool,
                 land_in_view: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each view-``a`` pixel followed along the chained pairs (``chain_target`` / ``chain_weight`` ``[E, 2, h, w]``:
    a -> a+1, ..., m-1 -> m, BA px): ``(pos [2, h, w], ok [h, w], conf [h, w])``, where it lands in view ``m``,
    whether every link started in view and was confident about it (initializer.confidence_threshold) -- and, with
    ``land_in_view``, whether it lands in view ``m`` too -- and the least confidence of its links (0 where not ok)."""
    h, w = chain_target.shape[-2:]
    pos = pixel_grid(h, w, chain_target.device).permute(2, 0, 1)  # [2, h, w] where each view-a pixel is, link by link
    ok = torch.ones(h, w, dtype=torch.bool, device=chain_target.device)
    conf = torch.ones(h, w, device=chain_target.device)
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], device=chain_target.device)

    def in_view(p: torch.Tensor) -> torch.Tensor:
        return (p[0] >= -1e-3) & (p[0] <= w - 1 + 1e-3) & (p[1] >= -1e-3) & (p[1] <= h - 1 + 1e-3)

    for t_e, w_e in zip(chain_target, chain_weight):
        ok &= in_view(pos)
        grid = (pos.permute(1, 2, 0) * scale - 1.0)[None]  # [1, h, w, 2] in grid_sample's [-1, 1]
        w_min = w_e.min(0).values.float()  # [h, w]
        thr = confidence_threshold(w_min.cpu().numpy(), relative_weight)
        # the link's target (x, y) and confidence at each pixel's current position, one bilinear sample
        at = torch.nn.functional.grid_sample(torch.cat([t_e.float(), w_min[None]])[None], grid, align_corners=True)[0]
        t_at, w_at = at[:2], at[2]
        ok &= (w_at > thr) & torch.isfinite(t_at).all(0)
        pos = torch.where(ok[None], t_at, pos)
        conf = torch.minimum(conf, w_at)
    if land_in_view:
        ok &= in_view(pos)
    return pos, ok, torch.where(ok, conf, torch.zeros_like(conf))


def chain_checked(target: torch.Tensor, weight: torch.Tensor, chain_target: torch.Tensor, chain_weight: torch.Tensor,
                  tol: float, relative_weight: bool) -> torch.Tensor:
    """``weight`` ``[2, h, w]`` of a pair's correspondences ``target`` (view-``a`` pixels in view ``m``, BA px) with 0
    where the pairs between, chained (``chain_target`` / ``chain_weight`` ``[E, 2, h, w]``: a -> a+1, ..., m-1 -> m),
    leave the view, pass a pixel they are not confident about (initializer.confidence_threshold) or land more than
    ``tol`` BA px from it.

    Why: a direct flow between views far apart matches what has left the view too.  On a fast forward drive the
    near road is behind the camera by the pair's second view, yet DIS matches it to the road still in view,
    forward-backward consistent, and the cheirality test then favours sideways or reversed motions.  Each short link
    keeps most of its pixels in view and the chain follows them out (docs/decisions.md: CHAIN_TOL)."""
    pos, ok, _ = chain_follow(chain_target, chain_weight, relative_weight)
    ok &= (target.float() - pos).norm(dim=0) <= tol
    return weight * ok[None].to(weight.dtype)


class Bootstrap:
    """Initialises the current map fragment (see the module docstring)."""

    def __init__(self, cfg: InitConfig, state: MapState, observer: EdgeObserver, frontend) -> None:
        self.cfg = cfg
        self.state = state
        self.observer = observer
        self.frontend = frontend
        self.last_reason = ""
        self._said_at: Optional[float] = None  # timestamp of the last "not initialised yet" message

    def options(self) -> TwoViewOptions:
        """How a pair's motion is chosen and checked."""
        return TwoViewOptions(min_inliers=INIT_MIN_INLIERS, min_parallax_deg=self.cfg.min_parallax_deg,
                              relative_weight=RELATIVE_CONFIDENCE, parallax_quantile=PARALLAX_QUANTILE,
                              ambiguity_ratio=AMBIGUITY_RATIO or None, tie_ratio=TIE_RATIO or None)

    def try_initialise(self, k: int) -> bool:
        """Try the pairs ending at the newest keyframe ``k`` (graph index); on success the fragment's keyframes are
        placed and True is returned."""
        first = self.state.fragment_start
        if not self.warmed_up(k):
            return False
        init, pair, reasons = None, None, []
        for a, m in init_pairs(first, k, INIT_WINDOW, INIT_TRIES):
            target, weight = self._correspondences(a, m)
            init, why = two_view_init_why(target, weight, self.state.graph.intrinsics, self.options())
            if init is not None:
                pair = (a, m)
                break
            reasons.append(f"pair {a}-{m}: {why}")
        if init is None:
            self._say(k, "; ".join(reasons))
            return False
        self._place(k, pair, init)
        LOG.info("map initialised with keyframes %d..%d (pair %d-%d, %s model: %d inliers, parallax %.2f deg)",
                 first, k, pair[0], pair[1], init.model, init.inliers, init.parallax_deg)
        self._said_at = None
        return True

    def _correspondences(self, a: int, m: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(target, weight)`` ``[2, h, w]`` of pair ``(a, m)``: its direct flow, checked against its chained links
        (and replaced by them when the direct flow lost the pair)."""
        g = self.state.graph
        obs = self.observer.observe_pair(a, m)  # not an edge: not observed again
        target, weight = obs.target[0], obs.weight[0]
        if CHAIN_TOL > 0 and m - a > 1:
            # the pairs between are odometry edges: observed now, before the map exists, their flows must not stay
            # cached (the window BA's first observation starts them from the map's poses)
            ii, jj = torch.arange(a, m, device=g.device), torch.arange(a + 1, m + 1, device=g.device)
            chain = self.frontend.observe(g, ii, jj)
            self.frontend.discard_pairs(g.ids[ii], g.ids[jj])
            weight = chain_checked(target, weight, chain.target, chain.weight, CHAIN_TOL, RELATIVE_CONFIDENCE)
            if CHAIN_FALLBACK and int(confident_mask(target, weight, RELATIVE_CONFIDENCE).sum()) < INIT_MIN_INLIERS:
                # the direct flow lost the pair (DIS from zero, no map yet to start it from): its links did not
                pos, ok, conf = chain_follow(chain.target, chain.weight, RELATIVE_CONFIDENCE, land_in_view=True)
                if int(ok.sum()) >= INIT_MIN_INLIERS:
                    target, weight = pos.to(target.dtype), conf[None].expand(2, -1, -1).to(weight.dtype)
        return target, weight

    def warmed_up(self, k: int) -> bool:
        """Enough keyframes to try: ``warmup`` of them, or at least 3 spanning ``WARMUP_SECONDS`` of video."""
        first = self.state.fragment_start
        count = k - first + 1
        if count >= self.cfg.warmup:
            return True
        if count < 3 or WARMUP_SECONDS <= 0:
            return False
        ts = self.state.graph.timestamps
        return float(ts[k] - ts[first]) >= WARMUP_SECONDS

    def _say(self, k: int, reason: str) -> None:
        g = self.state.graph
        self.last_reason = reason
        now = float(g.timestamps[k])
        if self._said_at is None or now - self._said_at >= SAY_EVERY_S:
            first = self.state.fragment_start
            span = now - float(g.timestamps[first])
            LOG.info("map not initialised yet (keyframes %d..%d, %.1f s of video); still trying. %s",
                     first, k, span, reason)
            self._said_at = now

    def _place(self, k: int, pair: tuple[int, int], init: TwoViewInit) -> None:
        """Poses and depths of the fragment's keyframes from the two-view result of ``pair``."""
        g = self.state.graph
        first = self.state.fragment_start
        a, m = pair
        dev = g.disps.device
        t_a = g.poses[a].double().cpu()
        pose_m = se3_mul(t_a, init.pose_wc)
        ts = g.timestamps.double().cpu()
        span = float(ts[m] - ts[a]) or 1.0
        idx = torch.arange(a + 1, k + 1)
        alpha = ((ts[idx] - ts[a]) / span).clamp(min=0)  # > 1 (constant-velocity extrapolation) after m
        g.set_poses(idx, se3_interpolate(t_a.expand(len(idx), 7), pose_m.expand(len(idx), 7), alpha))
        disp_a = init.disp0.to(dev)
        g.set_disps(torch.tensor([a]), disp_a[None])
        med = float(disp_a.median())
        rest = torch.tensor([j for j in range(first, k + 1) if j != a], dtype=torch.int64)
        if len(rest):
            g.set_disps(rest, torch.full((len(rest),) + tuple(g.ba_shape), med, device=dev))
        for j in range(a - 1, first - 1, -1):  # keyframes before the pair: their own flow to `a`
            obs = self.observer.observe_pair(a, j)
            pose = None
            # clone: .double().cpu() of a float64 CPU graph is a view, and writing a view of poses[j + 1] into
            # poses[j] is an overlapping in-place write (torch refuses it)
            nxt = g.poses[j + 1].double().cpu().clone()
            if float(obs.weight[0].mean()) > 0.2:
                pose = self.state.frames.motion_only(nxt.clone(), g.poses[a].double(), g.disps[a],
                                                     g.intrinsics, obs.target[0], obs.weight[0])
            g.set_poses(torch.tensor([j]), (pose if pose is not None else nxt)[None])
