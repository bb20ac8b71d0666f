"""Stress tests of geometry.surface_distance, the targets of the mesh and point-cloud fits: signed distances to
a mesh (open3d, float32) and to an oriented cloud, PCA normals, and area-weighted surface samples. Meshes and
clouds at tiny and huge scales, duplicated points, zero-area triangles, queries exactly on the surface and at
the centre: finite outputs (the geometry package treats meshes of any scale as legal, see
``geometry.mesh_stats``). The targets are not differentiated, so no gradients are checked."""

from __future__ import annotations

import open3d  # noqa: F401  (imported at collection: its first import inside a test costs ~1 s)
import pytest
import torch
import trimesh

from geometry.surface_distance import (
    estimate_normals,
    mesh_signed_distance,
    point_cloud_signed_distance,
    surface_samples,
)
from toolkit.errors import ToolkitError


def _sphere():
    m = trimesh.creation.icosphere(2)
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.long)


def _cloud(n: int = 200) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)


@pytest.mark.parametrize("scale", [1e-20, 1e-6, 1.0, 1e6, 1e20])
def test_estimated_normals_of_tiny_huge_and_duplicated_clouds(scale):
    d = _cloud()
    pts = torch.cat([d, d[:40]]) * scale
    n = estimate_normals(pts)
    assert torch.isfinite(n).all() and torch.allclose(n.norm(dim=-1), torch.ones(len(pts)), atol=1e-5)
    assert float((n * torch.cat([d, d[:40]])).sum(-1).mean()) > 0.9  # outward


@pytest.mark.parametrize("flat", ["plane", "line"])
def test_normals_of_a_flat_cloud_are_one_clear_error(flat):
    """Points on a plane or a line bound no volume: one ToolkitError, not qhull's many-line RuntimeError."""
    p = torch.rand(200, 3, generator=torch.Generator().manual_seed(0))
    p[:, 2] = 0 if flat == "plane" else p[:, 0]
    if flat == "line":
        p[:, 1] = p[:, 0]
    with pytest.raises(ToolkitError, match=r"^estimate_normals: the points lie on a plane or a line"):
        estimate_normals(p)


@pytest.mark.parametrize("scale", [1e-20, 1.0, 1e20])
def test_cloud_signed_distance_on_the_points_at_the_centre_and_with_duplicates(scale):
    d = _cloud()
    pts = torch.cat([d, d, d]) * scale  # every point three times
    q = torch.cat([pts[:20], torch.zeros(1, 3), d[:5] * 3 * scale])
    sd = point_cloud_signed_distance(pts, torch.cat([d, d, d]), q)
    assert torch.isfinite(sd).all()
    assert float(sd[:20].abs().max()) == 0.0 and float(sd[20]) < 0 < float(sd[21:].min())


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_mesh_signed_distance_at_moderate_scales(scale):
    v, f = _sphere()
    q = torch.tensor([[0.0, 0, 0], [0, 0, 2.0], [0.5, 0.5, 0.5]]) * scale
    sd = mesh_signed_distance(v * scale, f, torch.cat([q, v[:5] * scale]))
    assert torch.isfinite(sd).all() and float(sd[0]) < 0 < float(sd[1])


@pytest.mark.parametrize("scale", [1e-30, 1e-12, 1e12, 1e19])
def test_mesh_signed_distance_of_a_huge_or_tiny_mesh(scale):
    """open3d measures in float32: the mesh is measured in its own unit frame, so a mesh in units of 1e19 does
    not overflow to inf and one of 1e-30 keeps its inside negative."""
    v, f = _sphere()
    sd = mesh_signed_distance(v * scale, f, torch.tensor([[0.0, 0, 0], [0, 0, 2.0], [0.5, 0.5, 0.5]]) * scale)
    assert torch.isfinite(sd).all() and float(sd[0]) < 0 < float(sd[1])
    assert float(sd[1]) == pytest.approx(scale, rel=1e-3)


@pytest.mark.parametrize("scale", [1e-10, 1e-3, 1.0, 1e3, 1e10])
def test_surface_samples_with_zero_area_triangles(scale):
    """A sphere plus collapsed triangles (all three corners on one vertex, or on a line): samples are finite,
    on the sphere, never drawn from the zero-area triangles."""
    v, f = _sphere()
    f = torch.cat([f, torch.tensor([[0, 0, 0], [1, 1, 2]])])
    p = surface_samples(v * scale, f, 200, torch.Generator().manual_seed(1))
    r = p.norm(dim=-1) / scale
    assert torch.isfinite(p).all() and float(r.max()) <= 1.0 + 1e-5 and float(r.min()) > 0.9


@pytest.mark.parametrize("scale", [1e-20, 1e-12, 1e12, 1e20])
def test_surface_samples_of_a_huge_or_tiny_mesh(scale):
    """The areas are relative, in float64: a mesh in units of 1e12 does not overflow them to inf (no distribution
    to draw from), nor one of 1e-12 underflow them to "zero surface area"."""
    v, f = _sphere()
    p = surface_samples(v * scale, f, 100, torch.Generator().manual_seed(1))
    r = (p / scale).norm(dim=-1)  # the norm of p itself would overflow float32 at 1e20
    assert torch.isfinite(p).all() and float(r.max()) <= 1.0 + 1e-5 and float(r.min()) > 0.9
