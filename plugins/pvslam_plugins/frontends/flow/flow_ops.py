"""Numpy/OpenCV building blocks of the ``flow`` frontend: DIS flow, forward-backward confidence, BA pooling.

Pixel conventions: pixel centres at integer coordinates.  A BA pixel ``(x, y)`` covers the block of ``s x s``
flow-resolution pixels whose centres average to ``X = s x + (s - 1) / 2``; the target of that BA pixel is
``(X + mean_f - (s - 1) / 2) / s = x + mean_f / s``, where ``mean_f`` is the (confidence-weighted) mean flow
over the block.  For a non-integer ratio ``s = W_flow / w`` the same formula holds for ``cv2.INTER_AREA``.

DIS initial flow (verified with OpenCV 4.x/5.0): ``dis.calc(I0, I1, flow)`` with ``flow`` a float32
``[H, W, 2]`` array of the image size uses ``flow`` as the initialisation (downscaled to the coarsest level);
with ``None`` it starts from zero.  A good init recovers displacements of 100+ px that zero init misses.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np
import torch

from pvslam_core.imaging import create_dis, to_gray  # noqa: F401  (the frontend's DIS and gray images)

def compute_flow(dis, i0: np.ndarray, i1: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
    """DIS flow ``i0 -> i1`` as float32 ``[H, W, 2]`` (``i1(x + f(x)) ~ i0(x)``), optionally from ``init``."""
    if init is None:
        return dis.calc(i0, i1, None)
    flow = np.array(init, dtype=np.float32, order="C", copy=True)
    if flow.shape != (*i0.shape, 2):
        raise ValueError(f"initial flow shape {flow.shape} does not match image {i0.shape}")
    return dis.calc(i0, i1, flow)


_GRIDS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _grids(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    key = (h, w)
    g = _GRIDS.get(key)
    if g is None:
        xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        xy = np.ascontiguousarray(np.stack([xs, ys], -1))
        for a in (xs, ys, xy):
            a.setflags(write=False)
        if len(_GRIDS) > 16:
            _GRIDS.clear()
        g = _GRIDS[key] = (xs, ys, xy)
    return g


def pixel_grid_np(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Cached float32 ``(xs, ys)`` pixel-centre grids of shape ``[h, w]`` (read-only)."""
    xs, ys, _ = _grids(h, w)
    return xs, ys


def fb_consistency(fwd: np.ndarray, bwd: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Forward-backward check of ``fwd`` (i->j) against ``bwd`` (j->i).

    Returns ``conf = exp(-fb^2 / (2 sigma^2))`` (0 where ``x + f(x)`` leaves the image) and ``fb`` (the error
    ``|f(x) + b(x + f(x))|``, ``inf`` where ``x + f(x)`` leaves the image), both float32 ``[H, W]``; ``sigma``
    is in flow-resolution pixels.  OpenCV element-wise ops (~0.5 ms at 320x240).
    """
    h, w = fwd.shape[:2]
    _, _, xy = _grids(h, w)
    pos = cv2.add(xy, fwd)  # [H, W, 2] position of x + f(x)
    inside = cv2.inRange(pos, (0.0, 0.0), (float(w - 1), float(h - 1)))  # uint8 255 inside
    bw = cv2.remap(bwd, pos, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    d = cv2.add(fwd, bw)
    dx, dy = cv2.split(d)
    # numpy, not cv2.magnitude: OpenCV 4.x's SIMD magnitude returned run-to-run different values for the last
    # elements of an array (an out-of-bounds tail read), which made whole runs non-reproducible
    fb = np.sqrt(dx * dx + dy * dy)
    conf = cv2.exp(cv2.multiply(fb, fb, scale=-1.0 / (2.0 * sigma * sigma)))
    outside = inside == 0
    conf[outside] = 0.0
    fb[outside] = np.inf
    return conf, fb


def pool_to_ba(
    flow: np.ndarray, conf: np.ndarray, h: int, w: int, weighted: bool = True, eps: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """Flow-resolution flow + confidence -> BA-resolution ``target [2, h, w]`` and ``weight [h, w]``.

    ``target`` holds absolute (u, v) positions in BA pixels of the target frame; ``weight`` is the block mean of
    the confidence.  With ``weighted`` the block's flow is confidence-weighted (falls back to the plain mean where
    the block's total confidence is ~0).
    """
    hf, wf = flow.shape[:2]
    sx, sy = wf / w, hf / h
    if (hf, wf) == (h, w):
        mean_f = flow
        wgt = conf
    else:
        mean_f = cv2.resize(flow, (w, h), interpolation=cv2.INTER_AREA)
        wgt = cv2.resize(conf, (w, h), interpolation=cv2.INTER_AREA)
        if weighted:
            cf = cv2.resize(flow * conf[..., None], (w, h), interpolation=cv2.INTER_AREA)
            ok = wgt > eps
            mean_f = np.where(ok[..., None], cf / np.maximum(wgt, eps)[..., None], mean_f)
    xs, ys = pixel_grid_np(h, w)
    target = np.stack([xs + mean_f[..., 0] / sx, ys + mean_f[..., 1] / sy], 0).astype(np.float32)
    return target, np.ascontiguousarray(wgt, dtype=np.float32)


def init_flow_from_coords(
    coords: np.ndarray, valid: np.ndarray, hf: int, wf: int, min_valid: float = 0.3
) -> Optional[np.ndarray]:
    """Upsample a BA-resolution correspondence field (``coords [h, w, 2]`` absolute (u, v) in BA px of the target
    frame, ``valid [h, w]``) to a flow-resolution initial flow ``[hf, wf, 2]``; invalid pixels take the median
    flow of the valid ones.  None when fewer than ``min_valid`` of the pixels are valid or values are not finite.
    """
    h, w = valid.shape
    ok = valid & np.isfinite(coords).all(-1)
    if ok.mean() < min_valid:
        return None
    xs, ys = pixel_grid_np(h, w)
    f = np.stack([coords[..., 0] - xs, coords[..., 1] - ys], -1).astype(np.float32)
    med = np.median(f[ok], axis=0)
    f[~ok] = med
    f[..., 0] *= wf / w
    f[..., 1] *= hf / h
    if (hf, wf) == (h, w):
        return np.ascontiguousarray(f)
    return cv2.resize(f, (wf, hf), interpolation=cv2.INTER_LINEAR)


def downsample_ids(ids: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Nearest (block-centre) downsampling of an int id map ``[H, W]`` to ``[h, w]``."""
    hh, ww = ids.shape[-2:]
    rows = ((torch.arange(h, dtype=torch.float64) + 0.5) * hh / h).long().clamp(max=hh - 1)
    cols = ((torch.arange(w, dtype=torch.float64) + 0.5) * ww / w).long().clamp(max=ww - 1)
    return ids[..., rows[:, None], cols[None, :]].contiguous()


def invert_coords(coords: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert a BA-resolution correspondence field ``a -> b`` into ``b -> a`` by nearest-pixel splatting.

    ``coords [h, w, 2]``: absolute (u, v) in ``b`` of each pixel of ``a``.  Returns ``back [h, w, 2]``
    (absolute (u, v) in ``a`` of each pixel of ``b``) and ``valid_back [h, w]`` (pixels that received a splat).
    Used to initialise the backward flow of an edge whose source keyframe has no optimised depth yet.
    """
    h, w = valid.shape
    xs, ys = pixel_grid_np(h, w)
    ok = valid & np.isfinite(coords).all(-1)
    u = np.rint(coords[..., 0][ok]).astype(np.int64)
    v = np.rint(coords[..., 1][ok]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    back = np.full((h, w, 2), np.nan, np.float32)
    back[v[inside], u[inside], 0] = xs[ok][inside]
    back[v[inside], u[inside], 1] = ys[ok][inside]
    # the splat landed at the rounded position: correct by the rounding offset so the flow stays sub-pixel
    back[v[inside], u[inside], 0] += u[inside] - coords[..., 0][ok][inside]
    back[v[inside], u[inside], 1] += v[inside] - coords[..., 1][ok][inside]
    vb = np.isfinite(back).all(-1)
    return back, vb


def photometric_confidence(g0: np.ndarray, g1: np.ndarray, flow: np.ndarray, sigma: float,
                           window: int = 3) -> np.ndarray:
    """``exp(-r^2 / (2 sigma^2))`` with ``r`` the local mean absolute brightness residual ``|g1(x + f) - g0(x)|``
    (``window`` x ``window`` box, after removing the global exposure change: :func:`fit_exposure`), float32
    ``[H, W]``.

    Forward-backward consistency misses flows that are wrong the same way in both directions (weak or
    repetitive texture, large perspective shear such as the near road); their photometric residual is several
    times that of correct flows.
    """
    h, w = g0.shape
    _, _, xy = _grids(h, w)
    pos = cv2.add(xy, flow)
    warped = cv2.remap(g1, pos, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    g0f, g1w = g0.astype(np.float32), warped.astype(np.float32)
    diff = cv2.subtract(g1w, g0f)
    offset = float(np.median(diff[::4, ::4]))
    s0, s1 = g0f[::4, ::4], g1w[::4, ::4]
    unclipped = (s0 > 1) & (s0 < 254) & (s1 > 1) & (s1 < 254)  # a saturated pixel is no sample of the gain
    gain, off = fit_exposure(s0[unclipped], s1[unclipped])
    if gain != 1.0:
        offset = off
        diff = cv2.subtract(g1w, cv2.multiply(g0f, gain))
    r = cv2.blur(np.abs(diff - offset), (window, window))
    return cv2.exp(cv2.multiply(r, r, scale=-1.0 / (2.0 * sigma * sigma)))


def fit_exposure(g0: np.ndarray, g1: np.ndarray, max_gain: float = 4.0, min_gain_gain: float = 0.75,
                 min_corr: float = 0.6) -> tuple[float, float]:
    """Robust ``(gain, offset)`` with ``g1 ~ gain * g0 + offset`` over matched pixel samples (float32 arrays of one
    shape).  The median difference (gain 1) is the answer unless a gain explains the samples markedly better:
    least squares on the samples within 3 MADs of the offset model, then once more within 3 MADs of that fit
    (occlusions and wrong matches are the outliers), kept only when it brings the residuals' MAD below
    ``min_gain_gain`` x the offset model's and the samples' correlation is at least ``min_corr``.  Why: an
    auto-exposure step scales the brightness, and with the offset alone every textured pixel of a pair across the
    step looks like a wrong match; why the gates: where the exposure is constant a fitted gain only follows the
    scene's content or a wrong flow (docs/decisions.md: fit_exposure)."""
    x, y = g0.reshape(-1).astype(np.float64), g1.reshape(-1).astype(np.float64)
    if x.size == 0:
        return 1.0, 0.0
    d = y - x
    offset = float(np.median(d))
    # (medians of temporaries partition them in place: the same order statistics, no copy)
    mad0 = float(np.median(np.abs(d - offset), overwrite_input=True))
    gain, off = 1.0, offset
    for _ in range(2):
        a = np.abs(y - (gain * x + off))
        keep = a <= 3.0 * 1.4826 * float(np.median(a)) + 1.0
        n = int(keep.sum())
        xk = x[keep]
        if n < 16 or float(np.std(xk)) < 1.0:  # too few samples or no contrast: offset only
            return 1.0, offset
        A = np.stack([xk, np.ones(n)], 1)
        (g, o), *_ = np.linalg.lstsq(A, y[keep], rcond=None)
        if not (1.0 / max_gain <= g <= max_gain and np.isfinite(o)):
            return 1.0, offset
        gain, off = float(g), float(o)
    mad1 = float(np.median(np.abs(y - (gain * x + off)), overwrite_input=True))
    if not mad1 < min_gain_gain * mad0:
        return 1.0, offset
    # a wrong flow pairs unrelated pixels, and a least-squares gain fitted to them shrinks towards 0 with a weak
    # correlation; matched pixels under an exposure change follow a line
    corr = float(np.corrcoef(x, y)[0, 1])
    return (gain, off) if corr >= min_corr else (1.0, offset)


def texture_confidence(gray: np.ndarray, tau: float, block: int = 5, quantile: Optional[float] = None) -> np.ndarray:
    """``lam / (lam + tau)`` with ``lam`` the smaller eigenvalue of the local structure tensor (Shi-Tomasi),
    float32 ``[H, W]`` in [0, 1).  Flow in textureless regions (sky, flat walls) is an aperture-problem guess:
    DIS answers ~zero flow there consistently in both directions, which the forward-backward check cannot
    catch, and such pixels would otherwise dominate the BA (they are most of the confident pixels outdoors).

    With ``quantile``, ``tau`` is at most that quantile of the image's own ``lam``: an image whose texture is weak
    everywhere (a bare room) keeps its better-textured pixels at useful weights instead of scaling every weight
    down below the confidence thresholds downstream.
    """
    lam = cv2.cornerMinEigenVal(gray, blockSize=block, ksize=3)
    lam = np.maximum(lam, 0.0)  # OpenCV normalises by the kernel size and 255: ~1e-4 on textured regions
    if quantile is not None:
        tau = min(tau, max(float(np.quantile(lam, quantile)), 1e-12))
    return (lam / (lam + tau)).astype(np.float32)


class TextureTerm:
    """:func:`texture_confidence` of source images, computed once per image object: a keyframe's gray is the source
    of its tracking flows and of every edge out of it.  Bounded (``size`` images, about the active keyframes; older
    ones are rarely sources again).  Thread-safe enough for the frontend's flow lanes: a race computes twice."""

    def __init__(self, tau: float, quantile: Optional[float] = None, size: int = 32):
        self.tau, self.quantile, self.size = float(tau), quantile, int(size)
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # id(gray) -> (gray, term)

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        hit = self._cache.get(id(gray))
        if hit is not None and hit[0] is gray:
            return hit[1]
        term = texture_confidence(gray, self.tau, quantile=self.quantile)
        if len(self._cache) >= self.size:
            self._cache.clear()
        self._cache[id(gray)] = (gray, term)
        return term

    def nbytes(self) -> int:
        return sum(g.nbytes + t.nbytes for g, t in list(self._cache.values()))
