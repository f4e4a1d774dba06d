import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread():
    """The geometry tests use small tensors: one intra-op thread is faster and far less sensitive to a busy CPU."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
