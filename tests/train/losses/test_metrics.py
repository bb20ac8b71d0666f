import math

import pytest
import torch

from toolkit import ToolkitError
from train.losses.metrics import (
    bootstrap_mean_interval,
    composite_on_white,
    psnr,
    ssim,
    summarize,
    table1_markdown,
)


def test_psnr_known_value():
    a = torch.zeros(2, 3, 8, 8)
    b = torch.full((2, 3, 8, 8), 0.1)
    assert torch.allclose(psnr(a, b), torch.full((2,), 20.0), atol=1e-4)
    assert torch.isfinite(psnr(a, a)).all()


def test_ssim_identity_and_degradation():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 32, 32, generator=g)
    assert torch.allclose(ssim(x, x), torch.ones(2), atol=1e-5)
    noisy = (x + 0.2 * torch.randn(2, 3, 32, 32, generator=g)).clamp(0, 1)
    assert (ssim(x, noisy) < 0.9).all()
    assert torch.isfinite(ssim(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4))).all()
    assert torch.allclose(ssim(x[..., :2, :2], x[..., :2, :2]), torch.ones(2), atol=1e-5)  # the smallest size
    with pytest.raises(ToolkitError, match="ssim: images must be at least 2x2 pixels, got 1x1"):
        ssim(torch.zeros(1, 3, 1, 1), torch.zeros(1, 3, 1, 1))


def test_composite_on_white_ignores_background():
    x = torch.rand(1, 3, 8, 8)
    y = x.clone()
    y[..., :4] = 0.0  # differ only outside the mask
    m = torch.zeros(1, 8, 8)
    m[..., 4:] = 1
    assert torch.equal(composite_on_white(x, m), composite_on_white(y, m))
    assert composite_on_white(x, m)[..., :4].eq(1).all()


def test_shape_mismatch_is_clear():
    with pytest.raises(ToolkitError, match="one shape"):
        psnr(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))


def test_table1_layout():
    md = table1_markdown({"DiT-Gaze": {"gaze_error_deg": 3.21, "psnr": 27.5, "ssim": 0.91}, "U-Net": {}})
    lines = md.splitlines()
    assert lines[0].startswith("| Method | Gaze") and "PSNR" in lines[0] and "LPIPS" in lines[0]
    assert "| DiT-Gaze | 3.21 | n/a | 0.910 | 27.50 | n/a |" in lines[2]
    assert lines[3].count("n/a") == 8
    assert summarize([1.0, None, 3.0]) == 2.0 and summarize([None]) is None and summarize([math.nan]) is None


def test_bootstrap_interval_brackets_the_mean_and_narrows_with_more_samples():
    g = torch.Generator().manual_seed(0)
    few = (torch.randn(12, generator=g) * 4 + 6).tolist()
    many = (torch.randn(400, generator=g) * 4 + 6).tolist()
    lo, hi = bootstrap_mean_interval(few)
    assert lo < summarize(few) < hi
    # About 2 x 1.96 standard errors wide (sd 4): ~4.5 for 12 samples, ~0.8 for 400.
    assert 2.5 < hi - lo < 7.0
    lo2, hi2 = bootstrap_mean_interval(many)
    assert lo2 < 6.0 < hi2 and hi2 - lo2 < 1.2
    assert bootstrap_mean_interval(few) == (lo, hi)  # a fixed seed: a report is reproducible
    assert bootstrap_mean_interval(few + [None, float("nan")]) == (lo, hi)  # missing scores are left out


def test_bootstrap_interval_of_degenerate_samples():
    assert bootstrap_mean_interval([]) is None and bootstrap_mean_interval([3.0]) is None
    assert bootstrap_mean_interval([None, float("nan"), 2.0]) is None
    lo, hi = bootstrap_mean_interval([5.0] * 10)
    assert lo == hi == 5.0
    lo, hi = bootstrap_mean_interval([1e30, -1e30, 0.0, 1e-30])  # extreme values: finite bounds
    assert math.isfinite(lo) and math.isfinite(hi) and lo <= hi
