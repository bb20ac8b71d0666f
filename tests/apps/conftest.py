"""Shared by the app tests: a tiny trained run (the ``tiny`` preset, ~20 s on one thread), a face finder, a photo."""

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


@pytest.fixture(scope="package")
def finder():
    """One ``apps.photo.faces.FaceFinder`` (mediapipe's graphs take a second to load)."""
    pytest.importorskip("mediapipe")
    from apps.photo.faces import FaceFinder

    with FaceFinder() as ff:
        yield ff


@pytest.fixture(scope="package")
def astronaut():
    """[512, 512, 3] uint8: scikit-image's public-domain portrait (Eileen Collins), her face upright."""
    return pytest.importorskip("skimage.data").astronaut()
