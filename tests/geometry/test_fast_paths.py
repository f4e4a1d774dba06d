"""The CPU fast paths of the geometry against the formulas they replaced, kept here as references, and
the dense BA step against a brute-force Gauss-Newton step on the full (non-reduced) system.

* ``quat_to_rotmat`` (one matmul with exact +-2 coefficients) is bit-identical to the element-wise formula;
  ``quat_mul`` (one matmul with +-1 coefficients) equal up to the order of a 4-term sum.
* ``so3_exp`` / ``se3_exp`` (one branch evaluated when every element takes it) are bit-identical.
* ``project_points`` (rotation as one matmul, Jacobian rows written in place) equals the element-wise formula.
* ``dense_ba`` (sources bucketed by edge count, row-vector products): one float64 iteration equals an explicit
  Schur-complement step built from the stacked per-pixel Jacobians of ``reproject``.
* ``motion_only_ba`` (rotation-matrix composition) equals a plain Gauss-Newton loop on ``reproject``'s Jacobians.
"""
import itertools

import pytest
import torch

from pvslam_core.geometry.ba import WEIGHT_SCALE, dense_ba, motion_only_ba
from pvslam_core.geometry.ba_schur import plan_chunks
from pvslam_core.geometry.lie import quat_conj, quat_mul, quat_to_rotmat, se3_exp, se3_inv, se3_mul, so3_exp
from pvslam_core.geometry.projective import pixel_grid, project_points, reproject
from pvslam_core.geometry.testing import make_problem, perturb


# ------------------------------------------------------------------------------------- the replaced formulas
def _eps(dtype):
    return 1e-4 if dtype in (torch.float16, torch.bfloat16, torch.float32) else 1e-7


def ref_quat_to_rotmat(q):
    x, y, z, w = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    m = torch.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
                     2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
                     2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], dim=-1)
    return m.reshape(q.shape[:-1] + (3, 3))


def ref_quat_mul(a, b):
    av, aw = a[..., :3], a[..., 3:]
    bv, bw = b[..., :3], b[..., 3:]
    av, bv = torch.broadcast_tensors(av, bv)
    v = aw * bv + bw * av + torch.cross(av, bv, dim=-1)
    w = aw * bw - (av * bv).sum(-1, keepdim=True)
    return torch.cat([v, w], dim=-1)


def ref_quat_rotate(q, x):
    qv, qw = q[..., :3], q[..., 3:]
    qv, x = torch.broadcast_tensors(qv, x)
    uv = 2.0 * torch.cross(qv, x, dim=-1)
    return x + qw * uv + torch.cross(qv, uv, dim=-1)


def ref_se3_mul(A, B):
    q = ref_quat_mul(A[..., 3:], B[..., 3:])
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    t = ref_quat_rotate(A[..., 3:], B[..., :3]) + A[..., :3]
    shape = torch.broadcast_shapes(t.shape[:-1], q.shape[:-1])
    return torch.cat([t.expand(shape + (3,)), q.expand(shape + (4,))], dim=-1)


def ref_so3_exp(phi):
    th2 = (phi * phi).sum(-1, keepdim=True)
    small = th2 < _eps(phi.dtype) ** 2 * 100
    th = torch.sqrt(torch.where(small, torch.ones_like(th2), th2))
    k = torch.where(small, 0.5 - th2 / 48.0 + th2 * th2 / 3840.0, torch.sin(0.5 * th) / th)
    w = torch.where(small, 1.0 - th2 / 8.0 + th2 * th2 / 384.0, torch.cos(0.5 * th))
    return torch.cat([k * phi, w], dim=-1)


def ref_se3_exp(xi):
    tau, phi = xi[..., :3], xi[..., 3:]
    th2 = (phi * phi).sum(-1, keepdim=True)
    small = th2 < 1e-6 if th2.dtype == torch.float64 else th2 < 1e-3
    t2 = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(t2)
    a = torch.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - torch.cos(th)) / t2)
    b = torch.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0, (th - torch.sin(th)) / (t2 * th))
    c1 = torch.cross(phi, tau, dim=-1)
    c2 = torch.cross(phi, c1, dim=-1)
    return torch.cat([tau + a * c1 + b * c2, ref_so3_exp(phi)], dim=-1)


def ref_project_points(R, t, d, intr, h, w, min_depth=0.2, jacobians=False, translation_only=False):
    fx, fy, cx, cy = (float(v) for v in intr.tolist())
    grid = pixel_grid(h, w, d.device, d.dtype).reshape(-1, 2)
    X0, Y0 = (grid[:, 0] - cx) / fx, (grid[:, 1] - cy) / fy
    if translation_only:
        X, Y, Z = X0 + t[:, 0:1] * d, Y0 + t[:, 1:2] * d, 1.0 + t[:, 2:3] * d
    else:
        X = R[:, 0, 0:1] * X0 + R[:, 0, 1:2] * Y0 + R[:, 0, 2:3] + t[:, 0:1] * d
        Y = R[:, 1, 0:1] * X0 + R[:, 1, 1:2] * Y0 + R[:, 1, 2:3] + t[:, 1:2] * d
        Z = R[:, 2, 0:1] * X0 + R[:, 2, 1:2] * Y0 + R[:, 2, 2:3] + t[:, 2:3] * d
    valid = Z > min_depth
    iz = 1.0 / torch.where(valid, Z, torch.ones_like(Z))
    xn, yn = X * iz, Y * iz
    out = {"u": fx * xn + cx, "v": fy * yn + cy, "valid": valid, "z": Z}
    if jacobians:
        hz, zero = d * iz, torch.zeros_like(xn)
        out["JuT"] = torch.stack([hz, zero, -xn * hz, -xn * yn, 1 + xn * xn, -yn], dim=1) * fx
        out["JvT"] = torch.stack([zero, hz, -yn * hz, -1 - yn * yn, xn * yn, xn], dim=1) * fy
        out["Jdu"] = (fx * iz) * (t[:, 0:1] - t[:, 2:3] * xn)
        out["Jdv"] = (fy * iz) * (t[:, 1:2] - t[:, 2:3] * yn)
    return out


def rand_quats(n, dtype, seed=0):
    q = torch.randn(n, 4, dtype=dtype, generator=torch.Generator().manual_seed(seed))
    return q / q.norm(dim=-1, keepdim=True)


def rand_poses(n, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.cat([torch.randn(n, 3, dtype=dtype, generator=g), rand_quats(n, dtype, seed + 1)], -1)


# ------------------------------------------------------------------------------------------------------- lie
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_quat_to_rotmat_bit_identical(dtype):
    q = rand_quats(500, dtype)
    for x in (q, q[0], q.view(5, 100, 4), 3.0 * q):  # batches, one quaternion, non-unit input too
        assert torch.equal(quat_to_rotmat(x), ref_quat_to_rotmat(x))


def test_quat_conj_bit_identical():
    q = rand_quats(50, torch.float64, 9)
    for x in (q, q[0], q.float()):
        assert torch.equal(quat_conj(x), torch.cat([-x[..., :3], x[..., 3:]], dim=-1))


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-6), (torch.float64, 1e-15)])
def test_quat_mul_and_se3_mul_match(dtype, tol):
    a, b = rand_quats(300, dtype, 1), rand_quats(300, dtype, 2)
    for x, y in ((a, b), (a, b[:1]), (a[:1], b), (a[7], b[9]), (a.view(3, 100, 4), b[:100])):
        torch.testing.assert_close(quat_mul(x, y), ref_quat_mul(x, y), rtol=0, atol=tol)
    A, B = rand_poses(300, dtype, 3), rand_poses(300, dtype, 4)
    for x, y in ((A, B), (A, B[:1]), (A[:1], B), (A[5], B[6])):
        torch.testing.assert_close(se3_mul(x, y), ref_se3_mul(x, y), rtol=tol, atol=tol * 10)


def test_mixed_precision_promotes():
    """float32 with float64 computes in float64 (the cross-product formulas refused mixed dtypes)."""
    a, b = rand_quats(5, torch.float32, 1), rand_quats(5, torch.float64, 2)
    got = quat_mul(a, b)
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, ref_quat_mul(a.double(), b), rtol=0, atol=1e-15)
    A, B = rand_poses(5, torch.float32, 3), rand_poses(5, torch.float64, 4)
    for x, y in ((A, B), (B, A)):
        got = se3_mul(x, y)
        assert got.dtype == torch.float64
        torch.testing.assert_close(got, ref_se3_mul(x.double(), y.double()), rtol=1e-6, atol=1e-6)  # float32 input


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exp_maps_bit_identical(dtype):
    g = torch.Generator().manual_seed(5)
    for scale in (1e-9, 1e-5, 1e-2, 1.0, 3.0):
        xi = (torch.randn(60, 6, generator=g) * scale).to(dtype)
        xi[::3] *= 1e-6  # mixed batches: some elements on the Taylor branch, some not
        for x in (xi, xi[::3], xi[1::3], xi[0], xi[:1]):
            assert torch.equal(se3_exp(x), ref_se3_exp(x))
            assert torch.equal(so3_exp(x[..., 3:]), ref_so3_exp(x[..., 3:]))
    # the autograd path (both branches through torch.where) gives the same values and finite gradients at 0
    x = torch.zeros(2, 6, dtype=dtype, requires_grad=True)
    y = se3_exp(x)
    assert torch.equal(y.detach(), ref_se3_exp(x.detach()))
    y.sum().backward()
    assert torch.isfinite(x.grad).all()


# ----------------------------------------------------------------------------------------------- projective
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 2e-6), (torch.float64, 1e-13)])
@pytest.mark.parametrize("translation_only", [False, True])
def test_project_points_matches_elementwise_formula(dtype, tol, translation_only):
    h, w, E = 6, 9, 5
    g = torch.Generator().manual_seed(1)
    R = quat_to_rotmat(so3_exp(0.2 * torch.randn(E, 3, generator=g, dtype=torch.float64)))
    t = 0.3 * torch.randn(E, 3, generator=g, dtype=torch.float64)
    d = 0.2 + torch.rand(E, h * w, generator=g, dtype=torch.float64)
    intr = torch.tensor([7.0, 6.5, 4.2, 2.7])
    R, t, d = R.to(dtype), t.to(dtype), d.to(dtype)
    ref = ref_project_points(R, t, d, intr, h, w, 0.2, True, translation_only)
    for jac in (False, "pose", "parts", True):
        got = project_points(R, t, d, intr, h, w, 0.2, jac, translation_only)
        assert torch.equal(got["valid"], ref["valid"])
        keys = ["u", "v", "z"] + {False: [], "pose": ["JuT", "JvT"]}.get(jac, ["JuT", "JvT", "Jdu", "Jdv"])
        for k in keys:
            scale = float(ref[k].abs().max())
            torch.testing.assert_close(got[k], ref[k], rtol=0, atol=tol * scale, msg=k)
    # the differentiable path (inputs requiring grad) gives the same Jacobians
    dg = d.clone().requires_grad_(True)
    got = project_points(R, t, dg, intr, h, w, 0.2, "parts", translation_only)
    plain = project_points(R, t, d, intr, h, w, 0.2, "parts", translation_only)
    assert got["JuT"].requires_grad
    torch.testing.assert_close(got["JuT"].detach(), plain["JuT"], rtol=0, atol=tol * float(plain["JuT"].abs().max()))


def test_project_points_promotes_mixed_dtypes():
    """float64 rotations with float32 depths compute in float64, as the element-wise formula did."""
    h, w = 4, 5
    R = quat_to_rotmat(rand_quats(2, torch.float64, 7))
    t = torch.tensor([[0.1, 0.0, 0.2], [0.0, -0.1, 0.1]], dtype=torch.float64)
    d = torch.rand(2, h * w, generator=torch.Generator().manual_seed(2)) + 0.5
    intr = torch.tensor([5.0, 5.0, 2.0, 1.5])
    got, ref = project_points(R, t, d, intr, h, w), ref_project_points(R, t, d, intr, h, w)
    assert got["u"].dtype == ref["u"].dtype == torch.float64
    torch.testing.assert_close(got["u"], ref["u"], rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------- dense BA
def test_plan_pairs_are_all_pairs_sharing_a_source():
    """Bucketed sources: the planned pairs are exactly the ordered pairs (a, b) of edges with the same source."""
    ii = torch.tensor([0, 0, 0, 1, 2, 2, 3, 4, 4, 4, 4, 5])
    jj = torch.tensor([1, 2, 3, 0, 1, 3, 2, 0, 1, 2, 3, 4])
    n = 6
    pose_map = torch.arange(n) - 1  # keyframe 0 fixed
    src_map = torch.arange(n)
    for budget in (10**9, 4 * 12):
        chunks = plan_chunks(ii, jj, pose_map, src_map[ii], n, n - 1, 12, budget)
        for ch in chunks:
            e = torch.arange(len(ii))[ch.idx]
            src = ii[e][: ch.n_src]
            want = {(a, b) for a, b in itertools.product(range(ch.n_src), repeat=2) if src[a] == src[b]}
            got = set(zip(ch.pa.tolist(), ch.pb.tolist()))
            assert got == want and len(ch.pa) == len(want)
            # buckets: consecutive rows of sources with exactly c edges
            for c, b0, b1 in ch.buckets:
                s = src[b0:b1].reshape(-1, c)
                assert (s == s[:, :1]).all() and len(set(s[:, 0].tolist())) == s.shape[0]
                assert all(int((src == k).sum()) == c for k in s[:, 0].tolist())


def brute_force_step(pr, poses, disps, free, lm, ep, eta):
    """One LM-damped Gauss-Newton step of the dense BA, from the stacked full Jacobian (float64)."""
    N, h, w = disps.shape
    P = h * w
    ii, jj = pr.ii, pr.jj
    coords, valid, Ji, Jj, Jd = reproject(poses, disps.double(), pr.intr.double(), ii, jj, jacobians=True)
    E = len(ii)
    tgt = pr.target.double().permute(0, 2, 3, 1)  # [E, h, w, 2]
    r = (tgt - coords).reshape(E, P, 2)
    wgt = (WEIGHT_SCALE * pr.weight.double().permute(0, 2, 3, 1) * valid[..., None].double()).reshape(E, P, 2)
    fidx = torch.nonzero(free).squeeze(1).tolist()
    srcs = sorted(set(ii.tolist()))
    F, Ns = len(fidx), len(srcs)
    n_par = 6 * F + Ns * P
    J = torch.zeros(E, P, 2, n_par, dtype=torch.float64)
    for e in range(E):
        a, b = int(ii[e]), int(jj[e])
        if a in fidx:
            J[e, :, :, 6 * fidx.index(a):6 * fidx.index(a) + 6] += Ji.reshape(E, P, 2, 6)[e]
        if b in fidx:
            J[e, :, :, 6 * fidx.index(b):6 * fidx.index(b) + 6] += Jj.reshape(E, P, 2, 6)[e]
        col0 = 6 * F + srcs.index(a) * P
        J[e, torch.arange(P), :, col0 + torch.arange(P)] = Jd.reshape(E, P, 2)[e]
    J = J.reshape(-1, n_par)
    W, rr = wgt.reshape(-1), r.reshape(-1)
    H = J.T @ (W[:, None] * J)
    g = J.T @ (W * rr)
    k = 6 * F
    B, Em, C = H[:k, :k], H[:k, k:], torch.diagonal(H[k:, k:]) + eta
    assert torch.allclose(H[k:, k:], torch.diag(torch.diagonal(H[k:, k:])))  # depth block is diagonal
    S = B - Em @ (Em / C).T
    b = g[:k] - Em @ (g[k:] / C)
    S = S + torch.diag(ep + lm * torch.diagonal(S))
    dxi = torch.linalg.solve(S, b).reshape(F, 6)
    dd = (g[k:] - Em.T @ dxi.reshape(-1)) / C
    G = se3_inv(poses)
    G[fidx] = se3_mul(se3_exp(dxi), G[fidx])
    d = disps.double().clone().reshape(N, P)
    d[srcs] = (d[srcs] + dd.reshape(Ns, P)).clamp(min=1e-3)
    return se3_inv(G), d.reshape(N, h, w)


@pytest.mark.parametrize("max_chunk_pixels", [10**9, 3 * 48])
def test_dense_ba_step_equals_brute_force_schur(max_chunk_pixels):
    pr = make_problem(n=5, h=6, w=8, seed=3, noise=0.3, radius=2)
    p0, d0 = perturb(pr, fixed=(0,), seed=1)
    free = torch.ones(5, dtype=torch.bool)
    free[0] = False
    lm, ep, eta = 1e-4, 0.1, 1e-3
    g = pr.graph(p0, d0)
    rep = dense_ba(g, pr.obs(), free, iters=1, lm=lm, ep=ep, depth_damping=eta, dtype=torch.float64,
                   max_chunk_pixels=max_chunk_pixels)
    assert not rep.rejected and rep.iterations == 1
    ref_poses, ref_disps = brute_force_step(pr, p0, d0, free, lm, ep, eta)
    assert float((ref_poses - p0).abs().max()) > 1e-4  # the step moves the poses
    torch.testing.assert_close(g.poses, ref_poses, rtol=0, atol=1e-10)
    torch.testing.assert_close(g.disps, ref_disps.float(), rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------------------------------ motion-only BA
def test_motion_only_ba_equals_plain_gauss_newton():
    pr = make_problem(n=4, h=12, w=16, seed=2, noise=0.2)
    k, new = 1, 2
    e = int(torch.nonzero((pr.ii == k) & (pr.jj == new))[0])
    starts = torch.stack([se3_mul(pr.poses[new], se3_exp(torch.tensor(v, dtype=torch.float64)))
                          for v in ([0.03, -0.02, 0.02, 0.01, -0.02, 0.01], [-0.05, 0.01, 0.0, 0.0, 0.02, -0.01])])
    lm, ep, iters = 1e-4, 0.1, 4
    got, _ = motion_only_ba(starts, pr.poses[k], pr.disps[k], pr.intr, pr.target[e].expand(2, -1, -1, -1),
                            pr.weight[e].expand(2, -1, -1, -1), iters=iters, lm=lm, ep=ep)
    d = pr.disps[k].double()[None]
    tgt = pr.target[e].double().permute(1, 2, 0)  # [h, w, 2]
    for f in range(2):
        T = starts[f].clone()
        for _ in range(iters):
            poses = torch.stack([pr.poses[k], T])
            coords, valid, _, Jj, _ = reproject(poses, torch.cat([d, d]), pr.intr.double(), torch.tensor([0]),
                                                torch.tensor([1]), jacobians=True)
            r = (tgt - coords[0]).reshape(-1)
            wt = (WEIGHT_SCALE * pr.weight[e].double().permute(1, 2, 0) * valid[0][..., None]).reshape(-1)
            J = Jj[0].reshape(-1, 6)
            H = J.T @ (wt[:, None] * J)
            H = H + torch.diag(ep + lm * torch.diagonal(H))
            dx = torch.linalg.solve(H, J.T @ (wt * r))
            T = se3_inv(se3_mul(se3_exp(dx), se3_inv(T)))
        torch.testing.assert_close(got[f], T, rtol=0, atol=1e-10)
