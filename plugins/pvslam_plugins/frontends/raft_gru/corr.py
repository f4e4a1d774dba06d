"""Correlation pyramid and lookup (DROID-SLAM ``CorrBlock`` / ``AltCorrBlock``), in plain torch.

Definitions (shapes for one batch element ``b`` and edge ``e = (ii[e] -> jj[e])``; ``h, w`` = 1/8 image size):

* level 0: ``C0[y1, x1, y2, x2] = <f_ii[:, y1, x1] / 4, f_jj[:, y2, x2] / 4>`` - each map is divided by 4 *before*
  the product (dot / 16, not RAFT's 1/sqrt(C); it also keeps fp16 products in range under autocast);
* level l: level l-1 average-pooled 2x2, stride 2, over the **target** dims, floor for odd sizes (17, 8, 4, 2);
* lookup at ``coords1[y1, x1] = (x, y)`` (target-frame pixels, 1/8 resolution): channel ``l*49 + a*7 + b``
  samples level ``l`` at ``(x / 2**l - 3 + a, y / 2**l - 3 + b)`` - the outer window index ``a`` runs over
  **x** (x-major, although volumes are indexed [y][x]) - bilinearly with pixel centres at integers and zeros
  outside the map (``grid_sample(align_corners=True, padding_mode="zeros")``).  Level coordinates are
  ``coords / 2**l`` (not the half-pixel-corrected ``(coords + 0.5) / 2**l - 0.5``), as upstream.

Why not ``grid_sample`` itself: it is the same function, but its coordinate normalisation round trip
(``2x/(W-1) - 1`` and back) moves the sample by up to ~1e-6 px, which on the golden fixture costs up to 1.3e-5
(even in float64 it is 7e-6 away, because upstream's CUDA kernel forms its weights differently).  Both paths
here use the kernel's own arithmetic instead (:func:`_bilinear`): the ``(2r+2)**2`` integer positions around
``floor(x) - r``, weights ``dx*dy, ...`` from ``dx = x - floor(x)`` in the input dtype, summed in the kernel's
order; the tests keep ``grid_sample`` as an independent reference (agreement ~1e-5).

Two implementations with the same interface (``corr(coords1) -> (B, E, L*(2r+1)**2, h, w)``, ``select``, ``cat``,
``num_edges``):

* :class:`CorrVolume` stores the full pyramid, ``4 * h*w * h*w * 1.33`` bytes per edge at float32 (7.7 MB at
  320x240): one batched matmul per edge set, then each lookup is a cheap gather of ``(2r+2)**2`` values per
  pixel and level.  The choice when the same edges are looked up many times (frontend iterations).
* :class:`OnTheFlyCorr` stores only the per-frame feature pyramid (pooling the features equals pooling the
  volume: both are linear) and computes, per lookup and in chunks of bounded memory, either a level's
  correlation rows by matmul (small target maps) or only the ``(2r+2)**2`` integer-window correlations each pixel
  needs (large ones, DROID's ``altcorr``).  Nothing of size ``(h*w)**2`` per edge is kept; for many edges or large
  images (global BA), where stored volumes would not fit.

Gradients: like upstream's CUDA samplers, the lookup gives no gradient to ``coords`` (they are detached);
gradients reach the volume / feature maps.

Minimum size: with ``L`` levels the coarsest target level must be >= 2 px in both dims, i.e. the 1/8 map must be
>= ``2**L`` px (16 for 4 levels: images >= 128 x 128), which is also upstream's limit.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch
import torch.nn.functional as F

NUM_LEVELS = 4
RADIUS = 3
FMAP_SCALE = 4.0  # each feature map is divided by this before the dot product (upstream: / 4.0 each)


def coords_grid(ht: int, wd: int, device=None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Pixel grid ``(ht, wd, 2)``: ``[..., 0] = x`` (column), ``[..., 1] = y`` (row) (upstream ``coords_grid``)."""
    y, x = torch.meshgrid(
        torch.arange(ht, device=device, dtype=dtype), torch.arange(wd, device=device, dtype=dtype), indexing="ij"
    )
    return torch.stack([x, y], dim=-1)


def lookup_channels(num_levels: int = NUM_LEVELS, radius: int = RADIUS) -> int:
    """Number of lookup channels ``L * (2r+1)**2`` (196 for the defaults)."""
    return num_levels * (2 * radius + 1) ** 2


def check_level_size(ht: int, wd: int, num_levels: int) -> None:
    """Raise if the coarsest level of an ``ht x wd`` map would be smaller than 2 px (see module doc)."""
    k = 2 ** (num_levels - 1)
    if ht // k < 2 or wd // k < 2:
        raise ValueError(
            f"feature map {ht}x{wd} (1/8 resolution) is too small for {num_levels} correlation levels: the "
            f"coarsest level would be {ht // k}x{wd // k}; need >= {2 * k} px per side (images >= {16 * k} px)"
        )


def _window(xy: torch.Tensor, radius: int, ht: int, wd: int):
    """Integer window of the lookup at ``xy (R, 2)`` (level coordinates) on an ``ht x wd`` map.

    Returns ``flat (R, K, K)`` clamped flat indices ``y * wd + x`` (dims: x-offset, y-offset; ``K = 2r+2``),
    ``ok (R, K, K)`` in-map flags, and the fractions ``dx, dy (R, 1, 1)``.
    """
    x0, y0 = xy[:, 0].floor(), xy[:, 1].floor()
    dx, dy = (xy[:, 0] - x0)[:, None, None], (xy[:, 1] - y0)[:, None, None]
    offs = torch.arange(-radius, radius + 2, device=xy.device)
    ix = x0.long()[:, None] + offs  # (R, K) window columns
    iy = y0.long()[:, None] + offs  # (R, K) window rows
    ok = ((ix >= 0) & (ix < wd))[:, :, None] & ((iy >= 0) & (iy < ht))[:, None, :]
    flat = iy.clamp(0, ht - 1)[:, None, :] * wd + ix.clamp(0, wd - 1)[:, :, None]
    return flat, ok, dx, dy


def _bilinear(win: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
    """Bilinear lookups from integer-window values ``win (R, K, K)`` [x-offset, y-offset] -> ``(R, (K-1)**2)``.

    Output channel ``a * (K-1) + b`` (x-major) samples ``(floor(x) - r + a + dx, floor(y) - r + b + dy)``.  The
    four corner terms are added in the order of DROID's ``corr_index`` kernel loop.
    """
    k = win.shape[1] - 1
    out = (
        win[:, :k, :k] * ((1 - dx) * (1 - dy))
        + win[:, :k, 1:] * ((1 - dx) * dy)
        + win[:, 1:, :k] * (dx * (1 - dy))
        + win[:, 1:, 1:] * (dx * dy)
    )
    return out.reshape(-1, k * k)


def _lookup_level(vol: torch.Tensor, xy: torch.Tensor, radius: int, ht: int, wd: int) -> torch.Tensor:
    """Bilinear window lookup on one pyramid level: ``vol (R, ht*wd)`` rows, ``xy (2, R)`` level coordinates
    (compute dtype) -> ``(k*k, R)``, channel ``a*k + b`` (x-major), ``k = 2r+1``.

    The same arithmetic as :func:`_window` + :func:`_bilinear` (same products, same order of the four corner terms:
    bitwise equal results), laid out with the pixel index ``R`` innermost so that every elementwise op runs over
    contiguous rows with per-pixel weights broadcast along them (the ``(R, k, k)`` layout made each of the 16
    multiplications a slow strided broadcast, a large share of the lookup time).
    """
    x0, y0 = xy[0].floor(), xy[1].floor()
    dx, dy = xy[0] - x0, xy[1] - y0  # (R,)
    offs = torch.arange(-radius, radius + 2, device=xy.device)[:, None]
    ix = x0.long()[None] + offs  # (K, R) window columns
    iy = y0.long()[None] + offs  # (K, R) window rows
    # in-map flags as 0/1 factors (K, K, R) [x-offset, y-offset, pixel]: multiplying by them equals upstream's
    # "outside contributes 0" (the volume is finite) at a tenth of the cost of torch.where on a bool mask
    okx = ((ix >= 0) & (ix < wd)).to(xy.dtype)
    oky = ((iy >= 0) & (iy < ht)).to(xy.dtype)
    ok = okx[:, None] * oky[None]
    flat = iy.clamp(0, ht - 1)[None] * wd + ix.clamp(0, wd - 1)[:, None]
    kk, rows = flat.shape[0], flat.shape[-1]
    flat = flat + torch.arange(0, rows * ht * wd, ht * wd, device=flat.device)  # row offsets into vol.view(-1)
    # one flat index_select: ~7x faster than gather over the transposed rows (and 1.5x than gather + transpose)
    win = vol.reshape(-1).index_select(0, flat.view(-1)).view(kk, kk, rows).to(xy.dtype) * ok
    k = kk - 1
    out = (
        win[:k, :k] * ((1 - dx) * (1 - dy))
        + win[:k, 1:] * ((1 - dx) * dy)
        + win[1:, :k] * (dx * (1 - dy))
        + win[1:, 1:] * (dx * dy)
    )
    return out.reshape(k * k, -1)


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """Dtype of the bilinear arithmetic for a volume of ``dtype``: float32 for 16-bit volumes (bf16 elementwise ops
    are slow on CPUs and would round the sub-pixel weights and every partial sum to 8 bits), else ``dtype``."""
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def _check_coords(coords: torch.Tensor, batch: int, edges: int, ht: int, wd: int) -> None:
    if coords.shape != (batch, edges, ht, wd, 2):
        raise ValueError(f"coords1 must be (B, E, h, w, 2) = {(batch, edges, ht, wd, 2)}, got {tuple(coords.shape)}")


class CorrVolume:
    """Full correlation pyramid for ``E`` edges (upstream ``CorrBlock``).

    ``pyramid[l]``: ``(B, E, h, w, h2 // 2**l, w2 // 2**l)``.  Build it with :meth:`from_edges` (per-frame
    features + edge lists) or directly from paired maps ``fmap1 = fmaps[:, ii]``, ``fmap2 = fmaps[:, jj]``.
    """

    def __init__(
        self, fmap1: torch.Tensor, fmap2: torch.Tensor, num_levels: int = NUM_LEVELS, radius: int = RADIUS,
        pool: str = "volume",
    ) -> None:
        """``pool="volume"``: levels 1.. average-pool the level-0 volume (upstream's order of operations, the
        golden fixture's numbers bit for bit); ``"features"``: each level is the product of the source features
        with the pooled target features - the same quantity (both are linear; the /4 scaling is exact), other
        rounding (fp32 ~1e-6), and ~4x cheaper on a CPU (pooling the (h w)**2 volume costs more than the matmul)."""
        if pool not in ("volume", "features"):
            raise ValueError(f"pool must be 'volume' or 'features', got {pool!r}")
        if fmap1.dim() != 5 or fmap1.shape[:3] != fmap2.shape[:3]:
            raise ValueError(
                "fmap1/fmap2 must be (B, E, C, h, w) with equal B, E, C; "
                f"got {tuple(fmap1.shape)}, {tuple(fmap2.shape)}"
            )
        b, e, c, h1, w1 = fmap1.shape
        h2, w2 = fmap2.shape[-2:]
        check_level_size(h2, w2, num_levels)
        self.num_levels, self.radius = num_levels, radius
        # (B*E, h1*w1, h2*w2): one batched matmul; the /4 on each map as upstream.
        f1 = fmap1.reshape(b * e, c, h1 * w1) / FMAP_SCALE
        f2 = fmap2.reshape(b * e, c, h2 * w2) / FMAP_SCALE
        self.pyramid: list[torch.Tensor] = []
        if pool == "features":
            f1t, f2 = f1.transpose(1, 2), f2.view(b * e, c, h2, w2)
            for i in range(num_levels):
                hl, wl = f2.shape[-2:]
                self.pyramid.append(torch.matmul(f1t, f2.reshape(b * e, c, hl * wl)).view(b, e, h1, w1, hl, wl))
                if i + 1 < num_levels:  # pooled in (at least) fp32, as avg_pool2d accumulates a 16-bit volume
                    f2 = F.avg_pool2d(f2.to(_compute_dtype(f2.dtype)), 2, stride=2).to(f1t.dtype)
            return
        corr = torch.matmul(f1.transpose(1, 2), f2)
        corr = corr.reshape(b * e * h1 * w1, 1, h2, w2)
        for i in range(num_levels):
            self.pyramid.append(corr.view(b, e, h1, w1, *corr.shape[-2:]))
            if i + 1 < num_levels:  # upstream pools once more after the last level; that result is unused
                corr = F.avg_pool2d(corr, 2, stride=2)

    @classmethod
    def from_edges(
        cls, fmaps: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor, num_levels: int = NUM_LEVELS, radius: int = RADIUS
    ) -> "CorrVolume":
        """Volumes of edges ``ii[e] -> jj[e]`` from per-frame features ``fmaps (B, N, C, h, w)``."""
        ii, jj = ii.to(fmaps.device), jj.to(fmaps.device)
        return cls(fmaps[:, ii], fmaps[:, jj], num_levels, radius)  # pool="volume": upstream's order

    @property
    def num_edges(self) -> int:
        return self.pyramid[0].shape[1]

    def __call__(self, coords1: torch.Tensor) -> torch.Tensor:
        """Lookup at ``coords1 (B, E, h, w, 2)`` (x, y) -> ``(B, E, L*(2r+1)**2, h, w)``."""
        b, e, h1, w1 = self.pyramid[0].shape[:4]
        _check_coords(coords1, b, e, h1, w1)
        n, k = b * e * h1 * w1, 2 * self.radius + 1
        dtype = self.pyramid[0].dtype
        cdt = _compute_dtype(dtype)
        # coordinates never in 16 bits (bf16 has 1/4 px steps at 32..64 px); (2, n) so that pixels are innermost
        xy = coords1.detach().reshape(n, 2).to(cdt).t()
        out = torch.cat([_lookup_level(vol.reshape(n, -1), xy / 2**i, self.radius, *vol.shape[-2:])
                         for i, vol in enumerate(self.pyramid)])  # (L*k*k, n)
        out = out.view(-1, b, e, h1, w1).permute(1, 2, 0, 3, 4)
        return out.to(dtype).contiguous()

    def select(self, index) -> "CorrVolume":
        """The volumes of a subset of edges (``index``: indices / bool mask over E); shares storage when possible."""
        new = object.__new__(CorrVolume)
        new.num_levels, new.radius = self.num_levels, self.radius
        new.pyramid = [v[:, index] for v in self.pyramid]
        return new

    def cat(self, other: "CorrVolume") -> "CorrVolume":
        """Edges of ``self`` followed by those of ``other`` (a new object)."""
        new = object.__new__(CorrVolume)
        new.num_levels, new.radius = self.num_levels, self.radius
        new.pyramid = [torch.cat([a, c], dim=1) for a, c in zip(self.pyramid, other.pyramid)]
        return new

    def nbytes(self) -> int:
        return sum(v.numel() * v.element_size() for v in self.pyramid)


class OnTheFlyCorr:
    """Memory-light correlation lookup: per-frame feature pyramid + edge lists, no stored volume.

    Args:
        fmaps: ``(B, N, C, h, w)`` per-frame matching features (``fnet`` output).
        ii, jj: ``(E,)`` source / target frame indices into ``N``.
        chunk_mb: working-memory budget of one chunk (see below); the output itself is extra.
        dense_max_pixels: levels whose target map has at most this many pixels are computed densely per chunk.
        fmaps_target: optional different per-frame maps for the targets (default ``fmaps``).

    Each level is computed in one of two ways, both within ``chunk_mb`` and both giving the volume path's numbers
    (to float rounding: here the *features* are pooled, which equals pooling the volume):

    * **window** (large target maps): for each edge-pixel, gather the target features at the ``(2r+2)**2``
      integer positions around ``floor(coords / 2**l) - r``, dot them with the source feature, combine the
      neighbours bilinearly (DROID's ``altcorr``).  Cost per lookup ``E*h*w * (2r+2)**2 * C``, independent of
      the image size per pixel; memory-bound gathers.
    * **dense** (small target maps, ``h_l*w_l <= dense_max_pixels``): the level's correlation rows of a chunk of
      edges, ``(edges, h*w, h_l*w_l)``, by one batched matmul, then the window lookup on them; discarded after.
      Cost ``E*h*w * h_l*w_l * C`` but at matmul speed: on a 2-core CPU it beats the window gather by ~9x at
      320x240 (level 0 has 1200 target pixels), hence the default: dense up to 8192 (a 1/8 map of ~90x90).
    """

    def __init__(
        self,
        fmaps: torch.Tensor,
        ii: torch.Tensor,
        jj: torch.Tensor,
        num_levels: int = NUM_LEVELS,
        radius: int = RADIUS,
        chunk_mb: float = 32.0,
        dense_max_pixels: int = 8192,
        fmaps_target: Optional[torch.Tensor] = None,
    ) -> None:
        if fmaps.dim() != 5:
            raise ValueError(f"fmaps must be (B, N, C, h, w), got {tuple(fmaps.shape)}")
        target = fmaps if fmaps_target is None else fmaps_target
        if target.shape[:3] != fmaps.shape[:3]:
            raise ValueError(f"fmaps_target {tuple(target.shape)} must share (B, N, C) with fmaps {tuple(fmaps.shape)}")
        b, n, c, h, w = target.shape
        check_level_size(h, w, num_levels)
        self.num_levels, self.radius = num_levels, radius
        self.chunk_mb, self.dense_max_pixels = chunk_mb, dense_max_pixels
        # Sources (B*N, h*w, C) and, per level, targets (B*N, h_l*w_l, C); all already divided by 4.
        self.src = (fmaps / FMAP_SCALE).flatten(3).transpose(2, 3).reshape(b * n, -1, c)
        self.levels: list[tuple[int, int, torch.Tensor]] = []
        f = target.reshape(b * n, c, h, w)
        for i in range(num_levels):
            hl, wl = f.shape[-2:]
            self.levels.append((hl, wl, (f / FMAP_SCALE).flatten(2).transpose(1, 2)))
            if i + 1 < num_levels:
                f = F.avg_pool2d(f, 2, stride=2)
        self.batch, self.frames, self.ht, self.wd = b, n, fmaps.shape[-2], fmaps.shape[-1]
        self.ii = ii.to(fmaps.device, torch.long)
        self.jj = jj.to(fmaps.device, torch.long)

    @property
    def num_edges(self) -> int:
        return int(self.ii.numel())

    def with_edges(self, ii: torch.Tensor, jj: torch.Tensor) -> "OnTheFlyCorr":
        """Same feature pyramid, other edges (no copy)."""
        new = object.__new__(OnTheFlyCorr)
        new.__dict__.update(self.__dict__)
        new.ii = ii.to(self.src.device, torch.long)
        new.jj = jj.to(self.src.device, torch.long)
        return new

    def select(self, index) -> "OnTheFlyCorr":
        return self.with_edges(self.ii[index], self.jj[index])

    def cat(self, other: "OnTheFlyCorr") -> "OnTheFlyCorr":
        if other.src is not self.src:
            raise ValueError("OnTheFlyCorr.cat needs both objects built on the same feature maps (use with_edges)")
        return self.with_edges(torch.cat([self.ii, other.ii]), torch.cat([self.jj, other.jj]))

    def __call__(self, coords1: torch.Tensor) -> torch.Tensor:
        """Lookup at ``coords1 (B, E, h, w, 2)`` -> ``(B, E, L*(2r+1)**2, h, w)`` (same numbers as CorrVolume)."""
        b, e, h, w = self.batch, self.num_edges, self.ht, self.wd
        _check_coords(coords1, b, e, h, w)
        k = 2 * self.radius + 1
        xy = coords1.detach().reshape(b * e, h * w, 2)
        bi = torch.arange(b, device=xy.device).repeat_interleave(e)
        src = bi * self.frames + self.ii.repeat(b)  # (B*E,) rows of self.src / level tables
        tgt = bi * self.frames + self.jj.repeat(b)
        out = xy.new_empty(self.num_levels, b * e, h * w, k * k, dtype=self.src.dtype)
        for lvl, (hl, wl, table) in enumerate(self.levels):
            level_xy = xy / 2**lvl
            if hl * wl <= self.dense_max_pixels:
                self._dense(out[lvl], level_xy, src, tgt, hl, wl, table)
            else:
                self._window(out[lvl], level_xy, src, tgt, hl, wl, table)
        # (L, B*E, h*w, k*k) -> (B, E, L*k*k, h, w)
        out = out.view(self.num_levels, b, e, h, w, k * k).permute(1, 2, 0, 5, 3, 4)
        return out.reshape(b, e, self.num_levels * k * k, h, w).contiguous()

    def _rows_per_chunk(self, bytes_per_row: int) -> int:
        return max(1, int(self.chunk_mb * 2**20) // max(1, bytes_per_row))

    def _dense(self, out, xy, src, tgt, hl, wl, table) -> None:
        """Level by batched matmul, ``(Ec, pc, C) @ (Ec, C, hl*wl)`` per chunk of edges (or of one edge's pixels
        when a whole edge exceeds the budget), then the window lookup on those rows."""
        m, p = xy.shape[:2]
        px_step = min(p, self._rows_per_chunk(hl * wl * table.element_size()))
        e_step = max(1, self._rows_per_chunk(px_step * hl * wl * table.element_size())) if px_step == p else 1
        for s in range(0, m, e_step):
            es = slice(s, min(m, s + e_step))
            f2t = table[tgt[es]].transpose(1, 2)  # (Ec, C, hl*wl)
            for q in range(0, p, px_step):
                ps = slice(q, min(p, q + px_step))
                vol = torch.bmm(self.src[src[es], ps], f2t)  # (Ec, pc, hl*wl) correlation rows
                flat, ok, dx, dy = _window(xy[es, ps].reshape(-1, 2), self.radius, hl, wl)
                win = vol.reshape(-1, hl * wl).gather(1, flat.reshape(flat.shape[0], -1)).view_as(ok)
                win = torch.where(ok, win, win.new_zeros(()))
                val = _bilinear(win, dx.to(win.dtype), dy.to(win.dtype))
                out[es, ps] = val.view(vol.shape[0], -1, out.shape[-1]).to(out.dtype)

    def _window(self, out, xy, src, tgt, hl, wl, table) -> None:
        """Level by gathering the ``(2r+2)**2`` window features per edge-pixel (chunks of edge-pixels)."""
        m, p = xy.shape[:2]
        c, kk = table.shape[-1], 2 * self.radius + 2
        rows = m * p
        flat_xy = xy.reshape(rows, 2)
        out = out.view(rows, -1)
        edge = torch.arange(m, device=xy.device).repeat_interleave(p)
        pix = torch.arange(p, device=xy.device).repeat(m)
        src_rows, tgt_rows = self.src.reshape(-1, c), table.reshape(-1, c)
        step = self._rows_per_chunk(kk * kk * c * table.element_size())
        for s in range(0, rows, step):
            sl = slice(s, min(rows, s + step))
            flat, ok, dx, dy = _window(flat_xy[sl], self.radius, hl, wl)
            win = tgt_rows[(tgt[edge[sl]] * (hl * wl))[:, None, None] + flat]  # (R, kk, kk, C), x-major
            f1 = src_rows[src[edge[sl]] * p + pix[sl]]  # (R, C)
            cw = torch.bmm(win.view(-1, kk * kk, c), f1[:, :, None]).view_as(ok)  # integer-window correlations
            cw = torch.where(ok, cw, cw.new_zeros(()))  # outside the map contributes 0
            out[sl] = _bilinear(cw, dx.to(cw.dtype), dy.to(cw.dtype)).to(out.dtype)


def make_corr(
    fmaps: torch.Tensor,
    ii: torch.Tensor,
    jj: torch.Tensor,
    impl: str = "volume",
    num_levels: int = NUM_LEVELS,
    radius: int = RADIUS,
    **kwargs,
):
    """``CorrVolume.from_edges`` (``impl="volume"``) or ``OnTheFlyCorr`` (``impl="onthefly"``)."""
    if impl == "volume":
        return CorrVolume.from_edges(fmaps, ii, jj, num_levels, radius)
    if impl == "onthefly":
        return OnTheFlyCorr(fmaps, ii, jj, num_levels, radius, **kwargs)
    raise ValueError(f"impl must be 'volume' or 'onthefly', got {impl!r}")


CORR_IMPLS: Sequence[str] = ("volume", "onthefly")
