import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "core"))  # the framework tests' fake plugins


@pytest.fixture(autouse=True)
def _single_thread(single_torch_thread):
    """Small tensors (see ``single_torch_thread`` in the root conftest)."""
