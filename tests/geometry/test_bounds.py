"""Every count, size and tolerance the geometry API takes is checked before the work starts (the CLI's flags
are covered by tests/fuzz/test_cli_geometry.py); tiny and huge meshes are measured right."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from geometry.cleanup import CleanupConfig, clean_mesh, remeshed_faces
from geometry.fit import FitConfig, fit_sdf_to_targets
from geometry.init_gaussians import InitConfig, init_gaussians
from geometry.mesh_stats import inspect_mesh, sample_surface
from geometry.render_sheet import check_sheet
from toolkit.errors import ToolkitError


def _sphere(sub=1, r=1.0):
    m = trimesh.creation.icosphere(sub)
    return torch.tensor(m.vertices * r, dtype=torch.float32), torch.tensor(m.faces)


@pytest.mark.parametrize("field, value, match", [
    ("weld_tolerance", math.nan, r"weld_tolerance: expected a fraction .* got nan"),
    ("weld_tolerance", -1e-3, r"weld_tolerance: .* got -0\.001"),
    ("min_component_fraction", 1.5, r"min_component_fraction: .* \[0, 1\]"),
    ("max_hole_edges", -1, r"max_hole_edges: .* got -1"),
    ("remesh_edge_fraction", math.inf, r"remesh_edge_fraction: .* got inf"),
    ("remesh_edge_fraction", 1e-6, r"remesh_edge_fraction: an edge of 1e-06 x the diagonal would remesh"),
    ("remesh_iterations", 10**9, r"remesh_iterations: .* \[1, 100\]"),
    ("taubin_steps", 10**9, r"taubin_steps: expected a number of smoothing steps in \[0, 1000\]"),
    ("taubin_lambda", math.nan, r"taubin_lambda: .* got nan"),
    ("target_faces", 2, r"target_faces: .* \[4, "),
])
def test_clean_mesh_refuses_bad_settings_before_any_work(field, value, match):
    v, f = _sphere()
    with pytest.raises(ToolkitError, match=match):
        clean_mesh(v, f, CleanupConfig(**{field: value}))


def test_remeshed_face_estimate():
    v, f = _sphere(3)  # area ~ 4 pi, diagonal 2 sqrt(3)
    n = remeshed_faces(v, f, 0.05)
    edge = 0.05 * 2 * math.sqrt(3)
    assert n == pytest.approx(4 * math.pi / (math.sqrt(3) / 4 * edge**2), rel=0.05)


@pytest.mark.parametrize("field, value, match", [
    ("steps", 10**9, r"fit: steps: expected a count in \[0, 100000\]"),
    ("pool", 10**12, r"fit: pool"),
    ("batch", 0, r"fit: batch"),
    ("extract_res", 100_000, r"fit: extract_res"),
    ("seed", -1, r"fit: seed"),
    ("lr", math.nan, r"fit: lr: .* got nan"),
    ("w_eikonal", -1.0, r"fit: w_eikonal"),
    ("grid_kind", "hex", r"fit: grid_kind"),
])
def test_fit_refuses_bad_settings_before_any_work(field, value, match):
    pts = torch.rand(64, 3)
    with pytest.raises(ToolkitError, match=match):
        fit_sdf_to_targets(pts, pts.norm(dim=-1) - 0.5, FitConfig(**{field: value}))


def test_fit_pool_over_the_memory_budget(monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "0.5")
    pts = torch.rand(64, 3)
    with pytest.raises(ToolkitError, match=r"a sample pool of 40000000 points would allocate .* lower pool"):
        fit_sdf_to_targets(pts, pts.norm(dim=-1) - 0.5, FitConfig(pool=40_000_000))


@pytest.mark.parametrize("field, value, match", [
    ("n_points", 10**12, r"init_gaussians: n_points: .* \[16, 10000000\]"),
    ("eye_points", 10**12, r"init_gaussians: eye_points"),
    ("min_eye_points", -1, r"init_gaussians: min_eye_points"),
    ("opacity_face", math.nan, r"init_gaussians: opacity_face: expected an opacity in \(0, 1\), got nan"),
    ("shell_tolerance", math.inf, r"init_gaussians: expected eye_radius_ratio and shell_tolerance"),
])
def test_init_gaussians_refuses_bad_counts(field, value, match):
    v, f = _sphere(2)
    with pytest.raises(ToolkitError, match=match):
        init_gaussians(v, f, torch.zeros(68, 3), config=InitConfig(**{field: value}))


@pytest.mark.parametrize("views, size, match", [(10**8, 64, r"views: .* \[1, 256\]"), (4, 10**5, r"size: .* \[8, 4096\]"),
                                                (math.nan, 64, r"views: .* got nan")])
def test_contact_sheet_sizes_are_bounded(views, size, match):
    with pytest.raises(ToolkitError, match=match):
        check_sheet(views, size)


@pytest.mark.parametrize("scale", [1e-30, 1.0, 1e30])
def test_inspect_and_sample_are_scale_free(scale):
    v, f = _sphere(2, scale)
    s = inspect_mesh(v, f)
    assert s["degenerate_faces"] == 0 and s["area"] == pytest.approx(4 * math.pi * scale**2, rel=0.05)
    p, n = sample_surface(v, f, 100)
    assert torch.allclose(n.norm(dim=-1), torch.ones(100, dtype=torch.float64))
    assert float(p.norm(dim=-1).max()) <= scale * 1.0001
