"""Stress tests of train.losses.metrics: PSNR of identical images (a log of a zero error, capped by eps), SSIM of
zero-variance images and of the smallest images it takes (2x2, odd shapes), composites with masks outside
[0, 1], dilation wider than the image, and bootstrap intervals of constant, tiny and huge samples. Scores
and their gradients with respect to the prediction stay finite."""

from __future__ import annotations

import math

import pytest
import torch

from train.losses.metrics import (
    bootstrap_mean_interval,
    composite_on_white,
    dilate_mask,
    downsample_to,
    psnr,
    ssim,
)


def _pairs():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 9, 7, generator=g)
    return {
        "identical": (x, x.clone()),
        "constant-identical": (torch.full_like(x, 0.5), torch.full_like(x, 0.5)),
        "black-vs-white": (torch.zeros_like(x), torch.ones_like(x)),
        "black-identical": (torch.zeros_like(x), torch.zeros_like(x)),
        "one-lsb-apart": (torch.full_like(x, 0.5), torch.full_like(x, 0.5 + 2**-24)),
    }


@pytest.mark.parametrize("case", list(_pairs()))
def test_psnr_and_ssim_of_identical_constant_and_opposite_images(case):
    pred, target = _pairs()[case]
    pred = pred.clone().requires_grad_(True)
    p, s = psnr(pred, target), ssim(pred, target)
    assert torch.isfinite(p).all() and torch.isfinite(s).all()
    # SSIM's local variances are E[x^2] - E[x]^2 in float32: a hair above 1 on near-constant images.
    assert float(p.detach().max()) <= 100.0 + 1e-3 and float(s.detach().max()) <= 1.0 + 1e-3
    (p.sum() + s.sum()).backward()
    assert torch.isfinite(pred.grad).all()


@pytest.mark.parametrize("hw", [(2, 2), (2, 3), (3, 2), (4, 4), (5, 64)])
def test_ssim_on_the_smallest_images(hw):
    g = torch.Generator().manual_seed(1)
    a = torch.rand(1, 3, *hw, generator=g).requires_grad_(True)
    s = ssim(a, torch.full((1, 3, *hw), 0.5))
    assert torch.isfinite(s).all()
    s.sum().backward()
    assert torch.isfinite(a.grad).all()


def test_composite_dilate_and_downsample_at_the_extremes():
    g = torch.Generator().manual_seed(2)
    img = torch.rand(2, 3, 6, 5, generator=g).requires_grad_(True)
    for mask in (torch.zeros(2, 1, 6, 5), torch.ones(2, 6, 5), torch.randn(2, 1, 6, 5, generator=g) * 1e6):
        out = composite_on_white(img, mask)
        assert torch.isfinite(out).all()
        out.sum().backward()
        assert torch.isfinite(img.grad).all()
    grown = dilate_mask(torch.zeros(1, 1, 6, 5).index_put_((torch.tensor([0]), torch.tensor([0]), torch.tensor([2]),
                                                            torch.tensor([2])), torch.tensor(1.0)), 40)
    assert torch.isfinite(grown).all() and float(grown.min()) == 1.0  # wider than the image: all of it
    small = downsample_to(torch.rand(1, 3, 1, 97, generator=g), 1)
    assert small.shape == (1, 3, 1, 1) and torch.isfinite(small).all()


@pytest.mark.parametrize("values", [[0.5] * 10, [1e-300, 2e-300, 3e-300], [1e300, -1e300, 1e300],
                                    [7.0, None, math.nan, 7.0]])
def test_bootstrap_interval_of_constant_tiny_huge_and_gappy_samples(values):
    lo, hi = bootstrap_mean_interval(values, resamples=200)
    assert math.isfinite(lo) and math.isfinite(hi) and lo <= hi
