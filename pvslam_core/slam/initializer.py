"""Monocular map initialisation from two views: motion hypotheses from the essential matrix and the homography,
chosen by cheirality and the Sampson cost, then triangulation (OpenCV).

Given dense correspondences from one keyframe to a later keyframe at the BA resolution, estimate the relative pose
and the inverse depth of the first view.  The hypotheses: the minima of the robust Sampson cost over the motion
(:func:`refine_relative_pose`, started from OpenCV's RANSAC essential matrix, from the homography's decompositions
and from fixed translation directions) and the homography's decompositions themselves (a planar scene leaves the
essential matrix a family of solutions).  Each is scored on every confident correspondence: how many epipolar
inliers it puts in front of both views, and its truncated Sampson cost.  The chosen one has the lowest cost among
those that put at least ``front_frac`` of the best count in front; near-ties in cost (within 5 percent: the two
homography solutions of a plane) go to the one with more points in front.

Why not ORB-SLAM's score ratio ``R_H = S_H / (S_H + S_F)`` (still printed): with dense, accurate BA-resolution
flow both models fit nearly every correspondence, the ratio cannot tell them apart and the homography wins almost
every time, with a translation far off.  Why not the count alone (the most points in front): on a forward drive the
points near the focus of expansion have no parallax and land behind a camera from noise, so a sideways hypothesis
can have more points in front than the true motion at a far higher cost (docs/decisions.md: TWO-VIEW MODEL
CHOICE).  The pair must show enough parallax.  The map scale is arbitrary in monocular SLAM; it is fixed here so
that the median inverse depth of the first view is 1.

:func:`two_view_init_why` also says why a pair was declined (the bootstrap prints it while it keeps trying).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np
import torch

from ..geometry.lie import se3_from_matrix
from ..geometry.two_view import find_essential

LOG = logging.getLogger("pvslam.init")

# two_view_init_why's tie check (tie_ratio): a rival motion counts when it puts this share of the chosen one's points
# in front and its translation direction is this far from the chosen one's
TIE_FRONT = 0.9
TIE_ANGLE_DEG = 20.0


@dataclass
class TwoViewInit:
    pose_wc: torch.Tensor  # float64 [7] pose of the second view; the first is the identity
    disp0: torch.Tensor  # float32 [h, w] inverse depth of the first view
    inliers: int
    parallax_deg: float
    model: str = "E"  # "E" (essential matrix) or "H" (homography)


@dataclass(frozen=True)
class TwoViewOptions:
    """How :func:`two_view_init_why` chooses and checks the motion of a pair."""

    min_inliers: int = 60  # confident correspondences, and points in front of both views, the pair needs
    min_parallax_deg: float = 1.0  # parallax (degrees) the pair must show at `parallax_quantile` of its points
    ransac_px: float = 0.3  # RANSAC threshold (BA px) of the essential matrix (2x for the homography)
    refine: bool = True  # refine the motion on all correspondences from several starts (refine_relative_pose)
    front_frac: float = 0.65  # hypotheses with at least this share of the best count in front compete on cost
    # a correspondence is confident above a weight of 0.5, or with relative_weight above half of the pair's
    # 90th-percentile weight (within [RELATIVE_FLOOR, 0.5])
    relative_weight: bool = False
    parallax_quantile: float = 0.5  # 0.5: the median parallax of the triangulated points
    # decline the pair when the chosen motion fits this many times worse than another with min_inliers points in
    # front (None: never)
    ambiguity_ratio: Optional[float] = None
    # decline the pair when another motion with TIE_FRONT of the points in front fits within this factor of the
    # chosen one's cost and heads more than TIE_ANGLE_DEG away (None: never)
    tie_ratio: Optional[float] = None


def two_view_init(
    target: torch.Tensor,  # [2, h, w] positions in view 1 of view-0 pixels (BA resolution)
    weight: torch.Tensor,  # [2, h, w]
    intr: torch.Tensor,  # [4] fx fy cx cy at the BA resolution
    min_inliers: int = 60,
    min_parallax_deg: float = 1.0,
    ransac_px: float = 0.3,
    relative_weight: bool = False,
) -> Optional[TwoViewInit]:
    """The two-view initialisation of a keyframe pair, or None (see :func:`two_view_init_why`)."""
    opts = TwoViewOptions(min_inliers=min_inliers, min_parallax_deg=min_parallax_deg, ransac_px=ransac_px,
                          relative_weight=relative_weight)
    return two_view_init_why(target, weight, intr, opts)[0]


RELATIVE_FLOOR = 0.05  # the lowest weight that counts as a confident correspondence under ``relative_weight``


def confidence_threshold(w_min: np.ndarray, relative_weight: bool) -> float:
    """The weight above which a correspondence (``w_min``: the smaller of its two weights, any shape) counts as
    confident: 0.5, or with ``relative_weight`` half of the pair's 90th-percentile weight within
    ``[RELATIVE_FLOOR, 0.5]``."""
    if not relative_weight:
        return 0.5
    # "confident": above half of the pair's own high weights (90th percentile), at most 0.5: a frontend whose
    # confidences carry a texture term keeps most weights of a textured street below 0.5.  Never below
    # RELATIVE_FLOOR: where the flow failed almost everywhere the 90th percentile is ~0 and any trace of weight would
    # count (docs/decisions.md: RELATIVE_CONFIDENCE)
    return max(RELATIVE_FLOOR, min(0.5, 0.5 * float(np.quantile(w_min, 0.9))))


def confident_mask(target: torch.Tensor, weight: torch.Tensor, relative_weight: bool) -> np.ndarray:
    """bool ``[h*w]``: the correspondences of a pair (``target`` / ``weight`` ``[2, h, w]``) that count as confident
    (:func:`confidence_threshold` on the smaller of the two weights) and have a finite target."""
    p1 = target.detach().cpu().double().numpy().reshape(2, -1).T  # [P, 2]
    w_min = weight.detach().cpu().numpy().reshape(2, -1).min(0)  # [P]
    return (w_min > confidence_threshold(w_min, relative_weight)) & np.isfinite(p1).all(1)


@dataclass
class _Pair:
    """A pair's confident correspondences in pixels (``p0``, ``p1`` ``[P, 2]``) and normalised rays (``x0``, ``x1``
    ``[P, 3]``), the camera, and where they sit among the ``h x w`` view-0 pixels (``good`` bool ``[h*w]``)."""

    p0: np.ndarray
    p1: np.ndarray
    x0: np.ndarray
    x1: np.ndarray
    K: np.ndarray
    px: float  # normalised -> pixel units
    good: np.ndarray
    h: int
    w: int


# a scored motion hypothesis: (points in front, truncated Sampson cost, R, t, inlier mask, X, in-front mask, model)
_Scored = tuple


def two_view_init_why(target: torch.Tensor, weight: torch.Tensor, intr: torch.Tensor,
                      opts: TwoViewOptions = TwoViewOptions()) -> tuple[Optional[TwoViewInit], str]:
    """``(init or None, reason)``: the two-view initialisation of a pair (``target`` ``[2, h, w]``: view-0 pixels in
    view 1, BA px; ``weight`` ``[2, h, w]``; ``intr`` ``[4]`` at the BA resolution), or why it was declined ("" on
    success).  See the module docstring and :class:`TwoViewOptions`.

    ``ambiguity_ratio`` declines a pair whose chosen motion fits far worse than a motion with fewer points in front:
    with little parallax a forward drive's points near the focus of expansion fall behind from noise, and a sideways
    motion wins on the count (docs/decisions.md: AMBIGUITY_RATIO).  ``tie_ratio`` declines a pair on which two
    motions far apart fit alike: with ~100 confident points the data may not tell them apart at all
    (docs/decisions.md: TIE_RATIO).  Declined, the pair is tried again with more motion."""
    pair = _confident_pair(target, weight, intr, opts)
    if isinstance(pair, str):
        return None, pair
    import cv2

    E, mask = find_essential(pair.p0, pair.p1, pair.K, opts.ransac_px)
    if E is None:
        return None, "no essential matrix found"
    E = E[:3]
    H, _ = cv2.findHomography(pair.p0, pair.p1, cv2.RANSAC, 2.0 * opts.ransac_px)
    r_h = homography_score_ratio(H, E, pair.p0, pair.p1, pair.K, sigma=max(opts.ransac_px, 0.5)) \
        if H is not None else 0.0
    scored = _score(pair, _hypotheses(pair, E, mask, H, opts), opts)
    best = _choose(pair, scored, opts, r_h)
    if isinstance(best, str):
        return None, best
    return _triangulated_init(pair, best, opts, r_h)


def _confident_pair(target: torch.Tensor, weight: torch.Tensor, intr: torch.Tensor,
                    opts: TwoViewOptions) -> Union[_Pair, str]:
    """The pair's confident correspondences, or why there are not enough of them."""
    h, w = target.shape[-2:]
    ys, xs = np.mgrid[0:h, 0:w]
    p0 = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)  # [P, 2]
    p1 = target.detach().cpu().double().numpy().reshape(2, -1).T  # [P, 2]
    good = confident_mask(target, weight, opts.relative_weight)
    if good.sum() < opts.min_inliers:
        return f"{int(good.sum())} confident correspondences < {opts.min_inliers} (the views do not overlap)"
    p0g, p1g = p0[good], p1[good]
    fx, fy, cx, cy = [float(v) for v in intr.detach().cpu()]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    if float(np.median(np.linalg.norm(p1g - p0g, axis=1))) < 1e-3:
        return "no motion between the views"
    Kinv = np.linalg.inv(K)
    x0 = np.hstack([p0g, np.ones((len(p0g), 1))]) @ Kinv.T  # [P, 3] normalised rays
    x1 = np.hstack([p1g, np.ones((len(p1g), 1))]) @ Kinv.T
    return _Pair(p0g, p1g, x0, x1, K, float(np.sqrt(fx * fy)), good, h, w)


def _hypotheses(pair: _Pair, E: np.ndarray, mask: np.ndarray, H: Optional[np.ndarray],
                opts: TwoViewOptions) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """``(R, t, model)`` motion hypotheses of the pair (module docstring)."""
    import cv2

    cands = []
    _, R_e, t_e, _ = cv2.recoverPose(E, pair.p0, pair.p1, pair.K, mask=mask.copy())
    h_sols = []
    if H is not None:
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, pair.K)
        h_sols = [(R, t / np.linalg.norm(t)) for R, t in zip(Rs, ts) if float(np.linalg.norm(t)) > 1e-9]
    if opts.refine:
        # the essential matrix of OpenCV's RANSAC is its best *minimal* sample, not refined on the inliers: with a
        # narrow view and little parallax its translation can be far off (the rotation / translation confusion).
        # Refine on all correspondences from several starts (the Sampson cost has local minima; each distinct
        # minimum is a hypothesis); see refine_relative_pose.
        cands += [(R, t, "E") for R, t, _ in refine_relative_pose(pair.x0, pair.x1, [(R_e, t_e)] + h_sols,
                                                                   f_scale=opts.ransac_px / pair.px)]
    else:
        cands.append((R_e, t_e, "E"))
    cands += [(R, t, "H") for R, t in h_sols]
    return cands


def _score(pair: _Pair, cands: list, opts: TwoViewOptions) -> list[_Scored]:
    """Each hypothesis scored on every confident correspondence: its epipolar inliers in front of both views and
    its truncated Sampson cost (hypotheses that triangulate nothing are left out)."""
    import cv2

    x0, x1 = pair.x0, pair.x1
    samp_thr = 2.0 * opts.ransac_px / pair.px
    scored = []
    for R, t, mdl in cands:
        inl = np.abs(sampson_error(_skew(t.ravel()) @ R, x0, x1)) < samp_thr  # epipolar inliers of this motion
        if mdl == "E":  # the cheirality test fixes the sign of t and the twisted pair (the Sampson cost cannot)
            _, R, t, _ = cv2.recoverPose(_skew(t.ravel()) @ R, pair.p0, pair.p1, pair.K,
                                         mask=inl.astype(np.uint8)[:, None].copy())
        tri = _triangulate(pair.K, R, t, pair.p0[inl], pair.p1[inl])
        if tri is None:
            continue
        X, z_ok, _ = tri
        cost = float(np.mean(np.minimum(sampson_error(_skew(t.ravel()) @ R, x0, x1) ** 2, samp_thr ** 2)))
        # (points with no parallax land in front or behind from noise alone; counting them as good instead, as
        # ORB-SLAM's CheckRT does, lets degenerate low-parallax solutions of a planar scene win)
        n_good = int(z_ok.sum())
        scored.append((n_good, cost, R, t, inl, X, z_ok, mdl))
    return scored


def _choose(pair: _Pair, scored: list[_Scored], opts: TwoViewOptions, r_h: float) -> Union[_Scored, str]:
    """The lowest cost among the hypotheses with enough points in front, near-ties to the most points in front
    (module docstring); or why the pair is declined (too few in front, ambiguous, tied)."""
    n_max = max((c[0] for c in scored), default=0)
    if n_max < opts.min_inliers:
        return f"too few points triangulate in front of both views (R_H {r_h:.2f})"
    ok_front = [c for c in scored if c[0] >= opts.front_frac * n_max]
    c_min = min(c[1] for c in ok_front)
    best = max((c for c in ok_front if c[1] <= 1.05 * c_min), key=lambda c: (c[0], -c[1]))
    if LOG.isEnabledFor(logging.DEBUG):
        px = pair.px
        LOG.debug("two-view hypotheses (model, in front, cost px^2, t): %s", "; ".join(
            f"{c[7]} {c[0]} {c[1] * px * px:.4f} {np.round(c[3].ravel(), 2).tolist()}" for c in scored))
    if opts.ambiguity_ratio is not None:
        rival = min((c for c in scored if c[0] >= opts.min_inliers), key=lambda c: c[1])  # n_max >= min_inliers
        worse = best[1] / max(rival[1], 1e-30)
        if worse > opts.ambiguity_ratio:
            return (f"ambiguous: a motion with fewer points in front ({rival[0]} of {n_max}) fits "
                    f"{worse:.0f}x better (R_H {r_h:.2f})")
    if opts.tie_ratio is not None:
        t_best = best[3].ravel() / np.linalg.norm(best[3])
        for c in scored:
            t_c = c[3].ravel() / np.linalg.norm(c[3])
            ang = float(np.degrees(np.arccos(np.clip(t_best @ t_c, -1.0, 1.0))))
            if c[0] >= TIE_FRONT * best[0] and c[1] <= opts.tie_ratio * best[1] and ang > TIE_ANGLE_DEG:
                return (f"ambiguous: two motions {ang:.0f} deg apart fit alike ({best[0]} / {c[0]} points in "
                        f"front, cost ratio {c[1] / max(best[1], 1e-30):.2f}; R_H {r_h:.2f})")
    return best


def _triangulated_init(pair: _Pair, best: _Scored, opts: TwoViewOptions,
                       r_h: float) -> tuple[Optional[TwoViewInit], str]:
    """The chosen motion's parallax check, then the first view's inverse depth (median 1) and the second view's
    pose in that scale."""
    _, _, R, t, inl, X, ok, model = best
    par = float(np.quantile(_parallax_deg(X, R, t)[ok], opts.parallax_quantile))
    if par < opts.min_parallax_deg:
        what = "mostly a rotation or a far scene" if model == "H" else "too short a baseline"
        which = "median" if opts.parallax_quantile == 0.5 else f"{100 * opts.parallax_quantile:.0f}th-percentile"
        return None, f"{which} parallax {par:.2f} deg < {opts.min_parallax_deg:.2f} ({what}; R_H {r_h:.2f})"
    z = X[:, 2]
    disp_pts = 1.0 / z[ok]
    scale = float(np.median(disp_pts))  # make the median inverse depth 1
    disp0 = np.full(pair.h * pair.w, 1.0, dtype=np.float64)
    idx = np.flatnonzero(pair.good)[inl][ok]
    disp0[idx] = disp_pts / scale
    disp0 = np.clip(disp0, 1e-3, 1e3)
    # unfilled pixels: a median filter of the filled map is overkill; use the median (=1)
    T_c1_c0 = np.eye(4)
    T_c1_c0[:3, :3] = R
    T_c1_c0[:3, 3] = t.ravel() * scale  # inverse depths were divided by `scale`, so depths and translation grow by it
    T_wc1 = np.linalg.inv(T_c1_c0)
    pose = se3_from_matrix(torch.from_numpy(T_wc1))
    LOG.info("two-view initialisation (%s model, R_H %.2f): %d inliers, parallax %.2f deg at quantile %.2f", model,
             r_h, int(ok.sum()), par, opts.parallax_quantile)
    return TwoViewInit(pose, torch.from_numpy(disp0.reshape(pair.h, pair.w)).float(), int(ok.sum()), par, model), ""


def _parallax_deg(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Angle [M] (degrees) between the rays from the two camera centres to the points ``X [M, 3]`` (view 0)."""
    c1 = (-R.T @ t).ravel()  # centre of view 1 in view-0 coordinates
    ray0 = X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)
    ray1 = (X - c1) / np.maximum(np.linalg.norm(X - c1, axis=1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip((ray0 * ray1).sum(1), -1, 1)))


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def sampson_error(E: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Signed Sampson distance ``[N]`` of the normalised correspondences ``x0 -> x1`` (``[N, 3]``, z = 1) to the
    essential matrix ``E`` (normalised units: multiply by the focal length for pixels)."""
    ex0 = x0 @ E.T
    etx1 = x1 @ E
    num = (x1 * ex0).sum(1)
    den = ex0[:, 0] ** 2 + ex0[:, 1] ** 2 + etx1[:, 0] ** 2 + etx1[:, 1] ** 2
    return num / np.sqrt(den + 1e-30)


# translation directions tried as extra starts (up to sign: the Sampson cost does not see the sign of t)
_T_STARTS = np.array([(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1)], float)
_T_STARTS /= np.linalg.norm(_T_STARTS, axis=1, keepdims=True)


def refine_relative_pose(x0: np.ndarray, x1: np.ndarray, starts: list, f_scale: float, max_nfev: int = 30,
                         max_points: int = 300, keep: int = 6) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Local minima ``[(R, t [3, 1], cost)]`` (lowest cost first, at most ``keep``, distinct) of the Huber-robust
    Sampson cost of the normalised correspondences ``x0 -> x1`` ``[N, 3]`` over the relative motion (5 DoF,
    ``|t| = 1``), from each ``(R, t)`` of ``starts`` and from the first start's rotation with each direction of
    ``_T_STARTS``.  The cost has several minima (with a narrow view a small sideways translation and a small
    rotation move the image almost alike, and a dominant plane such as a road leaves a family of solutions): a
    single start from OpenCV's RANSAC can end far off the true translation, and on a forward drive a sideways
    minimum can have a *lower* cost than the true forward motion.  So every distinct minimum is returned and the
    caller decides by cheirality.  The sign of ``t`` is left
    to the caller too (the Sampson cost does not see it)."""
    import cv2
    from scipy.optimize import least_squares

    def unpack(p):
        th, ph = p[3], p[4]
        return cv2.Rodrigues(p[:3])[0], np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])

    def pack(R, t):
        t = np.asarray(t, float).ravel()
        t = t / np.linalg.norm(t)
        return np.concatenate([cv2.Rodrigues(np.asarray(R, float))[0].ravel(),
                               [np.arccos(np.clip(t[2], -1.0, 1.0)), np.arctan2(t[1], t[0])]])

    def resid(p, a, b):
        R, t = unpack(p)
        return sampson_error(_skew(t) @ R, a, b)

    # the starts run on an even subsample (the cost is smooth; ~10x cheaper), the minima are polished on all
    sub = slice(None, None, max(1, len(x0) // max_points))
    minima = []
    for R, t in list(starts) + [(starts[0][0], d) for d in _T_STARTS]:
        r = least_squares(resid, pack(R, t), args=(x0[sub], x1[sub]), loss="huber", f_scale=f_scale,
                          max_nfev=max_nfev)
        minima.append((float(r.cost), r.x))
    out: list[tuple[np.ndarray, np.ndarray, float]] = []
    for _, p in sorted(minima, key=lambda m: m[0]):
        R, t = unpack(p)
        if any(abs(float(t @ t2.ravel())) > np.cos(np.radians(2.0)) and
               np.linalg.norm(cv2.Rodrigues(R @ R2.T)[0]) < np.radians(0.5) for R2, t2, _ in out):
            continue  # the same minimum (up to the sign of t) from another start
        r = least_squares(resid, p, args=(x0, x1), loss="huber", f_scale=f_scale, max_nfev=max_nfev)
        R, t = unpack(r.x)
        out.append((R, t.reshape(3, 1), float(r.cost)))
        if len(out) >= keep:
            break
    return out


def homography_score_ratio(H: np.ndarray, E: np.ndarray, p0: np.ndarray, p1: np.ndarray, K: np.ndarray,
                           sigma: float = 0.5) -> float:
    """ORB-SLAM's model selection ratio ``R_H = S_H / (S_H + S_F)``: ``S_M`` sums, over both transfer directions
    of every correspondence, ``5.991 - e^2 / sigma^2`` where that is positive (``e``: the transfer error of the
    homography; the distance to the epipolar line for the fundamental matrix ``K^-T E K^-1``, whose chi-square
    gate is 3.841 for one degree of freedom but whose score uses the same 5.991 so both models compete fairly)."""
    th_score, th_f = 5.991, 3.841
    hp0 = np.hstack([p0, np.ones((len(p0), 1))])
    hp1 = np.hstack([p1, np.ones((len(p1), 1))])

    def h_err(M, a, b):
        q = a @ M.T
        q = q[:, :2] / np.where(np.abs(q[:, 2:]) < 1e-12, 1e-12, q[:, 2:])
        return ((b[:, :2] - q) ** 2).sum(1) / sigma ** 2

    s_h = 0.0
    for e2 in (h_err(H, hp0, hp1), h_err(np.linalg.inv(H), hp1, hp0)):
        s_h += float(np.where(e2 < th_score, th_score - e2, 0.0).sum())
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ E @ Kinv
    s_f = 0.0
    for l_, x in ((hp0 @ F.T, hp1), (hp1 @ F, hp0)):  # epipolar lines in view 1 (of p0) and in view 0 (of p1)
        e2 = (l_ * x).sum(1) ** 2 / np.maximum(l_[:, 0] ** 2 + l_[:, 1] ** 2, 1e-12) / sigma ** 2
        s_f += float(np.where(e2 < th_f, th_score - e2, 0.0).sum())
    return s_h / max(s_h + s_f, 1e-12)


def _triangulate(K: np.ndarray, R: np.ndarray, t: np.ndarray, p0: np.ndarray, p1: np.ndarray):
    """Points ``X [M, 3]`` (view 0), the mask of those in front of both views, and the median reprojection error
    of those in view 1; None without points."""
    import cv2

    if len(p0) == 0:
        return None
    P0 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = K @ np.hstack([R, t.reshape(3, 1)])
    X = cv2.triangulatePoints(P0, P1, p0.T, p1.T)  # [4, M]
    X = (X[:3] / np.where(np.abs(X[3:]) < 1e-12, 1e-12, X[3:])).T  # [M, 3] in view 0
    X1 = X @ R.T + t.reshape(1, 3)
    ok = (X[:, 2] > 0) & (X1[:, 2] > 0) & np.isfinite(X).all(1)
    if not ok.any():
        return X, ok, float("inf")
    q = X1[ok] @ K.T
    err = np.linalg.norm(q[:, :2] / q[:, 2:] - p1[ok], axis=1)
    return X, ok, float(np.median(err))
