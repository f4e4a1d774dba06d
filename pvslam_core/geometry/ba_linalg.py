"""Linear algebra and safety helpers of the dense BA (:mod:`.ba`) and the Sim(3) pose graph (:mod:`.pose_graph`):
finiteness checks, the positive-definite solve, block-sparse assembly and the sparse LU, and the once-per-message
warning of the ``pvslam.ba`` logger."""
from __future__ import annotations

import logging
import re
from typing import Optional

import torch

__all__ = ["all_finite", "log_once", "solve_spd", "sparse_block_matrix", "sparse_solve", "SPARSE_MIN_POSES"]

log = logging.getLogger("pvslam.ba")
_LOGGED: set[str] = set()

# CPU pose systems with more free poses are solved sparsely: the dense Cholesky is faster below, the sparse LU above
# (docs/decisions.md: SPARSE_MIN_POSES)
SPARSE_MIN_POSES = 300


def log_once(msg: str) -> None:
    """Log a warning once per distinct message (numbers ignored, so per-iteration variants count once)."""
    key = re.sub(r"[0-9.e+-]+", "#", msg)
    if key not in _LOGGED:
        _LOGGED.add(key)
        log.warning(msg)


def all_finite(t: torch.Tensor) -> bool:
    """True when every element is finite.  Fast path: one reduction (NaN/Inf propagate into the sum); only an
    overflowing sum of finite values falls back to the element-wise test."""
    if t.numel() == 0:
        return True
    if bool(torch.isfinite(t.sum())):
        return True
    return bool(torch.isfinite(t).all())


def solve_spd(A: torch.Tensor, b: torch.Tensor) -> Optional[torch.Tensor]:
    """Solve the symmetric positive-definite system ``A x = b`` by Cholesky; None if A is not PD or x not finite.

    (A sparse LU from the dense assembly was slower than this dense Cholesky for the block-sparse systems of a
    global BA or a long pose graph up to a few thousand unknowns.)"""
    L, info = torch.linalg.cholesky_ex(A)
    if int(info) != 0:
        return None
    x = torch.cholesky_solve(b.unsqueeze(-1), L).squeeze(-1)
    return x if all_finite(x) else None


def sparse_block_matrix(br: torch.Tensor, bc: torch.Tensor, bv: torch.Tensor, F: int):
    """Symmetrised scipy CSC matrix ``[kF, kF]`` from ``k x k`` blocks ``bv [n, k, k]`` at block positions
    ``(br, bc)`` (duplicates summed)."""
    import scipy.sparse as sp

    k = bv.shape[-1]
    ar = torch.arange(k)
    rows = (br.cpu().view(-1, 1, 1) * k + ar.view(1, k, 1)).expand(-1, k, k)
    cols = (bc.cpu().view(-1, 1, 1) * k + ar.view(1, 1, k)).expand(-1, k, k)
    M = sp.coo_matrix((bv.detach().cpu().double().numpy().reshape(-1),
                       (rows.reshape(-1).numpy(), cols.reshape(-1).numpy())), shape=(k * F, k * F)).tocsc()
    return (0.5 * (M + M.T)).tocsc()


def sparse_solve(Hs, diag_add, b: torch.Tensor) -> Optional[torch.Tensor]:
    """Solve ``(Hs + diag(diag_add)) x = b`` with SuperLU; None on failure or a non-finite result."""
    import numpy as np
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    try:
        A = (Hs + sp.diags(np.asarray(diag_add, dtype=np.float64))).tocsc()
        x = splu(A).solve(b.detach().cpu().double().numpy())
    except (RuntimeError, ValueError):
        return None
    xt = torch.from_numpy(np.ascontiguousarray(x)).to(b.device, torch.float64)
    if not all_finite(xt):
        return None
    # the LU does not test definiteness: a positive-definite system gives b.x = x^T A x > 0
    bn = b.detach().cpu().double()
    if float(bn @ xt.cpu()) <= 0 and float(bn.abs().max()) > 0:
        return None
    return xt
