"""Comparison helpers for the raft_gru tests (imported through the sys.path entry set by this folder's conftest)."""
from __future__ import annotations

import torch

# Fixture README "Observed tolerances": per-op recomputation spread <= 6e-6; the target is <= 1e-5 absolute.
ATOL = 1e-5
# ... and about 1e-4 for a whole chain of ops computed in another order: the encoders' outputs (a dozen convolutions
# and norms) on a CPU whose convolution kernels sum in another order than the machine that recorded the fixture.
CHAIN_ATOL = 1e-4
ETA_RTOL = 1e-5  # eta is O(1e-2): compared relatively


def max_abs_err(got: torch.Tensor, want: torch.Tensor) -> float:
    return (got.double() - want.double()).abs().max().item()


def assert_close(name: str, got: torch.Tensor, want: torch.Tensor, atol: float = ATOL) -> None:
    assert got.shape == want.shape, f"{name}: shape {tuple(got.shape)} != {tuple(want.shape)}"
    err = max_abs_err(got, want)
    assert err <= atol, f"{name}: max abs error {err:.3e} > {atol:.0e}"


def assert_eta_close(got: torch.Tensor, want: torch.Tensor, name: str = "eta") -> None:
    assert got.shape == want.shape, f"{name}: shape {tuple(got.shape)} != {tuple(want.shape)}"
    rel = ((got.double() - want.double()).abs() / want.double().abs()).max().item()
    assert rel <= ETA_RTOL, f"{name}: max relative error {rel:.3e} > {ETA_RTOL:.0e}"
