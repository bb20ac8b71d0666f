"""Stress tests of train.losses.image (masked L1 + SSIM per region): zero-variance images (SSIM's variance terms
are 0), identical images (L1 at its kink), saturated and out-of-range predictions, a one-pixel region,
fractional masks down to 1e-30 and masks outside [0, 1], predictions of 1x1 and 3x3 pixels against a larger
target, and bf16 autocast. The loss terms and the gradient with respect to the prediction stay finite."""

from __future__ import annotations

import pytest
import torch

from train.losses import ImageLoss

B, S = 2, 16


def _one_pixel_mask() -> torch.Tensor:
    m = torch.zeros(B, 1, S, S)
    m[:, :, 7, 9] = 1.0
    return m


def _cases() -> dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    rand = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    ones = torch.ones(B, 1, S, S)
    return {
        "constant-identical": (torch.full((B, 3, S, S), 0.5), torch.full((B, 3, S, S), 0.5), ones),
        "black-identical": (torch.zeros(B, 3, S, S), torch.zeros(B, 3, S, S), ones),
        "white-vs-black": (torch.ones(B, 3, S, S), torch.zeros(B, 3, S, S), ones),
        "out-of-range": (torch.full((B, 3, S, S), 1e3), torch.full((B, 3, S, S), -1e3), ones),
        "one-pixel-region": (rand(B, 3, S, S), rand(B, 3, S, S), _one_pixel_mask()),
        "faint-mask": (rand(B, 3, S, S), rand(B, 3, S, S), torch.full((B, 1, S, S), 1e-30)),
        "mask-outside-0-1": (rand(B, 3, S, S), rand(B, 3, S, S), torch.randn(B, 1, S, S, generator=g) * 1e3),
        "1x1-prediction": (rand(B, 3, 1, 1), rand(B, 3, S, S), ones),
        "3x3-prediction": (rand(B, 3, 3, 3), torch.zeros(B, 3, S, S), ones),
    }


CASES = _cases()


@pytest.fixture(scope="module")
def loss_fn():
    return ImageLoss()


@pytest.mark.parametrize("case", list(CASES))
def test_region_loss_on_degenerate_images_and_masks(loss_fn, case):
    pred, target, mask = (t.clone() for t in CASES[case])
    pred.requires_grad_(True)
    terms = loss_fn.region_loss(pred, target, mask)
    assert all(torch.isfinite(v) for v in terms.values()), {k: float(v.detach()) for k, v in terms.items()}
    terms["total"].backward()
    assert torch.isfinite(pred.grad).all()


@pytest.mark.parametrize("case", ["constant-identical", "out-of-range", "one-pixel-region"])
def test_all_regions_under_bf16_autocast(loss_fn, case):
    """The loss computes in float32 under autocast: extreme bf16 inputs give a finite float32 total."""
    pred, target, mask = (t.clone() for t in CASES[case])
    pred = pred.to(torch.bfloat16).requires_grad_(True)
    masks = {"head": mask, "face": mask * 0, "eyes": mask}
    with torch.autocast("cpu", dtype=torch.bfloat16):
        total, logs = loss_fn({"head": pred, "face": pred, "eyes": pred}, target, masks)
    assert total.dtype == torch.float32 and torch.isfinite(total)
    assert all(v == v and abs(v) != float("inf") for v in logs.values())
    total.backward()
    assert torch.isfinite(pred.grad.float()).all()
