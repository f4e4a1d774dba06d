import pytest


@pytest.fixture(autouse=True)
def _single_thread(single_torch_thread):
    """The geometry tests use small tensors (see ``single_torch_thread`` in the root conftest)."""
