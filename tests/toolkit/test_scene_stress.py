"""Stress tests of toolkit.scene's activations: ``GaussianScene.from_activated`` inverts scales with a clamped
log and opacities with a clamped logit, and the activated views (``scales``, ``opacities``, ``unit_quats``) map
them back. Zero, denormal and huge scales, opacities of exactly 0 and 1, zero and tiny quaternions, in every
floating dtype a scene may hold: finite fields that pass ``validate`` and finite gradients."""

from __future__ import annotations

import pytest
import torch

from toolkit.scene import GaussianScene

DTYPES = [torch.float32, torch.float64, torch.bfloat16]


def _extreme_inputs(dtype: torch.dtype, scale_values: list[float]):
    n = len(scale_values)
    big = torch.finfo(dtype).max
    scales = torch.tensor(scale_values, dtype=torch.float64).clamp(max=big).to(dtype)[:, None].repeat(1, 3)
    opac = torch.tensor([0.0, 1e-9, 0.5, 1 - 1e-9, 1.0, 1.0][:n], dtype=torch.float64).to(dtype)
    quats = torch.zeros(n, 4, dtype=dtype)
    quats[1] = 1e-12  # tiny but normalizable
    quats[2:, 0] = 1.0
    return scales, opac, quats


def _check(dtype: torch.dtype, scale_values: list[float]):
    scales, opac, quats = _extreme_inputs(dtype, scale_values)
    scales.requires_grad_(True)
    opac.requires_grad_(True)
    n = scales.shape[0]
    s = GaussianScene.from_activated(torch.zeros(n, 3, dtype=dtype), scales, opac, torch.rand(n, 3).to(dtype), quats)
    for name in ("log_scales", "opacity_logits"):
        assert torch.isfinite(getattr(s, name)).all(), (name, getattr(s, name))
    assert s.validate() is s
    assert torch.isfinite(s.opacities).all() and torch.isfinite(s.unit_quats).all()
    assert torch.allclose(s.unit_quats.float().norm(dim=-1), torch.ones(n), atol=1e-2)
    (s.log_scales.float().sum() + s.opacity_logits.float().sum()).backward()
    assert torch.isfinite(scales.grad).all() and torch.isfinite(opac.grad).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_from_activated_with_zero_denormal_and_huge_scales_and_saturated_opacities(dtype):
    _check(dtype, [0.0, 1e-45, 1e-8, 1.0, 1e30, 3e38])


def test_from_activated_in_float16_with_positive_scales():
    """float16's own range up to its largest value; from 2e-5 up, where d log(s) / ds = 1 / s is itself a
    float16 number (below it the gradient overflows whatever the code does)."""
    _check(torch.float16, [2e-5, 1e-4, 1.0, 1e3, 6e4, 65504.0])


def test_from_activated_in_float16_with_a_zero_scale():
    """A zero scale is what the clamped log exists for (float32 gives log(1e-8)); in float16 it stays finite
    too: the floor is float16's smallest normal number where 1e-8 would round to 0."""
    _check(torch.float16, [0.0, 2e-5, 1.0, 1e3, 6e4, 65504.0])


@pytest.mark.parametrize("logit", [-1e4, -88.0, 0.0, 88.0, 1e4])
def test_activated_views_at_extreme_logits_have_finite_gradients(logit):
    """Saturated opacity logits and log-scales up to float32's exp range (88), a zero quaternion and a 1e-12
    one: finite activations and gradients (sigmoid and exp saturate instead of overflowing)."""
    n = 3
    quats = torch.tensor([[0.0, 0, 0, 0], [1e-12, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]])
    s = GaussianScene(means=torch.zeros(n, 3), quats=quats,
                      log_scales=torch.full((n, 3), float(max(min(logit, 88.0), -88.0))),
                      opacity_logits=torch.full((n,), float(logit)), features=torch.rand(n, 3),
                      part=torch.zeros(n, dtype=torch.int8), metadata={})
    for name in ("quats", "log_scales", "opacity_logits"):
        getattr(s, name).requires_grad_(True)
    outs = (s.scales, s.opacities, s.unit_quats)
    assert all(torch.isfinite(t).all() for t in outs)
    assert torch.allclose(s.unit_quats.norm(dim=-1), torch.ones(n))
    sum(t.sum() for t in outs).backward()
    for name in ("quats", "log_scales", "opacity_logits"):
        assert torch.isfinite(getattr(s, name).grad).all(), name
