"""One torch thread for the train tests: on the shared 2-core machine, 2 threads contending with other
processes made small convolutions over 10x slower. Restored after each module."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
