"""The tiny preset's trained run shared by the stage tests: trained once (~20 s on one thread) and never
changed (a test that runs stages on a run works on a copy)."""

import pytest
import torch


@pytest.fixture(scope="package")
def tiny_run(tmp_path_factory):
    from train import run

    d = tmp_path_factory.mktemp("run")
    torch.set_num_threads(1)  # tiny tensors: threads only add overhead (and thrash on a loaded machine)
    assert run.main(["--preset", "tiny", "--run-dir", str(d)]) == 0
    return d
