"""A tiny trained run (the ``tiny`` preset, ~20 s on one thread) shared by the app tests."""

import pytest
import torch


@pytest.fixture(scope="package")
def tiny_trained_run(tmp_path_factory):
    from train import run

    d = tmp_path_factory.mktemp("tiny_run")
    old = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: threads only add overhead
    try:
        assert run.main(["--preset", "tiny", "--run-dir", str(d)]) == 0
    finally:
        torch.set_num_threads(old)
    return d
