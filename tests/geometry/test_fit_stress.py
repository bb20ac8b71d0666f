"""Stress tests of geometry.fit: the SDF fit's every term on (eikonal through a double backward, landmarks,
the uniform Laplacian of the differentiably extracted mesh) for point clouds 1e-6 and 1e6 units across, with
duplicated points and all landmarks on one point. The fit's non-finite-step guard would hide a NaN, so every
step must have run (no skipped step), with finite terms and a finite mesh."""

from __future__ import annotations

import math

import pytest
import torch
import torch._dynamo  # noqa: F401  (the first torch optimizer imports it, ~2 s once per process: pay it here)

from geometry.fit import FitConfig, fit_points, fit_sdf_to_targets
from geometry.sdf import SDFNetConfig, SphereInit


def _cfg(**kw) -> FitConfig:
    base = dict(steps=4, batch=64, pool=512, extract_res=8, pretrain_steps=2, eikonal_batch=32, w_laplacian=0.1,
                laplacian_every=1, laplacian_res=8, net=SDFNetConfig(hidden=16, n_freqs=2, feature_dim=2))
    base.update(kw)
    return FitConfig(**base)


def _sphere_cloud(n: int = 300) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)


def _assert_clean(res) -> None:
    assert res.skipped_steps == 0
    assert res.history and all(math.isfinite(v) for h in res.history for k, v in h.items() if k != "step")
    assert "eikonal" in res.history[-1] and "laplacian" in res.history[-1]
    assert torch.isfinite(res.verts).all() and res.faces.shape[0] > 0
    assert all(torch.isfinite(p).all() for p in res.net.parameters())


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_point_fit_at_tiny_and_huge_scales_with_duplicates(scale):
    d = _sphere_cloud()
    pts = torch.cat([d, d[:50]]) * scale  # 50 points given twice
    nrm = torch.cat([d, d[:50]])
    res = fit_points(pts, nrm, _cfg())
    _assert_clean(res)
    r = res.verts.norm(dim=-1)
    assert float(r.max()) < 3 * scale and float(r.min()) > 0.05 * scale


def test_sdf_fit_with_coincident_landmarks_and_saturated_targets():
    """Every landmark on one point, and targets far beyond the truncation band (clamped): finite terms."""
    d = _sphere_cloud(400)
    pts = d * torch.rand(400, 1, generator=torch.Generator().manual_seed(1)) * 2
    target = (pts.norm(dim=-1) - 1) * 1e6
    box = SDFNetConfig(hidden=16, n_freqs=2, feature_dim=2, box_min=(-2.0,) * 3, box_max=(2.0,) * 3)
    landmarks = torch.tensor([[0.0, 0.0, -1.0]]).expand(8, 3)
    res = fit_sdf_to_targets(pts, target, _cfg(net=box, w_landmarks=1.0), landmarks=landmarks,
                             sphere=SphereInit((0.0, 0.0, 0.0), 1.0))
    _assert_clean(res)
    assert "landmarks" in res.history[-1]
