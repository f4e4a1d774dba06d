"""The dense BA's per-pixel work on the CPU as compiled loops (numba): one pass per edge computes the residual, the
robust weight and the Jacobian rows of each pixel and sums them straight into the edge's ``6 x 6`` block ``J^T W J``,
its gradient ``J^T W r`` and its source's depth diagonal ``C`` and gradient ``w``; a second pass writes the depth rows
``E^T C^-1/2`` once ``C`` is complete.  The maths is :mod:`.projective` (``jacobians="parts"``) followed by the
per-pixel part of :func:`.ba_schur.assemble_chunk`, which remains the reference (tests compare the two) and the path
for float64, CUDA tensors and the Huber kernel.  Nothing per-pixel is stored between the two passes: torch's
element-wise version moves each ``[E, P]`` temporary through memory once per operation, which is what made the BA
memory-bound.

Layout: ``R [E, 3, 3]``, ``t [E, 3]`` (camera i -> j), ``d [N, P]`` inverse depths, ``src_row [E]`` the row of
``d`` of each edge's source, ``rx, ry [P]`` the pixel rays, ``tgt, cf [E, 2, P]`` flow targets and confidences
(``cf >= 0``, tiny values zeroed: denormal floats slow every product they enter), all float32; the first ``m`` edges
have unknown source depths, in slots ``ls [m]``.  The robust kernel is Cauchy with ``inv_s2 = 1 / scale^2`` (``0``:
none).  Results match the torch path to float32 rounding (the sums run in another order).  The helpers are inlined
by numba (``inline="always"``), so that each entry point is one self-contained function: a freshly compiled and a
cached entry point then run the same machine code (with LLVM inlining a cached caller could differ from a fresh one
in the order of its sums, and a first run after installing from the runs after it)."""
import numpy as np
import numba as nb

f32 = np.float32
OPTS = dict(fastmath=True, cache=True, nogil=True, error_model="numpy", boundscheck=False)


@nb.njit(inline="always", **OPTS)
def _pixel(rt, x0, y0, dp, tu, tv, fx, fy, cx, cy, min_depth, inv_s2, ws):
    """One pixel's projection: ``(xn, yn, iz, ru, rv, vf, vw)``, ``vf`` 1 where the point is in front (``z >
    min_depth``), ``vw = vf * ws * robust``."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2 = rt
    one = f32(1.0)
    X = r00 * x0 + r01 * y0 + r02 + t0 * dp
    Y = r10 * x0 + r11 * y0 + r12 + t1 * dp
    Z = r20 * x0 + r21 * y0 + r22 + t2 * dp
    valid = Z > min_depth
    iz = one / (Z if valid else one)
    vf = one if valid else f32(0.0)
    xn = X * iz
    yn = Y * iz
    ru = tu - (fx * xn + cx)
    rv = tv - (fy * yn + cy)
    return xn, yn, iz, ru, rv, vf, vf * ws / (one + (ru * ru + rv * rv) * inv_s2)


@nb.njit(inline="always", **OPTS)
def _edge(rt, dr, rx, ry, tu, tv, cu_, cv_, fx, fy, cx, cy, min_depth, inv_s2, ws, acc):
    """One edge's sums: ``acc[0:21]`` the upper triangle of ``J^T W J`` (row-major), ``acc[21:27]`` ``J^T W r``,
    ``acc[27]`` the plain cost.  ``J = (Ju, Jv)``: d(u, v) / d xi_j, :func:`.projective._pose_jacobian_rows`."""
    h00 = h02 = h03 = h04 = h05 = f32(0.0)
    h11 = h12 = h13 = h14 = h15 = f32(0.0)
    h22 = h23 = h24 = h25 = f32(0.0)
    h33 = h34 = h35 = h44 = h45 = h55 = f32(0.0)
    q0 = q1 = q2 = q3 = q4 = q5 = f32(0.0)
    c_e = f32(0.0)
    one = f32(1.0)
    for p in range(rx.shape[0]):
        dp = dr[p]
        xn, yn, iz, ru, rv, vf, vw = _pixel(rt, rx[p], ry[p], dp, tu[p], tv[p], fx, fy, cx, cy, min_depth, inv_s2, ws)
        cu = cu_[p]
        cv = cv_[p]
        c_e += vf * (cu * ru * ru + cv * rv * rv)
        wu = cu * vw
        wv = cv * vw
        hz = dp * iz
        xy = xn * yn
        # Ju = fx (hz, 0, -xn hz, -xn yn, 1 + xn^2, -yn),  Jv = fy (0, hz, -yn hz, -1 - yn^2, xn yn, xn)
        u0 = fx * hz
        u2 = -fx * xn * hz
        u3 = -fx * xy
        u4 = fx * (one + xn * xn)
        u5 = -fx * yn
        v1 = fy * hz
        v2 = -fy * yn * hz
        v3 = -fy * (one + yn * yn)
        v4 = fy * xy
        v5 = fy * xn
        a0 = wu * u0
        a2 = wu * u2
        a3 = wu * u3
        a4 = wu * u4
        a5 = wu * u5
        b1 = wv * v1
        b2 = wv * v2
        b3 = wv * v3
        b4 = wv * v4
        b5 = wv * v5
        h00 += a0 * u0
        h02 += a0 * u2
        h03 += a0 * u3
        h04 += a0 * u4
        h05 += a0 * u5
        h11 += b1 * v1
        h12 += b1 * v2
        h13 += b1 * v3
        h14 += b1 * v4
        h15 += b1 * v5
        h22 += a2 * u2 + b2 * v2
        h23 += a2 * u3 + b2 * v3
        h24 += a2 * u4 + b2 * v4
        h25 += a2 * u5 + b2 * v5
        h33 += a3 * u3 + b3 * v3
        h34 += a3 * u4 + b3 * v4
        h35 += a3 * u5 + b3 * v5
        h44 += a4 * u4 + b4 * v4
        h45 += a4 * u5 + b4 * v5
        h55 += a5 * u5 + b5 * v5
        q0 += a0 * ru
        q1 += b1 * rv
        q2 += a2 * ru + b2 * rv
        q3 += a3 * ru + b3 * rv
        q4 += a4 * ru + b4 * rv
        q5 += a5 * ru + b5 * rv
    sums = (h00, f32(0.0), h02, h03, h04, h05, h11, h12, h13, h14, h15, h22, h23, h24, h25, h33, h34, h35, h44, h45,
            h55, q0, q1, q2, q3, q4, q5, c_e)
    for k in range(28):
        acc[k] = sums[k]


@nb.njit(inline="always", **OPTS)
def _edge_depth(rt, dr, rx, ry, tu, tv, cu_, cv_, fx, fy, cx, cy, min_depth, inv_s2, ws, C, wd):
    """A source edge's share of its source's depth diagonal ``C += w Jd^2`` and gradient ``wd += w Jd r`` ``[P]``."""
    t0, t1, t2 = rt[9], rt[10], rt[11]
    for p in range(rx.shape[0]):
        xn, yn, iz, ru, rv, vf, vw = _pixel(rt, rx[p], ry[p], dr[p], tu[p], tv[p], fx, fy, cx, cy, min_depth, inv_s2,
                                            ws)
        jdu = fx * iz * (t0 - t2 * xn)
        jdv = fy * iz * (t1 - t2 * yn)
        bu = cu_[p] * vw * jdu
        bv = cv_[p] * vw * jdv
        C[p] += bu * jdu + bv * jdv
        wd[p] += bu * ru + bv * rv


@nb.njit(inline="always", **OPTS)
def _edge_rows(rt, dr, rx, ry, tu, tv, cu_, cv_, fx, fy, cx, cy, min_depth, inv_s2, ws, sC, B):
    """A source edge's depth rows ``B [6, P] = (w Jdu Ju + w Jdv Jv) C^-1/2`` (:func:`.ba_schur.depth_rows`)."""
    t0, t1, t2 = rt[9], rt[10], rt[11]
    one = f32(1.0)
    B0, B1, B2, B3, B4, B5 = B[0], B[1], B[2], B[3], B[4], B[5]
    for p in range(rx.shape[0]):
        dp = dr[p]
        xn, yn, iz, ru, rv, vf, vw = _pixel(rt, rx[p], ry[p], dp, tu[p], tv[p], fx, fy, cx, cy, min_depth, inv_s2, ws)
        vw = vw * sC[p]
        bu = cu_[p] * vw * fx * iz * (t0 - t2 * xn) * fx
        bv = cv_[p] * vw * fy * iz * (t1 - t2 * yn) * fy
        hz = dp * iz
        xy = xn * yn
        B0[p] = bu * hz
        B1[p] = bv * hz
        B2[p] = -(bu * xn + bv * yn) * hz
        B3[p] = -bu * xy - bv * (one + yn * yn)
        B4[p] = bu * (one + xn * xn) + bv * xy
        B5[p] = -bu * yn + bv * xn


@nb.njit(inline="always", **OPTS)
def _rt(R, t, e):
    return (R[e, 0, 0], R[e, 0, 1], R[e, 0, 2], R[e, 1, 0], R[e, 1, 1], R[e, 1, 2], R[e, 2, 0], R[e, 2, 1],
            R[e, 2, 2], t[e, 0], t[e, 1], t[e, 2])


@nb.njit(**OPTS)
def pass_blocks(R, t, d, src_row, rx, ry, tgt, cf, fx, fy, cx, cy, min_depth, inv_s2, ws, m, ls, C, wd, acc):
    """Every edge's sums into ``acc [E, 28]`` (:func:`_edge`); the first ``m`` also add to ``C, wd [ns, P]``."""
    fx, fy, cx, cy, min_depth, inv_s2, ws = f32(fx), f32(fy), f32(cx), f32(cy), f32(min_depth), f32(inv_s2), f32(ws)
    for e in range(R.shape[0]):
        rt = _rt(R, t, e)
        dr = d[src_row[e]]
        _edge(rt, dr, rx, ry, tgt[e, 0], tgt[e, 1], cf[e, 0], cf[e, 1], fx, fy, cx, cy, min_depth, inv_s2, ws, acc[e])
        if e < m:
            _edge_depth(rt, dr, rx, ry, tgt[e, 0], tgt[e, 1], cf[e, 0], cf[e, 1], fx, fy, cx, cy, min_depth, inv_s2,
                        ws, C[ls[e]], wd[ls[e]])


@nb.njit(**OPTS)
def pass_rows(R, t, d, src_row, rx, ry, tgt, cf, fx, fy, cx, cy, min_depth, inv_s2, ws, m, ls, sC, B):
    """The depth rows ``B [m, 6, P]`` of the first ``m`` edges, ``sC = C^-1/2 [ns, P]`` (:func:`_edge_rows`)."""
    fx, fy, cx, cy, min_depth, inv_s2, ws = f32(fx), f32(fy), f32(cx), f32(cy), f32(min_depth), f32(inv_s2), f32(ws)
    for e in range(m):
        _edge_rows(_rt(R, t, e), d[src_row[e]], rx, ry, tgt[e, 0], tgt[e, 1], cf[e, 0], cf[e, 1], fx, fy, cx, cy,
                   min_depth, inv_s2, ws, sC[ls[e]], B[e])
