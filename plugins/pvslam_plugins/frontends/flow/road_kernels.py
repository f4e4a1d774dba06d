"""The road search's per-candidate pixel maps as one compiled loop (numba): :meth:`.road_plane.RoadPlane._block_costs`
scores every candidate plane motion on every searched pixel, and numpy's version moves each ``[M, N]`` temporary
through memory once per operation (eight of them before the image is even sampled).  Here each element is computed
once, with the same float32 operations in the same order (no fast-math, so no reassociation or fused multiply-adds):
the maps are bit-equal to numpy's (tested), and so is every cost computed from them.

Layout as ``_block_costs``: ``A [3, N]`` (``K R x~``), ``B [N]`` (the rays' y), ``KV [M, 3]`` (``K v``), all float32.
"""
import numpy as np
import numba as nb

f32 = np.float32


@nb.njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)
def candidate_maps(A, B, KV, w_max, h_max):
    """``(mx, my, inside)``, float32 ``[M, N]`` x2 and bool ``[M, N]``: where each pixel lands under each candidate's
    homography, ``nan`` behind the camera, and whether it lands inside ``[0, w_max] x [0, h_max]``."""
    m, n = KV.shape[0], B.shape[0]
    mx = np.empty((m, n), np.float32)
    my = np.empty((m, n), np.float32)
    inside = np.empty((m, n), np.bool_)
    eps, nan, one, zero = f32(1e-6), f32(np.nan), f32(1.0), f32(0.0)
    for i in range(m):
        k0, k1, k2 = KV[i, 0], KV[i, 1], KV[i, 2]
        for j in range(n):
            b = B[j]
            z = A[2, j] + k2 * b
            inv = one / z if z > eps else nan
            x = (A[0, j] + k0 * b) * inv
            y = (A[1, j] + k1 * b) * inv
            mx[i, j] = x
            my[i, j] = y
            inside[i, j] = (x >= zero) & (x <= w_max) & (y >= zero) & (y <= h_max)
    return mx, my, inside


@nb.njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)
def masked_abs_diff(s, ref, inside):
    """float32 ``[M, N]``: ``|s - ref|`` where ``inside``, else 0 (the terms the cost sums, in numpy's layout)."""
    m, n = s.shape
    out = np.empty((m, n), np.float32)
    zero = f32(0.0)
    for i in range(m):
        for j in range(n):
            out[i, j] = abs(s[i, j] - ref[j]) if inside[i, j] else zero
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)
def flow_length(flow):
    """float32 ``[H, W]``: the length of each vector of a float32 flow ``[H, W, 2]`` (``np.linalg.norm(flow,
    axis=-1)``, whose squares and sum round the same way)."""
    h, w = flow.shape[0], flow.shape[1]
    out = np.empty((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            a = flow[i, j, 0]
            b = flow[i, j, 1]
            out[i, j] = np.sqrt(a * a + b * b)
    return out
