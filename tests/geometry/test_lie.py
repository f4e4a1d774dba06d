import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pvslam_core.geometry.lie import (
    hat,
    identity_se3,
    identity_sim3,
    quat_to_rotmat,
    rotmat_to_quat,
    se3_act,
    se3_adjoint,
    se3_exp,
    se3_from_matrix,
    se3_interpolate,
    se3_inv,
    se3_log,
    se3_mul,
    se3_to_matrix,
    sim3_act,
    sim3_exp,
    sim3_from_se3,
    sim3_inv,
    sim3_log,
    sim3_mul,
)

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 2e-5, torch.float64: 1e-11}


def rand_tangent(n, dtype, max_angle=3.1, gen=None, scale_t=1.0):
    gen = gen or torch.Generator().manual_seed(0)
    tau = torch.randn(n, 3, generator=gen, dtype=torch.float64) * scale_t
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    ang = torch.rand(n, 1, generator=gen, dtype=torch.float64) * max_angle
    return torch.cat([tau, axis * ang], -1).to(dtype)


def qdist(a, b):
    return torch.minimum((a - b).abs().amax(-1), (a + b).abs().amax(-1))


@pytest.mark.parametrize("dtype", DTYPES)
def test_quaternion_matrix_against_scipy(dtype):
    q = torch.nn.functional.normalize(torch.randn(500, 4, dtype=torch.float64), dim=-1)
    R_ref = torch.from_numpy(Rotation.from_quat(q.numpy()).as_matrix())
    assert torch.allclose(quat_to_rotmat(q.to(dtype)).double(), R_ref, atol=TOL[dtype] * 10)
    q2 = rotmat_to_quat(R_ref.to(dtype)).double()
    assert qdist(q2, q).max() < TOL[dtype] * 10
    assert (q2[:, 3] >= 0).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_so3_exp_against_scipy(dtype):
    xi = rand_tangent(200, torch.float64)
    T = se3_exp(xi.to(dtype))
    R_ref = torch.from_numpy(Rotation.from_rotvec(xi[:, 3:].numpy()).as_matrix())
    assert torch.allclose(quat_to_rotmat(T[:, 3:]).double(), R_ref, atol=TOL[dtype] * 10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_se3_exp_is_matrix_exponential(dtype):
    xi = rand_tangent(100, torch.float64)
    G = torch.zeros(100, 4, 4, dtype=torch.float64)
    G[:, :3, :3] = hat(xi[:, 3:])
    G[:, :3, 3] = xi[:, :3]
    M = torch.linalg.matrix_exp(G)
    assert torch.allclose(se3_to_matrix(se3_exp(xi.to(dtype))).double(), M, atol=TOL[dtype] * 20)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-6, 1e-4, 1e-2, 1.0, 2.5, math.pi - 1e-3, math.pi - 1e-6])
def test_se3_log_exp_roundtrip_near_identity_and_pi(dtype, angle):
    axis = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), dim=-1)
    xi = torch.cat([torch.tensor([[0.5, -0.2, 1.0]]).expand(3, 3), axis * angle], -1).to(dtype)
    out = se3_log(se3_exp(xi))
    assert torch.isfinite(out).all()
    tol = TOL[dtype] * (50 if angle > 3 else 5)
    assert (out - xi).abs().max() < tol, (out - xi).abs().max()
    xs = torch.cat([xi, torch.full((3, 1), 0.3, dtype=dtype)], -1)
    outs = sim3_log(sim3_exp(xs))
    assert (outs - xs).abs().max() < tol * 5


@pytest.mark.parametrize("dtype", DTYPES)
def test_se3_log_at_exactly_pi(dtype):
    q = torch.tensor([[0.0, 1.0, 0.0, 0.0]], dtype=dtype)  # rotation by pi about y
    T = torch.cat([torch.tensor([[1.0, 2.0, 3.0]], dtype=dtype), q], -1)
    xi = se3_log(T)
    assert torch.isfinite(xi).all()
    assert abs(float(xi[0, 3:].norm()) - math.pi) < 1e-5
    assert torch.allclose(se3_to_matrix(se3_exp(xi)), se3_to_matrix(T), atol=1e-5)


@pytest.mark.parametrize("dtype", DTYPES)
def test_group_laws(dtype):
    g = torch.Generator().manual_seed(3)
    A, B, C = (se3_exp(rand_tangent(50, dtype, gen=g)) for _ in range(3))
    tol = TOL[dtype] * 50
    # associativity and identity / inverse
    assert torch.allclose(se3_to_matrix(se3_mul(se3_mul(A, B), C)), se3_to_matrix(se3_mul(A, se3_mul(B, C))), atol=tol)
    I = identity_se3(50, dtype)
    assert torch.allclose(se3_to_matrix(se3_mul(A, se3_inv(A))), se3_to_matrix(I), atol=tol)
    assert torch.allclose(se3_to_matrix(se3_mul(I, A)), se3_to_matrix(A), atol=tol)
    # matrix representation is a homomorphism; action matches the matrix
    assert torch.allclose(se3_to_matrix(se3_mul(A, B)), se3_to_matrix(A) @ se3_to_matrix(B), atol=tol)
    X = torch.randn(50, 3, dtype=dtype, generator=g)
    Xh = torch.cat([X, torch.ones(50, 1, dtype=dtype)], -1)
    assert torch.allclose(se3_act(A, X), (se3_to_matrix(A) @ Xh.unsqueeze(-1)).squeeze(-1)[:, :3], atol=tol)
    assert torch.allclose(se3_to_matrix(se3_from_matrix(se3_to_matrix(A))), se3_to_matrix(A), atol=tol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_adjoint(dtype):
    g = torch.Generator().manual_seed(4)
    T = se3_exp(rand_tangent(30, dtype, gen=g))
    xi = rand_tangent(30, dtype, gen=g, max_angle=0.5)
    lhs = se3_mul(se3_mul(T, se3_exp(xi)), se3_inv(T))
    rhs = se3_exp((se3_adjoint(T) @ xi.unsqueeze(-1)).squeeze(-1))
    assert torch.allclose(se3_to_matrix(lhs), se3_to_matrix(rhs), atol=TOL[dtype] * 100)


def test_broadcasting():
    A = se3_exp(rand_tangent(4, torch.float64)).reshape(4, 1, 7)
    B = se3_exp(rand_tangent(5, torch.float64)).reshape(1, 5, 7)
    assert se3_mul(A, B).shape == (4, 5, 7)
    X = torch.randn(4, 5, 3, dtype=torch.float64)
    assert se3_act(A, X).shape == (4, 5, 3)
    S = sim3_from_se3(A, torch.full((4, 1), 2.0, dtype=torch.float64))
    assert S.shape == (4, 1, 8) and torch.all(S[..., 7] == 2.0)
    assert sim3_mul(S, sim3_from_se3(B, 1.0)).shape == (4, 5, 8)


def test_interpolate():
    g = torch.Generator().manual_seed(5)
    A, B = se3_exp(rand_tangent(10, torch.float64, gen=g)), se3_exp(rand_tangent(10, torch.float64, gen=g))
    assert torch.allclose(se3_to_matrix(se3_interpolate(A, B, 0.0)), se3_to_matrix(A), atol=1e-10)
    assert torch.allclose(se3_to_matrix(se3_interpolate(A, B, 1.0)), se3_to_matrix(B), atol=1e-10)
    M = se3_interpolate(A, B, 0.5)
    # the midpoint splits the relative motion into two equal halves
    d1 = se3_log(se3_mul(M, se3_inv(A)))
    d2 = se3_log(se3_mul(B, se3_inv(M)))
    assert torch.allclose(d1, d2, atol=1e-9)
    alphas = torch.linspace(0, 1, 10, dtype=torch.float64)
    assert se3_interpolate(A, B, alphas).shape == (10, 7)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sim3_laws(dtype):
    g = torch.Generator().manual_seed(6)
    x = torch.cat([rand_tangent(40, torch.float64, gen=g), 0.5 * torch.randn(40, 1, generator=g, dtype=torch.float64)], -1)
    A = sim3_exp(x.to(dtype))
    B = sim3_exp(x.flip(0).to(dtype))
    X = torch.randn(40, 3, dtype=dtype, generator=g)
    tol = TOL[dtype] * 100
    assert torch.allclose(sim3_act(sim3_mul(A, B), X), sim3_act(A, sim3_act(B, X)), atol=tol)
    assert torch.allclose(sim3_act(sim3_inv(A), sim3_act(A, X)), X, atol=tol)
    assert torch.allclose(sim3_log(A), x.to(dtype), atol=tol)
    assert torch.allclose(sim3_act(identity_sim3(40, dtype), X), X)
    # Sim3 exp equals the 4x4 matrix exponential of the generator
    G = torch.zeros(40, 4, 4, dtype=torch.float64)
    G[:, :3, :3] = hat(x[:, 3:6]) + x[:, 6:7, None] * torch.eye(3, dtype=torch.float64)
    G[:, :3, 3] = x[:, :3]
    M = torch.linalg.matrix_exp(G)
    S = sim3_exp(x)
    assert torch.allclose(S[:, :3], M[:, :3, 3], atol=1e-10)
    assert torch.allclose(S[:, 7:8, None] * quat_to_rotmat(S[:, 3:7]), M[:, :3, :3], atol=1e-10)


def test_gradients_finite_at_identity():
    for fn, dim in ((se3_exp, 6), (lambda x: sim3_exp(x), 7)):
        x = torch.zeros(3, dim, dtype=torch.float64, requires_grad=True)
        fn(x).sum().backward()
        assert torch.isfinite(x.grad).all()
    T = identity_se3(2).requires_grad_(True)
    se3_log(T).sum().backward()
    assert torch.isfinite(T.grad).all()


def test_exp_jacobian_finite_difference():
    """d/dxi Exp(xi) at xi0 against central differences (autograd through the Taylor branches)."""
    xi0 = torch.tensor([0.1, -0.2, 0.3, 1e-5, 2e-5, -1e-5], dtype=torch.float64, requires_grad=True)
    J = torch.autograd.functional.jacobian(lambda x: se3_to_matrix(se3_exp(x)).reshape(-1), xi0)
    h = 1e-6
    Jfd = torch.stack([
        (se3_to_matrix(se3_exp(xi0.detach() + h * e)) - se3_to_matrix(se3_exp(xi0.detach() - h * e))).reshape(-1) / (2 * h)
        for e in torch.eye(6, dtype=torch.float64)
    ], -1)
    assert torch.allclose(J, Jfd, atol=1e-7)


angles = st.floats(min_value=0.0, max_value=math.pi - 1e-3)
coords = st.floats(min_value=-5.0, max_value=5.0)


@settings(max_examples=60, deadline=None)
@given(st.tuples(coords, coords, coords), st.tuples(coords, coords, coords), angles,
       st.floats(min_value=-2.0, max_value=2.0))
def test_property_log_exp(t, axis, angle, sigma):
    a = np.asarray(axis, dtype=np.float64)
    if np.linalg.norm(a) < 1e-3:
        a = np.array([0.0, 0.0, 1.0])
    a = a / np.linalg.norm(a)
    xi = torch.tensor(list(t) + list(a * angle), dtype=torch.float64)
    assert torch.allclose(se3_log(se3_exp(xi)), xi, atol=1e-8)
    xs = torch.cat([xi, torch.tensor([sigma], dtype=torch.float64)])
    assert torch.allclose(sim3_log(sim3_exp(xs)), xs, atol=1e-8)
    T = se3_exp(xi)
    assert torch.allclose(se3_to_matrix(se3_inv(T)), torch.linalg.inv(se3_to_matrix(T)), atol=1e-9)


def test_sim3_W_closed_form_matches_matrix_exponential():
    """The closed-form / series Sim3 'V' matrix equals its definition through a 6x6 matrix exponential,
    ``expm([[M, I], [0, 0]]) = [[e^M, W], [0, I]]``, over tiny, small, mixed and large arguments (both branches and
    the switch between them at max(|sigma|, theta) = 0.1)."""
    from pvslam_core.geometry.lie import _sim3_W, hat

    gen = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=torch.float64), dim=-1)
    thetas = torch.tensor([0.0, 1e-9, 1e-6, 1e-3, 0.05, 0.0999, 0.1001, 0.3, 1.0, 2.5, 3.1], dtype=torch.float64)
    sigmas = torch.tensor([0.0, -1e-8, 1e-6, -1e-3, 0.05, 0.0999, -0.1001, 0.4, -1.2, 3.0], dtype=torch.float64)
    T, S = torch.meshgrid(thetas, sigmas, indexing="ij")
    phi = dirs[torch.arange(T.numel()) % 64] * T.reshape(-1, 1)
    sigma = S.reshape(-1, 1)
    M = hat(phi) + sigma[..., None] * torch.eye(3, dtype=torch.float64)
    G = torch.zeros(phi.shape[0], 6, 6, dtype=torch.float64)
    G[:, :3, :3] = M
    G[:, :3, 3:] = torch.eye(3, dtype=torch.float64)
    ref = torch.linalg.matrix_exp(G)[:, :3, 3:]
    W = _sim3_W(phi, sigma)
    err = (W - ref).abs().amax(dim=(-2, -1)) / ref.abs().amax(dim=(-2, -1))
    assert float(err.max()) < 1e-13, float(err.max())
