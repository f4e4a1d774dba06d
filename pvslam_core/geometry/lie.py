"""Batched SE(3) / Sim(3) on plain torch tensors (float32 or float64, any device, autograd-friendly).

Layouts (see :mod:`pvslam_core.types`):

* SE3 ``[..., 7] = [tx, ty, tz, qx, qy, qz, qw]`` (Hamilton quaternion, scalar last), acting as ``X -> R X + t``.
* se3 tangent ``[..., 6] = [tau(3), phi(3)]`` (translation first, as lietorch / DROID-SLAM).
* Sim3 ``[..., 8] = [t, q, s]`` acting as ``X -> s R X + t``; tangent ``[..., 7] = [tau, phi, sigma]`` with
  ``sigma = log(s)``.

``Exp`` / ``Log`` are the group exponential and logarithm (``Exp(xi)`` is the 4x4 matrix exponential of the
generator ``[[phi^ (+ sigma I), tau], [0, 0]]``).  Everything broadcasts over leading dimensions.  Small-angle
branches use Taylor expansions, and the rotation logarithm goes through ``atan2`` on a quaternion with
non-negative scalar part, so it is stable near identity and near rotation angle pi.
"""
from __future__ import annotations

from typing import Sequence

import torch

__all__ = [
    "hat",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "quat_mul",
    "quat_conj",
    "quat_rotate",
    "so3_exp",
    "so3_log",
    "identity_se3",
    "se3_exp",
    "se3_log",
    "se3_inv",
    "se3_mul",
    "se3_act",
    "se3_adjoint",
    "se3_to_matrix",
    "se3_from_matrix",
    "se3_interpolate",
    "identity_sim3",
    "sim3_exp",
    "sim3_log",
    "sim3_inv",
    "sim3_mul",
    "sim3_act",
    "sim3_from_se3",
    "sim3_to_se3",
]


def _eps(dtype: torch.dtype) -> float:
    return 1e-4 if dtype in (torch.float16, torch.bfloat16, torch.float32) else 1e-7


def hat(v: torch.Tensor) -> torch.Tensor:
    """``[..., 3] -> [..., 3, 3]`` skew-symmetric matrix with ``hat(a) @ b = a x b``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


# ----------------------------------------------------------------------------------------------- quaternions
_CONJ: dict = {}


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    # one multiplication by a cached (-1, -1, -1, 1) (exact) instead of a negation, two slices and a cat
    key = (q.dtype, str(q.device))
    sign = _CONJ.get(key)
    if sign is None:
        sign = _CONJ[key] = torch.tensor([-1.0, -1.0, -1.0, 1.0], dtype=q.dtype, device=q.device)
    return q * sign


_CONST: dict = {}


def _bilinear_tables(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Constant tables (cached per dtype/device) that turn the two quaternion formulas below into one small matmul
    of the outer product ``a_i b_j [..., 16]``: ``QM [16, 4]`` (Hamilton product, entries +-1) and ``RM [16, 9]`` /
    ``RI [9]`` (rotation matrix ``RI + RM^T (q q^T)``, entries +-2).  Why: the element-wise formulas were ~40 tiny
    tensor ops each (Python dispatch dominated: these run ~10k times per run); the coefficients are exact (0, +-1,
    +-2), so the rotation matrix is bit-identical and the product differs only in the order of a 4-term sum."""
    key = (dtype, str(device))
    hit = _CONST.get(key)
    if hit is None:
        X, Y, Z, W = range(4)
        qm = torch.zeros(4, 4, 4, dtype=torch.float64)  # [i (of a), j (of b), out]
        for (i, j, o, sgn) in [
            (W, X, X, 1), (X, W, X, 1), (Y, Z, X, 1), (Z, Y, X, -1),
            (W, Y, Y, 1), (Y, W, Y, 1), (Z, X, Y, 1), (X, Z, Y, -1),
            (W, Z, Z, 1), (Z, W, Z, 1), (X, Y, Z, 1), (Y, X, Z, -1),
            (W, W, W, 1), (X, X, W, -1), (Y, Y, W, -1), (Z, Z, W, -1),
        ]:
            qm[i, j, o] = sgn
        rm = torch.zeros(4, 4, 9, dtype=torch.float64)  # one coefficient per monomial q_i q_j (i <= j)
        for (i, j, o, c) in [
            (Y, Y, 0, -2), (Z, Z, 0, -2), (X, Y, 1, 2), (Z, W, 1, -2), (X, Z, 2, 2), (Y, W, 2, 2),
            (X, Y, 3, 2), (Z, W, 3, 2), (X, X, 4, -2), (Z, Z, 4, -2), (Y, Z, 5, 2), (X, W, 5, -2),
            (X, Z, 6, 2), (Y, W, 6, -2), (Y, Z, 7, 2), (X, W, 7, 2), (X, X, 8, -2), (Y, Y, 8, -2),
        ]:
            rm[i, j, o] = c
        ri = torch.eye(3, dtype=torch.float64).reshape(9)
        hit = tuple(t.reshape(-1, t.shape[-1]).to(device, dtype) if t.dim() > 1 else t.to(device, dtype)
                    for t in (qm, rm, ri))
        _CONST[key] = hit
    return hit


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of ``[x, y, z, w]`` quaternions."""
    outer = a.unsqueeze(-1) * b.unsqueeze(-2)  # [..., 4, 4] (broadcast batch and dtype)
    return outer.reshape(outer.shape[:-2] + (16,)) @ _bilinear_tables(outer.dtype, outer.device)[0]


def quat_rotate(q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Rotate points ``x [..., 3]`` by unit quaternions ``q [..., 4]`` (``R x``)."""
    qv, qw = q[..., :3], q[..., 3:]
    qv, x = torch.broadcast_tensors(qv, x)
    uv = 2.0 * torch.cross(qv, x, dim=-1)
    return x + qw * uv + torch.cross(qv, uv, dim=-1)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``[..., 4]`` (xyzw) -> rotation matrix ``[..., 3, 3]``:
    ``[[1 - 2(yy + zz), 2(xy - wz), 2(xz + wy)], [2(xy + wz), 1 - 2(xx + zz), 2(yz - wx)],
    [2(xz - wy), 2(yz + wx), 1 - 2(xx + yy)]]`` (one matmul of ``q q^T`` with exact coefficients)."""
    _, rm, ri = _bilinear_tables(q.dtype, q.device)
    outer = q.unsqueeze(-1) * q.unsqueeze(-2)
    m = outer.reshape(outer.shape[:-2] + (16,)) @ rm + ri  # (not addmm: it would add the 1 first)
    return m.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``[..., 3, 3]`` -> unit quaternion ``[..., 4]`` (xyzw, ``w >= 0``).

    Shepperd's method, vectorised: of the four candidate formulas the one with the largest denominator is used.
    """
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # candidates (each is 4 * (component) * (that component))
    cand = torch.stack(
        [
            torch.stack([m21 - m12, m02 - m20, m10 - m01, 1 + tr], -1),  # w largest
            torch.stack([1 + m00 - m11 - m22, m01 + m10, m02 + m20, m21 - m12], -1),  # x largest
            torch.stack([m01 + m10, 1 - m00 + m11 - m22, m12 + m21, m02 - m20], -1),  # y largest
            torch.stack([m02 + m20, m12 + m21, 1 - m00 - m11 + m22, m10 - m01], -1),  # z largest
        ],
        dim=-2,
    )  # [..., 4, 4]
    diag = torch.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = diag.argmax(-1, keepdim=True)  # [..., 1]
    q = torch.gather(cand, -2, k.unsqueeze(-1).expand(k.shape[:-1] + (1, 4))).squeeze(-2)
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., 3:] < 0, -q, q)


def _select(small: torch.Tensor, x: torch.Tensor, f_small, f_large) -> torch.Tensor:
    """``where(small, f_small(x), f_large(x with 1 where small))``, evaluating one branch only when all entries
    take it (bit-identical; on the CPU, where the test costs no device sync: these run on a handful of elements,
    so every skipped tiny op counts)."""
    if x.device.type == "cpu" and not x.requires_grad:
        if not bool(small.any()):
            return f_large(x)
        if bool(small.all()):
            return f_small(x)
    return torch.where(small, f_small(x), f_large(torch.where(small, torch.ones_like(x), x)))


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rotation vector ``[..., 3]`` -> unit quaternion ``[..., 4]``."""
    return _so3_exp(phi, (phi * phi).sum(-1, keepdim=True))


def _so3_exp(phi: torch.Tensor, th2: torch.Tensor) -> torch.Tensor:
    small = th2 < _eps(phi.dtype) ** 2 * 100

    def taylor(t2):
        return torch.cat([(0.5 - t2 / 48.0 + t2 * t2 / 3840.0) * phi, 1.0 - t2 / 8.0 + t2 * t2 / 384.0], dim=-1)

    def closed(t2):
        th = torch.sqrt(t2)
        return torch.cat([torch.sin(0.5 * th) / th * phi, torch.cos(0.5 * th)], dim=-1)

    return _select(small, th2, taylor, closed)


def so3_log(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``[..., 4]`` -> rotation vector ``[..., 3]`` with angle in ``[0, pi]``."""
    q = torch.where(q[..., 3:] < 0, -q, q)
    v, w = q[..., :3], q[..., 3:]
    n2 = (v * v).sum(-1, keepdim=True)
    small = n2 < _eps(q.dtype) ** 2 * 100
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    ws = torch.where(small, torch.ones_like(w), w)
    # small: 2 atan(n / w) / n = 2 / w (1 - n^2 / (3 w^2) + ...)
    k = torch.where(small, 2.0 / ws * (1.0 - n2 / (3.0 * ws * ws)), 2.0 * torch.atan2(n, w) / n)
    return k * v


def _so3_left_jacobian_coeffs(th2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Coefficients ``a, b`` of ``V = I + a phi^ + b phi^2`` (SO3 left Jacobian)."""
    small = th2 < 1e-6 if th2.dtype == torch.float64 else th2 < 1e-3

    def taylor(t2):
        return torch.cat([0.5 - t2 / 24.0 + t2 * t2 / 720.0, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0], dim=-1)

    def closed(t2):
        th = torch.sqrt(t2)
        return torch.cat([(1.0 - torch.cos(th)) / t2, (th - torch.sin(th)) / (t2 * th)], dim=-1)

    ab = _select(small, th2, taylor, closed)
    return ab[..., 0:1], ab[..., 1:2]


def _so3_left_jacobian_inv_coeff(th2: torch.Tensor) -> torch.Tensor:
    """``c`` of ``V^-1 = I - 1/2 phi^ + c phi^2``; ``c = 1/th^2 - cot(th/2) / (2 th)`` (finite up to pi)."""
    small = th2 < 1e-6 if th2.dtype == torch.float64 else th2 < 1e-3
    t2 = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(t2)
    half = 0.5 * th
    c = 1.0 / t2 - torch.cos(half) / (2.0 * th * torch.sin(half))
    return torch.where(small, 1.0 / 12.0 + th2 / 720.0 + th2 * th2 / 30240.0, c)


# ------------------------------------------------------------------------------------------------------ SE3
def identity_se3(shape: Sequence[int] | int = (), dtype: torch.dtype = torch.float64,
                 device: str | torch.device = "cpu") -> torch.Tensor:
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    T = torch.zeros(shape + (7,), dtype=dtype, device=device)
    T[..., 6] = 1.0
    return T


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Tangent ``[..., 6] = [tau, phi]`` -> SE3 ``[..., 7]``: ``t = V(phi) tau``, ``q = exp(phi)``."""
    tau, phi = xi[..., :3], xi[..., 3:]
    th2 = (phi * phi).sum(-1, keepdim=True)
    a, b = _so3_left_jacobian_coeffs(th2)
    c1 = torch.cross(phi, tau, dim=-1)
    c2 = torch.cross(phi, c1, dim=-1)
    t = tau + a * c1 + b * c2
    return torch.cat([t, _so3_exp(phi, th2)], dim=-1)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """SE3 ``[..., 7]`` -> tangent ``[..., 6] = [tau, phi]``."""
    t, q = T[..., :3], T[..., 3:]
    phi = so3_log(q)
    th2 = (phi * phi).sum(-1, keepdim=True)
    c = _so3_left_jacobian_inv_coeff(th2)
    c1 = torch.cross(phi, t, dim=-1)
    c2 = torch.cross(phi, c1, dim=-1)
    tau = t - 0.5 * c1 + c * c2
    return torch.cat([tau, phi], dim=-1)


def se3_inv(T: torch.Tensor) -> torch.Tensor:
    qi = quat_conj(T[..., 3:])
    return torch.cat([-quat_rotate(qi, T[..., :3]), qi], dim=-1)


def se3_mul(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Composition ``A o B`` (apply B first)."""
    q = quat_mul(A[..., 3:], B[..., 3:])
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    # R_A t_B + t_A with the rotation matrix (4 ops; the two cross products of quat_rotate were ~10)
    R, tB = quat_to_rotmat(A[..., 3:]), B[..., :3].unsqueeze(-1)
    if R.dtype != tB.dtype:  # mixed precision promotes, as the element-wise formula did
        ct = torch.promote_types(R.dtype, tB.dtype)
        R, tB = R.to(ct), tB.to(ct)
    t = (R @ tB).squeeze(-1) + A[..., :3]
    t, q = _bcast_last(t, q)
    return torch.cat([t, q], dim=-1)


def se3_act(T: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """Apply ``T [..., 7]`` to points ``X [..., 3]``: ``R X + t``."""
    return quat_rotate(T[..., 3:], X) + T[..., :3]


def se3_adjoint(T: torch.Tensor) -> torch.Tensor:
    """Adjoint ``[..., 6, 6]`` for the ``[tau, phi]`` ordering: ``[[R, t^ R], [0, R]]``."""
    R = quat_to_rotmat(T[..., 3:])
    tR = hat(T[..., :3]) @ R
    z = torch.zeros_like(R)
    top = torch.cat([R, tR], dim=-1)
    bot = torch.cat([z, R], dim=-1)
    return torch.cat([top, bot], dim=-2)


def se3_to_matrix(T: torch.Tensor) -> torch.Tensor:
    R = quat_to_rotmat(T[..., 3:])
    M = torch.zeros(T.shape[:-1] + (4, 4), dtype=T.dtype, device=T.device)
    M[..., :3, :3] = R
    M[..., :3, 3] = T[..., :3]
    M[..., 3, 3] = 1.0
    return M


def se3_from_matrix(M: torch.Tensor) -> torch.Tensor:
    return torch.cat([M[..., :3, 3], rotmat_to_quat(M[..., :3, :3])], dim=-1)


def se3_interpolate(A: torch.Tensor, B: torch.Tensor, alpha: torch.Tensor | float) -> torch.Tensor:
    """``Exp(alpha Log(B A^-1)) A``: alpha = 0 gives A, alpha = 1 gives B."""
    if not torch.is_tensor(alpha):
        alpha = torch.tensor(alpha, dtype=A.dtype, device=A.device)
    alpha = alpha.to(A.dtype)
    if alpha.dim() > 0:
        alpha = alpha.unsqueeze(-1)
    return se3_mul(se3_exp(alpha * se3_log(se3_mul(B, se3_inv(A)))), A)


# ----------------------------------------------------------------------------------------------------- Sim3
def identity_sim3(shape: Sequence[int] | int = (), dtype: torch.dtype = torch.float64,
                  device: str | torch.device = "cpu") -> torch.Tensor:
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    S = torch.zeros(shape + (8,), dtype=dtype, device=device)
    S[..., 6] = 1.0
    S[..., 7] = 1.0
    return S


def _sim3_W(phi: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """``W = sum_k M^k / (k+1)! = C I + A Phi + B Phi^2`` with ``M = sigma I + Phi``, ``Phi = phi^``, ``theta = |phi|``
    (the Sim3 'V' matrix; Strasdat's thesis / Sophus ``calcW``):
    ``C = (e^s - 1) / s``, ``A = (e^s s sin t + (1 - e^s cos t) t) / (t (t^2 + s^2))``,
    ``B = (C - ((e^s cos t - 1) s + e^s t sin t) / (t^2 + s^2)) / t^2``.

    Why not one formula: near ``M = 0`` these lose every digit to cancellation (and the pose graph's central
    differences take 1e-6 steps there), so where ``max(|s|, t) < 0.1`` the power series is summed to ``M^9``
    (truncation below 3e-17 relative).  Elsewhere the closed form is exact to rounding (``t`` small but ``|s| >= 0.1``
    only cancels inside ``B``, which multiplies ``Phi^2 = O(t^2)``).  The 6x6 ``matrix_exp`` this replaces gave the
    same numbers (tested against it) at ~10x the cost, and dominated the loop pose graph's time."""
    shape = phi.shape[:-1]
    s = sigma.reshape(shape)
    t = torch.linalg.norm(phi, dim=-1)
    Phi = hat(phi)
    Phi2 = Phi @ Phi
    I3 = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(shape + (3, 3))
    small = torch.maximum(s.abs(), t) < 0.1
    # closed form on safe arguments (the small ones get dummies and are replaced by the series below)
    # (t -> 0 with |s| >= 0.1: A and B have finite limits and multiply Phi = O(t); t is clamped at sqrt(eps), where
    # their relative error O(t^2) is below rounding, so that t = 0 gives no 0 / 0)
    s_ = torch.where(small, torch.ones_like(s), s)
    t_ = torch.where(small, torch.ones_like(t), t.clamp(min=torch.finfo(t.dtype).eps ** 0.5))
    es, st, ct = torch.exp(s_), torch.sin(t_), torch.cos(t_)
    c = t_ * t_ + s_ * s_
    s0 = s_ == 0  # C's limit is 1 (expm1 keeps every other s exact)
    C = torch.where(s0, torch.ones_like(s_), torch.expm1(s_) / torch.where(s0, torch.ones_like(s_), s_))
    A = (es * s_ * st + (1 - es * ct) * t_) / (t_ * c)
    B = (C - ((es * ct - 1) * s_ + es * t_ * st) / c) / (t_ * t_)
    W = C[..., None, None] * I3 + A[..., None, None] * Phi + B[..., None, None] * Phi2
    if bool(small.any()):
        M = Phi + s[..., None, None] * I3
        term, series = I3.clone(), I3.clone()
        for k in range(1, 10):  # sum_k M^k / (k + 1)!
            term = term @ M / (k + 1)
            series = series + term
        W = torch.where(small[..., None, None], series, W)
    return W


def sim3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Tangent ``[..., 7] = [tau, phi, sigma]`` -> Sim3 ``[..., 8] = [t, q, s]``."""
    tau, phi, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6:7]
    W = _sim3_W(phi, sigma)
    t = (W @ tau.unsqueeze(-1)).squeeze(-1)
    return torch.cat([t, so3_exp(phi), torch.exp(sigma)], dim=-1)


def sim3_log(S: torch.Tensor) -> torch.Tensor:
    """Sim3 ``[..., 8]`` -> tangent ``[..., 7] = [tau, phi, sigma]``."""
    t, q, s = S[..., :3], S[..., 3:7], S[..., 7:8]
    phi = so3_log(q)
    sigma = torch.log(s)
    W = _sim3_W(phi, sigma)
    tau = torch.linalg.solve(W, t.unsqueeze(-1)).squeeze(-1)
    return torch.cat([tau, phi, sigma], dim=-1)


def sim3_inv(S: torch.Tensor) -> torch.Tensor:
    qi = quat_conj(S[..., 3:7])
    si = 1.0 / S[..., 7:8]
    return torch.cat([-si * quat_rotate(qi, S[..., :3]), qi, si], dim=-1)


def sim3_mul(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    q = quat_mul(A[..., 3:7], B[..., 3:7])
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    t = A[..., 7:8] * quat_rotate(A[..., 3:7], B[..., :3]) + A[..., :3]
    s = A[..., 7:8] * B[..., 7:8]
    t, q, s = _bcast_last(t, q, s)
    return torch.cat([t, q, s], dim=-1)


def sim3_act(S: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    return S[..., 7:8] * quat_rotate(S[..., 3:7], X) + S[..., :3]


def sim3_from_se3(T: torch.Tensor, s: torch.Tensor | float = 1.0) -> torch.Tensor:
    """``[R | t]`` with scale ``s`` -> Sim3 ``[t, q, s]``; ``s`` is a float, a tensor broadcastable to
    ``T.shape[:-1]`` (one scale per transform) or of shape ``[..., 1]``."""
    if not torch.is_tensor(s):
        s = torch.tensor(s, dtype=T.dtype, device=T.device)
    s = s.to(T.dtype)
    if s.dim() == T.dim() and s.shape[-1] == 1:  # already [..., 1]
        s = s.expand(T.shape[:-1] + (1,))
    else:  # one scale per transform, broadcast to T.shape[:-1]
        s = s.expand(T.shape[:-1]).unsqueeze(-1)
    return torch.cat([T, s], dim=-1)


def sim3_to_se3(S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a Sim3 into its rigid part ``[t, q]`` and its scale ``s [...]``."""
    return S[..., :7], S[..., 7]


def _bcast_last(*xs: torch.Tensor) -> list[torch.Tensor]:
    # torch.broadcast_shapes goes through torch._refs (~0.3 ms a call, and its first call imports sympy, ~1 s):
    # the composition of two poses runs thousands of times per run, so broadcast the batch shapes here
    shapes = [tuple(x.shape[:-1]) for x in xs]
    if all(s == shapes[0] for s in shapes):
        return list(xs)
    n = max(len(s) for s in shapes)
    out = []
    for dims in zip(*(((1,) * (n - len(s))) + s for s in shapes)):
        big = {d for d in dims if d != 1}
        if len(big) > 1:
            raise RuntimeError(f"shapes {shapes} cannot be broadcast together")
        out.append(big.pop() if big else 1)
    shape = torch.Size(out)
    return [x.expand(shape + x.shape[-1:]) for x in xs]
