"""Chunked Schur-complement assembly for :func:`pvslam_core.geometry.ba.dense_ba`.

The depth unknowns of one *source* keyframe (the ``ii`` of its edges) couple only the edges of that source, so
the reduced pose system ``S = B - E C^-1 E^T`` is a sum of independent per-source contributions and the
back-substitution ``dd = C^-1 (w - E^T dxi)`` is per source as well.  :func:`plan_chunks` groups the edges into
chunks of whole sources (consecutive depth slots, at most ``max_chunk_pixels`` edge-pixels per chunk unless
one source alone is larger) followed by chunks of fixed-depth edges (split by edge); every chunk carries its
static index plans (its sources grouped by edge count, pairs of edges sharing a source, scatter destinations in
the ``[F*F, 36]`` pose matrix and the ``[F, 6]`` rhs).  :func:`assemble_chunk` turns one chunk's linearisation into
its pose blocks, reduced gradients and per-source ``C^-1``, ``w``; :func:`depth_rows` / :func:`backsub_chunk`
recover the depth increments of a chunk.  Nothing here loops over edges or pixels.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Optional, Union

import torch

__all__ = ["Chunk", "plan_chunks", "assemble_chunk", "pose_blocks", "depth_rows", "backsub_chunk", "rowvec"]


@dataclass
class Chunk:
    """One chunk of edges: the first ``n_src`` have their source depth unknown (depth slots ``[s0, s1)``), grouped
    by source and the sources ordered by their number of edges (``buckets``), the rest have a fixed source depth."""

    idx: Union[slice, torch.Tensor]  # rows of the chunk's edges in the [E, ...] edge arrays
    ii: torch.Tensor
    jj: torch.Tensor
    n_src: int  # edges with an unknown source depth (the first ones of the chunk)
    s0: int
    s1: int
    ls: Optional[torch.Tensor]  # local depth slot of each source edge
    # (c, first row, end row): the sources with exactly c edges in this chunk, consecutive rows [c * sources]
    buckets: list
    pa: Optional[torch.Tensor]  # pairs of edges (a, b) sharing a source (every ordered pair, a == b too): rows
    pb: Optional[torch.Tensor]
    H_sel: list
    H_dest: Optional[torch.Tensor]
    v_sel: list
    v_dest: Optional[torch.Tensor]

    @property
    def ns(self) -> int:
        return self.s1 - self.s0


def _plan(terms, F: int):
    """Entries with both block indices >= 0 of each ``(row, col)`` term, and their rows in ``[F * F]``."""
    sels, dests = [], []
    for r_, c_ in terms:
        sel = torch.nonzero((r_ >= 0) & (c_ >= 0)).squeeze(1)
        sels.append(sel)
        dests.append(r_[sel] * F + c_[sel])
    return sels, torch.cat(dests)


def plan_chunks(ii: torch.Tensor, jj: torch.Tensor, pose_map: torch.Tensor, es: torch.Tensor, Ns: int, F: int,
                P: int, max_chunk_pixels: int) -> list[Chunk]:
    """Split the edges into chunks of at most ``max_chunk_pixels // P`` edges (whole sources; a source with more
    edges is a chunk of its own).  ``es``: depth slot of each edge's source (-1: fixed depth), ``pose_map``:
    free-pose slot of each keyframe (-1: fixed).  Chunks with fixed-depth edges only come first."""
    dev = ii.device
    E = int(ii.shape[0])
    has = es >= 0
    e_src = torch.nonzero(has).squeeze(1)
    order = e_src[torch.argsort(es[e_src], stable=True)]
    perm = torch.cat([order, torch.nonzero(~has).squeeze(1)])
    counts = torch.bincount(es[order], minlength=Ns) if Ns > 0 else torch.zeros(0, dtype=torch.int64, device=dev)
    # units: one per source (its edges), then one per fixed-depth edge; cum[u] = edges before unit u
    cum = [0] + torch.cumsum(torch.cat([counts, torch.ones(E - len(order), dtype=torch.int64, device=dev)]),
                             0).tolist()
    U, budget = len(cum) - 1, max(1, int(max_chunk_pixels) // max(P, 1))
    chunks: list[Chunk] = []
    u0 = 0
    while u0 < U:
        u1 = max(bisect.bisect_right(cum, cum[u0] + budget) - 1, u0 + 1)
        chunks.append(_make_chunk(ii, jj, pose_map, es, counts, perm, cum, u0, u1, Ns, F))
        u0 = u1
    # fixed-depth chunks first, the largest source chunk last (its E^T is kept for the back-substitution)
    return [c for c in chunks if c.ns == 0] + sorted((c for c in chunks if c.ns > 0), key=lambda c: c.n_src)


def _make_chunk(ii, jj, pose_map, es, counts, perm, cum, u0, u1, Ns, F) -> Chunk:
    dev = ii.device
    e0, e1 = cum[u0], cum[u1]
    s0, s1 = min(u0, Ns), min(u1, Ns)
    n_src = cum[s1] - cum[s0]
    ce = perm[e0:e1]
    ns = s1 - s0
    ls, buckets, pa, pb = None, [], None, None
    if ns > 0:
        # sources with the same number of edges c are consecutive, so that E^T C^-1 E of all their pairs is one
        # batched matmul of [sources, 6c, P] rows without padding (padding to the largest source computed 2.4x the
        # needed pair blocks on the driving loop's window)
        cnt = counts[s0:s1]
        ls0 = es[ce[:n_src]] - s0
        key = cnt[ls0] * ns + ls0
        ce = torch.cat([ce[:n_src][torch.argsort(key, stable=True)], ce[n_src:]])
        ls = es[ce[:n_src]] - s0
        pa_l, pb_l = [], []
        b0 = 0
        sizes, n_srcs = torch.unique_consecutive(torch.sort(cnt).values, return_counts=True)
        for c, n_c in zip(sizes.tolist(), n_srcs.tolist()):
            if c == 0:  # a depth slot without edges: no rows, no pairs
                continue
            b1 = b0 + c * n_c
            buckets.append((c, b0, b1))
            base = (b0 + torch.arange(n_c, device=dev) * c).view(-1, 1, 1)  # first row of each source
            ar = torch.arange(c, device=dev)
            pa_l.append((base + ar.view(1, -1, 1)).expand(n_c, c, c).reshape(-1))  # pair (s, a, b) in that order
            pb_l.append((base + ar.view(1, 1, -1)).expand(n_c, c, c).reshape(-1))
            b0 = b1
        pa, pb = torch.cat(pa_l), torch.cat(pb_l)
    n = e1 - e0
    contiguous = bool((ce == torch.arange(int(ce[0]), int(ce[0]) + n, device=dev)).all())
    idx = slice(int(ce[0]), int(ce[0]) + n) if contiguous else ce
    ii_c, jj_c = ii[idx], jj[idx]
    pi_c, pj_c = pose_map[ii_c], pose_map[jj_c]
    pair_terms = []
    if ns > 0:
        # -M_ab at (jj_a, jj_b) per pair; the couplings with the source pose are summed per edge (assemble_chunk)
        pk_e, pj_e = pi_c[:n_src], pj_c[:n_src]
        pair_terms = [(pj_c[pa], pj_c[pb]), (pk_e, pj_e), (pj_e, pk_e), (pk_e, pk_e)]
    H_sel, H_dest, v_sel, v_dest = [], None, [], None
    if F > 0:
        H_sel, H_dest = _plan([(pi_c, pi_c), (pj_c, pj_c), (pi_c, pj_c), (pj_c, pi_c)] + pair_terms, F)
        zero = torch.zeros_like(pi_c)
        v_sel, v_dest = _plan([(pj_c, zero), (pi_c, zero)], F)
        v_dest = torch.div(v_dest, F, rounding_mode="floor")
    return Chunk(idx, ii_c, jj_c, n_src, s0, s1, ls, buckets, pa, pb, H_sel, H_dest, v_sel, v_dest)


def depth_rows(ch: Chunk, JuT, JvT, bu, bv, sC) -> torch.Tensor:
    """``E^T C^-1/2``: the depth rows of the chunk's source edges ``[n_src, 6, P]`` (row ``k`` of edge ``e``: pose
    coordinate ``k`` of ``e``), scaled by ``sC = C^-1/2 [ns, P]`` of the edge's source.
    ``bu, bv = w Jd [n_src, P]``."""
    m = ch.n_src
    s = sC[ch.ls]
    rows = JuT[:m] * (bu * s).unsqueeze(1)
    rows.addcmul_(JvT[:m], (bv * s).unsqueeze(1))
    return rows


def _pair_blocks(ch: Chunk, B: torch.Tensor) -> torch.Tensor:
    """``M_ab = sum_p Ej_a C^-1 Ej_b^T [pairs, 6, 6]`` for every pair of ``ch.pa, ch.pb`` (the order of the plan):
    one batched matmul per bucket of sources with ``c`` edges, ``[sources, 6c, P] x [sources, P, 6c]``."""
    P = B.shape[-1]
    out = []
    for c, b0, b1 in ch.buckets:
        R = B[b0:b1].reshape(-1, 6 * c, P)
        out.append(torch.bmm(R, R.transpose(1, 2)).view(-1, c, 6, c, 6).permute(0, 1, 3, 2, 4).reshape(-1, 6, 6))
    return out[0] if len(out) == 1 else torch.cat(out)


def rowvec(x: torch.Tensor, JT: torch.Tensor) -> torch.Tensor:
    """``JT [E, k, P] @ x [E, P] -> [E, k]``, as ``x^T JT^T``: the row-vector product takes the BLAS gemm path, the
    matrix-vector ``bmm(JT, x[..., None])`` a slow one (0.64 vs 0.05 ms at [100, 6, 1200])."""
    return torch.bmm(x.unsqueeze(1), JT.transpose(1, 2)).squeeze(1)


def assemble_chunk(ch: Chunk, ru, rv, wu, wv, out, eta_c, F: int, want_B: bool, wd0=None):
    """One chunk's contribution: ``(blocks, q, Ad, Cinv, wd, B)``.

    ``blocks``: float64 ``6 x 6`` blocks aligned with ``ch.H_sel``; ``q [Ec, 6]``: reduced gradient of pose ``jj``
    of each edge (that of ``ii`` is ``-Ad^T q``); ``Cinv, wd [ns, P]``: inverse depth diagonal and depth gradient
    of the chunk's sources (None without sources; ``wd0 [ns, P]``: a depth gradient to start from, the disparity
    prior's); ``B``: :func:`depth_rows` (only with ``want_B``).  The
    Jacobians in ``out`` are scaled in place (by ``sqrt(w)``): ``out`` is spent afterwards."""
    JuT, JvT, Jdu, Jdv = out["JuT"], out["JvT"], out["Jdu"], out["Jdv"]  # [Ec, 6, P] x2, [Ec, P] x2
    Ad = out["Ad"].double()  # [Ec, 6, 6];  Ji = -Jj Ad is never formed
    blocks, q, Cinv, wd, B, sC = [], None, None, None, None, None
    m = ch.n_src
    if ch.ns > 0:
        bu, bv = wu[:m] * Jdu[:m], wv[:m] * Jdv[:m]
        C = eta_c.clone()
        C.index_add_(0, ch.ls, bu * Jdu[:m] + bv * Jdv[:m])
        wd = torch.zeros_like(C) if wd0 is None else wd0.to(C.dtype, copy=True)
        wd.index_add_(0, ch.ls, bu * ru[:m] + bv * rv[:m])
        Cinv = 1.0 / C.clamp(min=1e-12)
        del C
        if F > 0:
            sC = Cinv.sqrt()
            B = depth_rows(ch, JuT, JvT, bu, bv, sC)
        del bu, bv
    if F > 0:
        # pose-pose blocks and pose gradients: J^T W J with the rows scaled by sqrt(w) in place (no W J^T copy)
        su, sv = wu.sqrt(), wv.sqrt()
        JuT.mul_(su.unsqueeze(1))
        JvT.mul_(sv.unsqueeze(1))
        Hjj = (torch.bmm(JuT, JuT.transpose(1, 2)) + torch.bmm(JvT, JvT.transpose(1, 2))).double()
        q = (rowvec(su * ru, JuT) + rowvec(sv * rv, JvT)).double()
        del su, sv
        blocks, q = pose_blocks(ch, Hjj, q, Ad, B, sC, wd)
    return blocks, q, Ad, Cinv, wd, (B if want_B else None)


def pose_blocks(ch: Chunk, Hjj: torch.Tensor, q: torch.Tensor, Ad: torch.Tensor, B: Optional[torch.Tensor], sC,
                wd) -> tuple[list, torch.Tensor]:
    """The chunk's ``6 x 6`` blocks aligned with ``ch.H_sel`` and its reduced gradients ``q [Ec, 6]`` (float64)
    from each edge's ``Hjj = J^T W J``, ``q = J^T W r`` (d / d xi_j), the adjoints ``Ad [Ec, 6, 6]`` and, for a
    chunk with depth unknowns, its depth rows ``B`` (:func:`depth_rows`), ``sC = C^-1/2`` and ``wd``."""
    m = ch.n_src
    AdT = Ad.transpose(1, 2)
    Hij = -torch.bmm(AdT, Hjj)
    blocks = [-torch.bmm(Hij, Ad), Hjj, Hij, Hij.transpose(1, 2)]
    if B is not None:
        # g_e = sum_p Ej C^-1 w:  reduced gradients v[jj] -= g, v[ii] += Ad^T g
        g = rowvec((sC * wd)[ch.ls], B).double()
        q = torch.cat([q[:m] - g, q[m:]])
        # M_ab = sum_p Ej_a C^-1 Ej_b^T for all pairs of edges of one source k; with Ei = -Ej Ad the pair adds
        # -M_ab at (jj_a, jj_b), Ad_a^T M_ab at (k, jj_b), M_ab Ad_b at (jj_a, k), -Ad_a^T M_ab Ad_b at (k, k).
        # The last three are summed per edge before scattering: Y_b = sum_a Ad_a^T M_ab at (k, jj_b), its
        # transpose at (jj_b, k) (M_ba = M_ab^T) and -Y_b Ad_b at (k, k) (one [pairs] and one [edges] 6x6
        # product instead of three [pairs] ones, and a third of the blocks to scatter)
        M = _pair_blocks(ch, B).double()  # [pairs, 6, 6]
        Y = torch.zeros(m, 6, 6, dtype=M.dtype, device=M.device).index_add_(0, ch.pb, torch.bmm(AdT[ch.pa], M))
        blocks += [-M, Y, Y.transpose(1, 2), -torch.bmm(Y, Ad[:m])]
    return blocks, q


def backsub_chunk(ch: Chunk, B: torch.Tensor, Ad: torch.Tensor, xi_full: torch.Tensor, Cinv: torch.Tensor,
                  wd: torch.Tensor) -> torch.Tensor:
    """Depth increments ``dd = C^-1 (w - sum_e Ej (dxi_jj - Ad dxi_ii))`` of the chunk's sources ``[ns, P]``
    (``B``: :func:`depth_rows`, i.e. ``E^T C^-1/2``)."""
    m = ch.n_src
    y = xi_full[ch.jj[:m]] - torch.bmm(Ad[:m], xi_full[ch.ii[:m]].unsqueeze(-1)).squeeze(-1)  # [m, 6]
    ey = torch.bmm(y.to(B.dtype).unsqueeze(1), B).squeeze(1)  # [m, P]: y_e^T E_e^T C^-1/2 of each edge
    acc = torch.zeros_like(wd).index_add_(0, ch.ls, ey)
    return Cinv * wd - Cinv.sqrt() * acc
