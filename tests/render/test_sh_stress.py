"""Stress tests of render.sh: spherical-harmonic colours toward directions of zero length (a camera centre on a
Gaussian's mean), of 1e-30 and 1e30 length, exactly along the coordinate axes and the diagonals, with huge
coefficients, in every degree. Outputs and gradients (coefficients, directions, means, camera centres) finite."""

from __future__ import annotations

import pytest
import torch

from render.sh import eval_sh, num_sh_bases, sh_to_color
from render.splat import rasterize
from tests.render import dense_reference as ref

DIRS = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1], [-1, 1, -1],
                     [0.0, 0, 0]])


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("length", [0.0, 1e-30, 1e-6, 1.0, 1e6, 1e30])
def test_eval_sh_along_axes_at_any_length(degree, length):
    g = torch.Generator().manual_seed(degree)
    dirs = (DIRS * length).requires_grad_(True)
    coeffs = torch.randn(len(DIRS), num_sh_bases(degree), 3, generator=g).requires_grad_(True)
    out = eval_sh(degree, coeffs, dirs)
    assert out.shape == (len(DIRS), 3) and torch.isfinite(out).all()
    (out * torch.randn(out.shape, generator=g)).sum().backward()
    assert torch.isfinite(coeffs.grad).all()
    assert (dirs.grad is None) == (degree == 0)  # degree 0 is direction-free
    assert dirs.grad is None or torch.isfinite(dirs.grad).all()


@pytest.mark.parametrize("magnitude", [1e-30, 1e6, 1e30])
def test_eval_sh_with_tiny_and_huge_coefficients(magnitude):
    """Coefficients up to 1e30 stay finite: every basis value is at most ~3 in magnitude."""
    g = torch.Generator().manual_seed(7)
    coeffs = (torch.randn(5, 16, 3, generator=g) * magnitude).requires_grad_(True)
    dirs = torch.randn(5, 3, generator=g).requires_grad_(True)
    out = eval_sh(3, coeffs, dirs)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert torch.isfinite(coeffs.grad).all() and torch.isfinite(dirs.grad).all()


def test_sh_to_color_with_a_camera_centre_on_a_mean():
    """The view direction of a Gaussian whose mean is the camera centre has zero length: its colour is the
    clamped DC term (+0.5), and no NaN reaches the gradients of means or centres."""
    g = torch.Generator().manual_seed(1)
    means = torch.tensor([[0.0, 0.0, 0.0], [1e-30, 0, 0], [0.3, -0.2, 2.0], [1e6, 0, 1e6]], requires_grad=True)
    centres = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 2.0]], requires_grad=True)
    coeffs = torch.randn(4, 16, 3, generator=g).requires_grad_(True)
    col = sh_to_color(3, coeffs, means, centres)
    assert col.shape == (2, 4, 3) and torch.isfinite(col).all() and float(col.detach().min()) >= 0
    (col * torch.randn(col.shape, generator=g)).sum().backward()
    for t in (means, centres, coeffs):
        assert torch.isfinite(t.grad).all()


def test_rasterize_with_sh_colours_seen_head_on_along_the_optical_axis():
    """SH colours through the splatter: Gaussians strung along the optical axis (view directions exactly
    (0, 0, 1)) and one just beyond the near plane (depth 0.02), degree 3, finite image and gradients."""
    V, K = ref.camera(16, 12)
    tz = float(V[0, 2, 3])
    means = torch.tensor([[0.0, 0.0, z] for z in (0.02 - tz, 0.5, 1.0, 3.0)], requires_grad=True)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 4)
    scales = torch.full((4, 3), 0.2)
    opac = torch.tensor([0.9, 0.5, 1 - 1e-7, 0.3])
    sh = torch.randn(4, 16, 3, generator=torch.Generator().manual_seed(2)).requires_grad_(True)
    img, alpha, _ = rasterize(means, quats, scales, opac, sh, V, K, 16, 12, sh_degree=3)
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    (img.sum() + alpha.sum()).backward()
    assert torch.isfinite(means.grad).all() and torch.isfinite(sh.grad).all()
