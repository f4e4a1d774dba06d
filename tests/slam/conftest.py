import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "core"))  # the framework tests' fake plugins


@pytest.fixture(autouse=True)
def _single_thread():
    """Small tensors: one intra-op thread is faster and less sensitive to a busy CPU."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
