"""Repository-wide pytest fixtures.

``shared_dir``: the project's shared folder (golden fixtures, real KITTI excerpts, reference notes). It lives
beside the checkout (``<repo>/../shared``), on every development machine and in CI; ``PVSLAM_SHARED`` points
elsewhere. A test that needs it FAILS when it is missing (a silent skip would hide that CI tested nothing);
set ``PVSLAM_ALLOW_MISSING_SHARED=1`` to skip those tests instead on a machine that really has no copy.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent


def find_shared_dir() -> Path:
    env = os.environ.get("PVSLAM_SHARED")
    return Path(env).resolve() if env else (REPO_ROOT.parent / "shared").resolve()


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    path = find_shared_dir()
    if not path.is_dir():
        msg = (f"shared folder not found at {path} (expected beside the checkout, or set PVSLAM_SHARED); "
               "set PVSLAM_ALLOW_MISSING_SHARED=1 to skip the tests that need it")
        if os.environ.get("PVSLAM_ALLOW_MISSING_SHARED") == "1":
            pytest.skip(msg)
        pytest.fail(msg)
    return path


@pytest.fixture(scope="session")
def fixtures_dir(shared_dir: Path) -> Path:
    """``shared/fixtures``: golden outputs of the original upstream networks (see its README)."""
    return shared_dir / "fixtures"


@pytest.fixture
def single_torch_thread():
    """One intra-op torch thread for the test (restored after): faster on small tensors and far less sensitive
    to a busy CPU.  Folders of small-tensor tests make it autouse in their conftest."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
