"""Map initialisation of a fragment: which keyframe pairs are tried, and how the fragment's keyframes are placed.

Before, the two-view initialisation paired the fragment's *first* keyframe with the newest ones only.  A hand-held
camera that turns away from where it started never overlaps that keyframe again: on the synthetic room (seed 5)
the map initialised after 19.8 s, when the camera came back.  Here the first view of a pair slides with the
newest keyframe ``k``: ``a = max(first, k - init_window)`` and the pairs ``(a, k)``, ``((a + k) // 2, k)`` and
``(k - 2, k)`` are tried (``init_tries`` of them), the farthest first (the most parallax), the nearest last: a
turning hand-held camera (synthetic room, tune seed 1, a keyframe every ~3 frames at 15 fps) shares no confident
flow with a keyframe 4 back, and with ``(a, k - 1)`` as the third try instead of ``(k - 2, k)`` it never
initialised.  Each try goes through the model selection of :func:`~.initializer.two_view_init_why` (homography or
essential matrix).

When a pair ``(a, m)`` initialises: keyframe ``a`` gets the triangulated depth, ``m`` the two-view pose; the
keyframes after ``a`` are interpolated / extrapolated in time between ``a`` and ``m`` (the window BA that follows
refines them); those before ``a`` (the camera turned, they no longer overlap ``m``) are placed by motion-only BA
against ``a`` from their own flow to it, else left at ``a``'s pose.

Pairs are tried once ``warmup`` keyframes are collected, or at least 3 that span ``warmup_seconds`` of video: a
slow camera over a textureless room makes keyframes rarely (indoor_textureless, tune seed 1: at 0, 0.17, 0.37, 0.67
and 1.37 s), and the 5th came up to 2.1 s into the motion; on the 10-12 frames/s driving sequences (a keyframe every
~2 frames) the count comes first, as before.

A pair more than one keyframe apart is checked against its links, the pairs of consecutive keyframes between it,
chained (:func:`chain_checked`, ``graph.init_chain_tol``).  When its own flow keeps too few confident
correspondences, the chained links give them instead (:func:`chain_follow`, ``graph.init_chain_fallback``): before
the map exists nothing starts a far pair's flow from the motion, and DIS from zero finds a few tens of pixels at
most.  Through a 45 deg lens a hand-held camera (synthetic room, seed 147, 15 fps) moves the image 1.4x as far as
through the default 61 deg one: every pair two or more keyframes apart came back with 0-69 confident pixels while
each link had 400-660; the map started 27 frames in, on keyframes 7-9, 22 deg / 61 deg off (rotation / direction
of motion), and the run ended at 3.9 % of the path (0.1 % with the chained links; bench/RESULTS.md, 12-04 e).

While it cannot initialise, the reason is printed (INFO) about once per second of video, so a user sees why (too
little parallax, no overlap, too few points in front of the cameras) while it keeps trying.  Poses are T_wc.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Optional

import torch

from ..geometry.lie import se3_interpolate, se3_mul
from .initializer import TwoViewInit, confident_mask, two_view_init_why

if TYPE_CHECKING:  # pragma: no cover
    from .mapper import Mapper

LOG = logging.getLogger("pvslam")


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
    from ..geometry.projective import pixel_grid
    from .initializer import confidence_threshold

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

    Why: a direct flow between views far apart matches what has left the view too.  On a fast forward drive
    (highway, 23 m/s, frames 0-5) the near road is behind the camera by the pair's second view, yet DIS matches it to
    the road still in view, forward-backward consistent: 255 of the 321 confident correspondences of the highway's
    init pair (unseen seed 69) had no true match, and the cheirality test then favoured sideways or reversed motions
    (bench/RESULTS.md, 12-03 g).  Each short link keeps most of its pixels in view and the chain follows them out."""
    pos, ok, _ = chain_follow(chain_target, chain_weight, relative_weight)
    ok &= (target.float() - pos).norm(dim=0) <= tol
    return weight * ok[None].to(weight.dtype)


INIT_MIN_INLIERS = 60  # confident correspondences a pair needs (two_view_init_why's min_inliers)


class Bootstrap:
    """Initialises the mapper's current fragment (``Mapper._try_initialise`` delegates here)."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg  # GraphSection
        self.last_reason = ""
        self._said_at: Optional[float] = None  # timestamp of the last "not initialised yet" message

    def try_initialise(self, mapper: "Mapper", k: int) -> bool:
        g = mapper.graph
        first = mapper.fragment_start
        if not self.warmed_up(mapper, k):
            return False
        init, pair, reasons = None, None, []
        for a, m in init_pairs(first, k, self.cfg.init_window, self.cfg.init_tries):
            obs = mapper._observe(torch.tensor([a]), torch.tensor([m]))
            mapper._release_pairs(torch.tensor([a]), torch.tensor([m]))  # not an edge: not observed again
            target, weight = obs.target[0], obs.weight[0]
            if self.cfg.init_chain_tol > 0 and m - a > 1:
                # the pairs between are odometry edges: observed now, before the map exists, their flows must not
                # stay cached (the window BA's first observation starts them from the map's poses)
                ii, jj = torch.arange(a, m, device=g.device), torch.arange(a + 1, m + 1, device=g.device)
                chain = mapper.frontend.observe(g, ii, jj)
                mapper.frontend.discard_pairs(g.ids[ii], g.ids[jj])
                weight = chain_checked(target, weight, chain.target, chain.weight, self.cfg.init_chain_tol,
                                       self.cfg.init_relative_confidence)
                if (self.cfg.init_chain_fallback
                        and int(confident_mask(target, weight, self.cfg.init_relative_confidence).sum())
                        < INIT_MIN_INLIERS):
                    # the direct flow lost the pair (DIS from zero, no map yet to start it from): its links did not
                    pos, ok, conf = chain_follow(chain.target, chain.weight, self.cfg.init_relative_confidence,
                                                 land_in_view=True)
                    if int(ok.sum()) >= INIT_MIN_INLIERS:
                        target, weight = pos.to(target.dtype), conf[None].expand(2, -1, -1).to(weight.dtype)
            init, why = two_view_init_why(target, weight, g.intrinsics, min_inliers=INIT_MIN_INLIERS,
                                          min_parallax_deg=self.cfg.init_min_parallax_deg,
                                          relative_weight=self.cfg.init_relative_confidence,
                                          parallax_quantile=self.cfg.init_parallax_quantile,
                                          ambiguity_ratio=self.cfg.init_ambiguity_ratio or None,
                                          tie_ratio=self.cfg.init_tie_ratio or None)
            if init is not None:
                pair = (a, m)
                break
            reasons.append(f"pair {a}-{m}: {why}")
        if init is None:
            self._say(mapper, k, "; ".join(reasons))
            return False
        self._place(mapper, k, pair, init)
        LOG.info("map initialised with keyframes %d..%d (pair %d-%d, %s model: %d inliers, parallax %.2f deg)",
                 first, k, pair[0], pair[1], init.model, init.inliers, init.parallax_deg)
        self._said_at = None
        return True

    def warmed_up(self, mapper: "Mapper", k: int) -> bool:
        """Enough keyframes to try: ``warmup`` of them, or at least 3 spanning ``warmup_seconds`` of video."""
        count = k - mapper.fragment_start + 1
        if count >= self.cfg.warmup:
            return True
        if count < 3 or self.cfg.warmup_seconds <= 0:
            return False
        ts = mapper.graph.timestamps
        return float(ts[k] - ts[mapper.fragment_start]) >= self.cfg.warmup_seconds

    def _say(self, mapper: "Mapper", k: int, reason: str) -> None:
        g = mapper.graph
        self.last_reason = reason
        now = float(g.timestamps[k])
        if self._said_at is None or now - self._said_at >= 1.0:
            span = now - float(g.timestamps[mapper.fragment_start])
            LOG.info("map not initialised yet (keyframes %d..%d, %.1f s of video); still trying. %s",
                     mapper.fragment_start, k, span, reason)
            self._said_at = now

    def _place(self, mapper: "Mapper", k: int, pair: tuple[int, int], init: TwoViewInit) -> None:
        """Poses and depths of the fragment's keyframes from the two-view result of ``pair``."""
        g = mapper.graph
        first = mapper.fragment_start
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
            obs = mapper._observe(torch.tensor([a]), torch.tensor([j]))
            mapper._release_pairs(torch.tensor([a]), torch.tensor([j]))
            pose = None
            # clone: .double().cpu() of a float64 CPU graph is a view, and writing a view of poses[j + 1] into
            # poses[j] is an overlapping in-place write (torch refuses it)
            nxt = g.poses[j + 1].double().cpu().clone()
            if float(obs.weight[0].mean()) > 0.2:
                pose = mapper.frames.motion_only(nxt.clone(), g.poses[a].double(), g.disps[a],
                                                 g.intrinsics, obs.target[0], obs.weight[0])
            g.set_poses(torch.tensor([j]), (pose if pose is not None else nxt)[None])
