"""The road's flow from a direct search of the ground plane's homography (``road.enabled``; its use: road_prior.py).

Why: DIS is a patch matcher started at its coarsest pyramid level, and the near road of a car camera at speed is
magnified and sheared between two views, has fine texture that vanishes at coarse levels, and moves tens of pixels:
DIS settles on a small, wrong, self-consistent flow there.  That road is the one scale reference of a low-parallax
forward drive (docs/decisions.md: frontend.road.enabled).

The ground ahead of a car camera is a plane whose normal is (close to) the camera's y axis, so its flow is the
homography ``H = K (R + v n^T) K^-1`` with ``n = (0, 1, 0)``, ``R`` the rotation between the views (from the
map) and ``v = t / h`` (translation over the camera height): three unknowns.  They are found by brute force, not by
gradients (the fine texture gives a basin of about a pixel): a grid over the size and direction of ``v`` on every
4th pixel of the rows well below the principal point (``region``), then a pattern search on every 2nd pixel, each
candidate scored by the mean absolute brightness difference over the pixels that stay in view.  A pair far apart
has no near road left in common; there the search starts from a ``prior`` (the plane motions of the frames in
between, chained: :class:`RoadChain`) and covers the rows from just below the horizon.  The plane is kept only
when it explains its rows better than DIS's flow, and then, per pixel, the flow that explains a 5x5 window better
(plane or DIS, with a ``margin``) is kept: what is not road (cars, barriers, the floor of a tilted hand-held
camera, where the plane model is wrong) keeps DIS's flow.

Pixel conventions as flow_ops (centres at integer coordinates); ``K`` is at the flow resolution.
"""
from __future__ import annotations

import functools
from typing import Callable, Optional

import cv2
import numpy as np

from . import flow_ops as F

_N = np.array([0.0, 1.0, 0.0])  # ground normal in the camera frame (x right, y down, z forward)
_REMAP_MAX = 32766  # cv2.remap asserts that each side of its maps is below SHRT_MAX
_COST_BLOCK = 1 << 24  # candidates x pixels scored at once: bounds the search's memory on very large frames
_OFFS = np.concatenate([np.eye(3), -np.eye(3)])  # the pattern search's neighbours


def flow_intrinsics(fx: float, fy: float, cx: float, cy: float, sx: float, sy: float) -> np.ndarray:
    """``K [3, 3]`` of an image resized by ``(sx, sy)`` (pixel centres kept: ``c' = (c + 0.5) s - 0.5``)."""
    return np.array([[fx * sx, 0.0, (cx + 0.5) * sx - 0.5], [0.0, fy * sy, (cy + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])


def _kernels():
    """:mod:`.road_kernels`, imported on first use: numba loads there, not when the plugins register."""
    from . import road_kernels

    return road_kernels


def _warp(g1: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``g1`` seen from the first view through ``flow`` (``g1(x + f(x))``, uint8; flow_ops' cached pixel grid)."""
    pos = cv2.add(F._grids(*g1.shape)[2], flow)
    return cv2.remap(g1, pos, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _remap(src: np.ndarray, mx: np.ndarray, my: np.ndarray, border: int) -> np.ndarray:
    """``cv2.remap`` (bilinear; outside: 0 for BORDER_CONSTANT) of maps of any width: maps wider than OpenCV takes
    (a very large frame's search) go in column blocks; each output pixel depends on its own map entry only."""
    if mx.shape[1] <= _REMAP_MAX:
        return cv2.remap(src, mx, my, cv2.INTER_LINEAR, borderMode=border, borderValue=0.0)
    return np.concatenate([cv2.remap(src, np.ascontiguousarray(mx[:, i:i + _REMAP_MAX]),
                                     np.ascontiguousarray(my[:, i:i + _REMAP_MAX]), cv2.INTER_LINEAR,
                                     borderMode=border, borderValue=0.0)
                           for i in range(0, mx.shape[1], _REMAP_MAX)], 1)


@functools.lru_cache(maxsize=8)
def _pixels64(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read-only float64 pixel grids ``ys, xs [h, w]`` and ``(x, y, 1) [3, h, w]`` (plane_flow's, per frame size)."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    P = np.stack([xs, ys, np.ones_like(xs)])
    for a in (ys, xs, P):
        a.setflags(write=False)
    return ys, xs, P


def homography(K: np.ndarray, R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The ground plane's homography ``K (R + v n^T) K^-1`` (pixels of the first view -> the second)."""
    return K @ (R + np.outer(v, _N)) @ np.linalg.inv(K)


class RoadPlane:
    """Search of ``v``, the acceptance test and the per-pixel merge (module docstring).

    ``region``: a search from scratch covers the rows from ``cy + region * H``, ``horizon``: a search from a prior
    those from ``cy + horizon * H`` (the plane's flow is merged on the rows its search covered); ``margin``: a pixel
    takes the plane's flow where its local residual is below ``margin`` x DIS's; ``min_inside``: the least share of
    the searched pixels that must stay in view; ``prior_tol``: how far (relative) a search may leave its prior."""

    def __init__(self, region: float = 0.15, margin: float = 0.9, horizon: float = 0.03, min_inside: float = 0.08,
                 window: int = 5, starts: int = 3, prior_tol: float = 0.25):
        self.region, self.margin, self.horizon = float(region), float(margin), float(horizon)
        self.min_inside, self.window, self.starts = float(min_inside), int(window), int(starts)
        self.prior_tol = float(prior_tol)
        self.stats = {"searches": 0, "accepted": 0, "replaced_px": 0, "none_in_view": 0, "worse_than_dis": 0,
                      "left_prior": 0, "backed_off": 0}  # backed_off: frames the frontend did not search

    # ------------------------------------------------------------------------------------------ search --
    def _level(self, g0: np.ndarray, K: np.ndarray, R: np.ndarray, stride: int, r0: int):
        """What every candidate's cost needs on every ``stride``-th pixel of rows ``r0:``: ``K R x~`` (``[3, N]``),
        the rays' y (``n^T K^-1 x~``, ``[N]``), the brightness of ``g0`` there (``[N]``) and the pixels."""
        H, W = g0.shape
        ys, xs = np.mgrid[r0:H:stride, 0:W:stride]
        ys, xs = ys.ravel(), xs.ravel()
        P = np.linalg.inv(K) @ np.stack([xs, ys, np.ones(xs.size)]).astype(np.float64)
        return (K @ R @ P).astype(np.float32), P[1].astype(np.float32), g0[ys, xs].astype(np.float32), (ys, xs)

    def _costs(self, g1f: np.ndarray, K: np.ndarray, V: np.ndarray, level) -> np.ndarray:
        """Mean |g1(H_v x) - g0(x)| over a level's pixels for each candidate ``V [M, 3]`` (inf: too little in view);
        on a very large frame in blocks of candidates (each candidate's cost is its own row: the same values)."""
        per = max(1, _COST_BLOCK // max(level[1].size, 1))
        if len(V) <= per:
            return self._block_costs(g1f, K, V, level)
        return np.concatenate([self._block_costs(g1f, K, V[i:i + per], level) for i in range(0, len(V), per)])

    def _block_costs(self, g1f: np.ndarray, K: np.ndarray, V: np.ndarray, level) -> np.ndarray:
        A, B, ref, _ = level
        H, W = g1f.shape
        KV = (V @ K.T).astype(np.float32)  # [M, 3]
        # [M, N] each: x, y = (A + KV B) / z for z > 1e-6, else NaN (behind the camera), and inside the image
        mx, my, inside = _kernels().candidate_maps(A, B, KV, np.float32(W - 1), np.float32(H - 1))
        s = _remap(g1f, mx, my, cv2.BORDER_CONSTANT)
        n_in = inside.sum(1)
        c = _kernels().masked_abs_diff(s, ref, inside).sum(1) / np.maximum(n_in, 1)
        return np.where(n_in >= self.min_inside * B.size, c, np.inf)

    def _pattern(self, g1f: np.ndarray, K: np.ndarray, v: np.ndarray, level, step0: float) -> tuple[np.ndarray, float]:
        """Pattern search from ``v``: the 6 axis neighbours at once, the step halved when none is better."""
        step = np.array([0.6, 0.6, 1.0]) * step0 * max(abs(v[2]), 0.05)
        cost = float(self._costs(g1f, K, v[None], level)[0])
        for _ in range(20):
            cand = v[None] + _OFFS * step[None]
            cc = self._costs(g1f, K, cand, level)
            k = int(np.argmin(cc))
            if cc[k] < cost:
                cost, v = float(cc[k]), cand[k]
            else:
                step = step / 2
                if step[2] < 2e-3 * max(abs(v[2]), 0.05):
                    break
        return v, cost

    def near_prior(self, v: np.ndarray, prior: np.ndarray) -> bool:
        """Whether a search from ``prior`` stayed near it (within ``prior_tol`` of its length)."""
        return bool(np.linalg.norm(v - prior) <= self.prior_tol * max(np.linalg.norm(prior), 1e-9))

    def _grid_starts(self, g1f: np.ndarray, K: np.ndarray, level) -> list[np.ndarray]:
        """The best few distinct candidates of a grid: |v| on a log scale along -z (forward) and +z (reversing,
        straight only), the direction within ~7 deg of the optical axis.  The cost is noisy every 4th pixel of
        fine texture, so the pattern search starts from several (distinct: |v| at least a fifth apart)."""
        mags = np.geomspace(0.02, 8.0, 32)
        a = np.array([-0.12, 0.0, 0.12])
        ax, ay = np.meshgrid(a, a, indexing="ij")
        dirs = np.stack([ax.ravel(), ay.ravel(), -np.ones(ax.size)], 1)
        dirs = np.concatenate([dirs, [[0.0, 0.0, 1.0]]])
        V = np.concatenate([(mags[:, None, None] * dirs[None]).reshape(-1, 3), np.zeros((1, 3))])
        c = self._costs(g1f, K, V, level)
        starts: list[np.ndarray] = []
        for k in np.argsort(c):
            if not np.isfinite(c[k]) or len(starts) == self.starts:
                break
            m = np.linalg.norm(V[k])
            if all(abs(m - np.linalg.norm(s)) > 0.2 * max(m, np.linalg.norm(s)) for s in starts):
                starts.append(V[k])
        return starts

    def search(self, g0: np.ndarray, g1: np.ndarray, K: np.ndarray, R: np.ndarray,
               prior: Optional[np.ndarray] = None) -> Optional[tuple[np.ndarray, float, int]]:
        """``(v, cost, first row)`` of the plane explaining ``g0``'s ground rows best in ``g1`` (None: none in
        view).  ``R``: rotation of the camera of ``g0`` into that of ``g1`` (``X1 = R X0 + t``).  Without a
        ``prior`` a grid search on the rows from ``region``, with one a pattern search from it on the rows from
        ``horizon``."""
        self.stats["searches"] += 1
        H = g0.shape[0]
        r0 = int(np.ceil(K[1, 2] + (self.region if prior is None else self.horizon) * H))
        if r0 >= H - 2:
            return None
        g1f = g1.astype(np.float32)
        fine = self._level(g0, K, R, 2, r0)
        starts = [np.asarray(prior, np.float64)] if prior is not None else \
            self._grid_starts(g1f, K, self._level(g0, K, R, 4, r0))
        best = (np.inf, None)
        for v in starts:
            v, cost = self._pattern(g1f, K, v, fine, 0.06 if prior is None else 0.03)
            if cost < best[0]:
                best = (cost, v)
        if not np.isfinite(best[0]):
            return None
        return best[1], best[0], r0

    # ----------------------------------------------------------------------------------- flows, merge --
    @staticmethod
    def plane_flow(Hm: np.ndarray, shape: tuple[int, int], r0: int) -> tuple[np.ndarray, np.ndarray]:
        """Flow ``float32 [H, W, 2]`` of homography ``Hm`` and where it applies (rows ``r0:``, the target in front
        of the camera and in view)."""
        H, W = shape
        r = min(max(r0, 0), H)  # rows above r0 keep a zero flow: only the rows below are computed
        ys, xs, P = _pixels64(H, W)
        ys, xs, P = ys[r:], xs[r:], P[:, r:]
        q = np.einsum("ij,jhw->ihw", Hm, P)
        with np.errstate(divide="ignore", invalid="ignore"):
            mx, my = q[0] / q[2], q[1] / q[2]
        ok = np.zeros((H, W), bool)
        ok_r = ok[r:]
        np.greater(q[2], 1e-6, out=ok_r)
        ok_r &= mx >= 0
        ok_r &= mx <= W - 1
        ok_r &= my >= 0
        ok_r &= my <= H - 1
        out = ~ok_r
        f = np.zeros((H, W, 2), np.float32)  # the float64 differences rounded to float32 on assignment
        np.subtract(mx, xs, out=mx)
        np.copyto(mx, 0.0, where=out)
        f[r:, :, 0] = mx
        np.subtract(my, ys, out=my)
        np.copyto(my, 0.0, where=out)
        f[r:, :, 1] = my
        return f, ok

    def _local_residual(self, g0f: np.ndarray, g1: np.ndarray, flow: np.ndarray) -> np.ndarray:
        """5x5 mean of ``|g1(x + f(x)) - g0(x)|`` (``g0f``: ``g0`` as float32)."""
        diff = np.abs(_warp(g1, flow).astype(np.float32) - g0f)
        return cv2.blur(diff, (self.window, self.window))

    def merge(self, g0: np.ndarray, g1: np.ndarray, dis: np.ndarray, plane: np.ndarray,
              ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``dis`` with the plane's flow where it applies and explains ``g0`` in ``g1`` better (module docstring);
        also the bool mask of replaced pixels."""
        g0f = g0.astype(np.float32)
        use = ok & (self._local_residual(g0f, g1, plane) < self.margin * self._local_residual(g0f, g1, dis))
        self.stats["replaced_px"] += int(use.sum())
        return np.where(use[..., None], plane, dis).astype(np.float32, copy=False), use

    @staticmethod
    def _dis_cost(g0: np.ndarray, g1: np.ndarray, dis: np.ndarray, rows: int) -> tuple[float, np.ndarray]:
        """Mean |g1(x + f(x)) - g0(x)| of DIS's flow over every 2nd pixel of rows ``rows:`` that it keeps in view."""
        H, W = g0.shape
        ys, xs = np.mgrid[rows:H:2, 0:W:2]
        f = dis[ys, xs]
        mx, my = (xs + f[..., 0]).astype(np.float32), (ys + f[..., 1]).astype(np.float32)
        inside = (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
        s = _remap(g1.astype(np.float32), mx, my, cv2.BORDER_CONSTANT)
        d = np.abs(s - g0[ys, xs].astype(np.float32))
        return (float(d[inside].mean()) if inside.any() else np.inf), inside

    def apply(self, g0: np.ndarray, g1: np.ndarray, fwd: np.ndarray, bwd: np.ndarray, K: np.ndarray, R: np.ndarray,
              prior: Optional[np.ndarray] = None, verify: Optional[Callable] = None, defer_backward: bool = False):
        """Both DIS flows of a pair with the road's plane flow merged in: ``(fwd, bwd, use_f, use_b, v, res_f,
        res_b)``; the flows unchanged and the rest None when no plane was found or it explains its rows worse
        than DIS's flow does (its mean brightness residual over the searched rows that stay in view).

        ``verify([(i0, i1), ...]) -> [flow, ...]``: DIS calls (both directions at once: the caller may run them in
        parallel).  The two directions of the plane's flow come from one homography,
        so a forward-backward check cannot tell a wrong plane pixel (a curb, a parked car's flank, a plane from
        a poor prior); instead DIS runs between ``g0`` and ``g1`` warped into ``g0``'s view by the merged flow:
        where that flow is right, the views agree and DIS finds ~0.  ``res_f`` / ``res_b`` are the lengths of
        those residual flows (flow px, float32 [H, W]; None without ``verify``).  ``defer_backward``: ``res_b`` is
        a function that runs the backward verification when called (a tracked frame needs it only if it becomes a
        keyframe)."""
        none = (fwd, bwd, None, None, None, None, None)
        found = self.search(g0, g1, K, R, prior)
        if found is None:
            self.stats["none_in_view"] += 1
            return none
        v, cost, r0 = found
        if prior is None:  # a plane from scratch must explain its rows better than DIS's flow
            if not cost < self._dis_cost(g0, g1, fwd, r0)[0]:
                self.stats["worse_than_dis"] += 1
                return none
        elif not self.near_prior(v, prior):
            # from a prior (a pair far apart: its rows near the horizon are mostly not road, where DIS's flow is
            # right and the plane's is not, so the comparison above would reject the road too) it must stay near it
            self.stats["left_prior"] += 1
            return none
        Hm = homography(K, R, v)
        pf, okf = self.plane_flow(Hm, g0.shape, r0)
        pb, okb = self.plane_flow(np.linalg.inv(Hm), g1.shape, r0)
        fwd2, use_f = self.merge(g0, g1, fwd, pf, okf)
        bwd2, use_b = self.merge(g1, g0, bwd, pb, okb)
        self.stats["accepted"] += 1
        res_f = res_b = None
        if verify is not None:
            def residual(a: np.ndarray, b: np.ndarray, flow: np.ndarray) -> np.ndarray:
                return _kernels().flow_length(verify([(a, _warp(b, flow))])[0])

            if defer_backward:
                res_f, res_b = residual(g0, g1, fwd2), functools.partial(residual, g1, g0, bwd2)
            else:
                rf, rb = verify([(g0, _warp(g1, fwd2)), (g1, _warp(g0, bwd2))])
                res_f, res_b = _kernels().flow_length(rf), _kernels().flow_length(rb)
        return fwd2, bwd2, use_f, use_b, v, res_f, res_b


class RoadChain:
    """Each keyframe's camera pose relative to the road, chained from the plane motions found while tracking: a
    rotation and a translation in units of the camera height, in the frame of the keyframe that began the chain.
    The ``prior`` of a pair far apart is their relative ``v = t_b - R_ab t_a`` (translations compose like the
    keyframes' positions because the camera height is the same all along).  A keyframe tracked without a plane
    motion (none found, and no velocity to bridge with) starts a new chain; pairs in different chains have no
    prior.  A chain may also grow backwards (:meth:`prepend`, ``RoadPrior.extend_back``).  A removed keyframe's pose
    is kept (the newest ``keep`` of them): a frame tracked against a keyframe that the map then dropped still chains
    through it."""

    def __init__(self, keep: int = 256):
        self._pose: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}  # kf id -> (chain, rot [3, 3], trans [3])
        self._removed: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}  # the same, of removed keyframes
        self._first: dict[int, int] = {}  # chain -> its first keyframe's id
        self._keep = int(keep)
        self._chains = 0

    def add(self, kf_id: int, ref_id: Optional[int], R: Optional[np.ndarray], v: Optional[np.ndarray]) -> None:
        """Keyframe ``kf_id`` tracked from ``ref_id`` with plane motion ``(R, v)`` (None: none found)."""
        if ref_id is None or v is None or R is None:
            self._chains += 1
            self._pose[kf_id] = (self._chains, np.eye(3), np.zeros(3))
            self._first[self._chains] = kf_id
            return
        ref = self._pose.get(ref_id, self._removed.get(ref_id))
        if ref is None:
            self.add(kf_id, None, None, None)
            return
        c, rot, tr = ref
        self._pose[kf_id] = (c, R @ rot, R @ tr + v)

    def prepend(self, kf_id: int, next_id: int, R: np.ndarray, v: np.ndarray) -> None:
        """Keyframe ``kf_id``, the first of a chain of its own, joins the chain of ``next_id`` (that chain's first
        keyframe) before it, with ``(R, v)`` the plane motion ``kf_id -> next_id``: ``next`` is ``(R rot, R tr + v)``
        of ``kf_id``'s pose ``(rot, tr)``, solved for it."""
        c, rot, tr = self._pose[next_id]
        self._first.pop(self._pose[kf_id][0], None)
        self._pose[kf_id] = (c, R.T @ rot, R.T @ (tr - v))
        self._first[c] = kf_id

    def first(self, kf_id: int) -> bool:
        """Whether keyframe ``kf_id`` is the first of its chain."""
        pose = self._pose.get(kf_id)
        return pose is not None and self._first.get(pose[0]) == kf_id

    def same(self, a: int, b: int) -> bool:
        """Whether keyframes ``a`` and ``b`` are in one chain."""
        pa, pb = self._pose.get(a), self._pose.get(b)
        return pa is not None and pb is not None and pa[0] == pb[0]

    def remove(self, kf_id: int) -> None:
        pose = self._pose.pop(kf_id, None)
        if pose is not None:
            self._removed[kf_id] = pose
            while len(self._removed) > self._keep:
                del self._removed[next(iter(self._removed))]

    def prior(self, a: int, b: int) -> Optional[np.ndarray]:
        pa, pb = self._pose.get(a), self._pose.get(b)
        if pa is None or pb is None or pa[0] != pb[0]:
            return None
        R_ab = pb[1] @ pa[1].T
        return pb[2] - R_ab @ pa[2]

    def __len__(self) -> int:
        return len(self._pose)
