"""The geometry package's public functions given what a user's own arrays look like (float64 from numpy and
trimesh, integer or out-of-range faces, too few points, bad normals, degenerate settings): float64 is converted,
the rest is one ToolkitError naming the argument, never an error from inside torch, scipy or open3d."""

from __future__ import annotations

import pytest
import torch
import trimesh

from geometry.dmtet import marching_tets
from geometry.fit import FitConfig, fit_mesh, fit_points
from geometry.sdf import SDFNet, SDFNetConfig, SphereInit, pretrain_sphere
from geometry.surface_distance import check_points, estimate_normals, point_cloud_signed_distance
from geometry.tets import tet_grid
from toolkit.errors import ToolkitError

CFG = FitConfig(steps=1, pretrain_steps=1, pool=2000, extract_res=8)


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(1)
    return torch.from_numpy(m.vertices), torch.from_numpy(m.faces)


def test_float64_points_are_converted_not_refused(sphere):
    v, _ = sphere
    assert v.dtype == torch.float64
    out = check_points(v, "mesh vertices")
    assert out.dtype == torch.float32 and torch.equal(out, v.float())
    v32 = v.float()
    assert check_points(v32, "mesh vertices") is v32  # float32 passes through untouched


@pytest.mark.parametrize("bad, message", [
    ("numpy", r"mesh vertices must be a floating-point torch tensor \[N, 3\] .*got a TrackedArray"),
    ("int", r"mesh vertices must be a floating-point torch tensor .*got a torch.int64 tensor"),
    ("faces+10", r"fit_mesh: face indices must be in \[0, 42\), got \[10, 51\]"),
    ("float faces", r"fit_mesh: faces must be integer vertex indices, got torch.float32"),
])
def test_fit_mesh_refuses_what_it_cannot_fit(sphere, bad, message):
    v, f = sphere
    m = trimesh.creation.icosphere(1)
    args = {"numpy": (m.vertices, f), "int": (v.long(), f), "faces+10": (v, f + 10), "float faces": (v, f.float())}
    with pytest.raises(ToolkitError, match=message):
        fit_mesh(*args[bad], CFG)


@pytest.mark.parametrize("bad", ["shape", "nan", "zero"])
def test_fit_points_refuses_bad_normals(sphere, bad):
    p = sphere[0].float()
    n = p / p.norm(dim=-1, keepdim=True)
    normals = {"shape": n[:4], "nan": n * float("nan"), "zero": n * 0}[bad]
    with pytest.raises(ToolkitError, match=r"^fit: normals must be"):
        fit_points(p, normals, CFG)


def test_one_zero_normal_among_others_is_taken(sphere):
    """trimesh gives unreferenced vertices zero normals: harmless, a query's side is its neighbours' mean."""
    from geometry.surface_distance import check_normals

    p = sphere[0].float()
    n = p / p.norm(dim=-1, keepdim=True)
    n[0] = 0
    assert check_normals(n, p) is n


def test_cloud_distance_with_fewer_points_than_neighbours(sphere):
    """Five points and k = 8: every query reads the five (cKDTree would answer the missing three with index 5)."""
    p = sphere[0].float()[:5]
    n = p / p.norm(dim=-1, keepdim=True)
    d = point_cloud_signed_distance(p, n, torch.zeros(1, 3))
    assert torch.isfinite(d).all() and float(d[0]) < 0
    with pytest.raises(ToolkitError, match="k must be >= 1"):
        point_cloud_signed_distance(p, n, torch.zeros(1, 3), k=0)


@pytest.mark.parametrize("k", [0, 2, 5000])
def test_normal_estimation_neighbour_count_is_bounded(sphere, k):
    """k = 0 used to crash the whole process inside open3d."""
    with pytest.raises(ToolkitError, match=r"estimate_normals: k must be in \[3, 1000\]"):
        estimate_normals(sphere[0].float(), k=k)


@pytest.mark.parametrize("field, value, message", [
    ("n_freqs", -1, r"SDFNetConfig.n_freqs: expected >= 0, got -1"),
    ("feature_dim", -1, r"SDFNetConfig.feature_dim: expected >= 0, got -1"),
    ("softplus_beta", 0.0, r"softplus_beta: expected a finite value > 0"),
    ("softplus_beta", float("nan"), r"softplus_beta: expected a finite value > 0"),
])
def test_sdf_network_config_ranges(field, value, message):
    with pytest.raises(ToolkitError, match=message):
        SDFNet(SDFNetConfig(**{field: value}))


def test_sdf_network_names_points_of_the_wrong_shape():
    with pytest.raises(ToolkitError, match=r"SDFNet: points expected \[N, 3\], got \[5, 2\]"):
        SDFNet(SDFNetConfig(hidden=8))(torch.zeros(5, 2))


@pytest.mark.parametrize("init, message", [
    (SphereInit((float("nan"), 0.0, 0.0), 0.5), "finite centre"),
    (SphereInit(radius=float("inf")), "finite centre and a radius > 0"),
    (SphereInit(steps=0), "steps >= 1 and batch >= 1"),
    (SphereInit(batch=0), "steps >= 1 and batch >= 1"),
])
def test_sphere_pretraining_refuses_what_would_return_nan(init, message):
    with pytest.raises(ToolkitError, match=message):
        pretrain_sphere(SDFNet(SDFNetConfig(hidden=8)), init)


@pytest.mark.parametrize("name", ["verts", "features"])
def test_marching_tets_refuses_non_finite_positions_and_features(name):
    verts, tets = tet_grid("kuhn", 4)
    sdf = verts.norm(dim=-1) - 0.5
    feats = torch.zeros(verts.shape[0], 2)
    args = {"verts": verts, "features": feats}
    args[name] = args[name] * float("nan")
    with pytest.raises(ToolkitError, match=rf"marching_tets: {name} contain NaN/inf"):
        marching_tets(args["verts"], tets, sdf, args["features"])


def test_marching_tets_names_a_non_finite_sdf_before_the_features():
    """The finiteness flags are read together, yet a NaN SDF is still named first: before a features tensor
    of the wrong shape or with NaN/inf values."""
    verts, tets = tet_grid("kuhn", 4)
    sdf = verts.norm(dim=-1) - 0.5
    sdf[0] = float("nan")
    for feats in (torch.zeros(3, 2), torch.full((verts.shape[0], 2), float("inf"))):
        with pytest.raises(ToolkitError, match=r"marching_tets: sdf has 1 NaN/inf value\(s\) of 125"):
            marching_tets(verts, tets, sdf, feats)


def test_marching_tets_names_tensors_on_another_device():
    """The finiteness flags are stacked on one device: a tensor elsewhere is named, not a torch RuntimeError (the
    meta device stands in for a GPU)."""
    verts, tets = tet_grid("kuhn", 4)
    sdf = verts.norm(dim=-1) - 0.5
    with pytest.raises(ToolkitError, match=r"^marching_tets: sdf is on meta and verts on cpu; expected one device$"):
        marching_tets(verts, tets, sdf.to("meta"))
    with pytest.raises(ToolkitError, match=r"^marching_tets: features is on meta"):
        marching_tets(verts, tets, sdf, torch.zeros(verts.shape[0], 2, device="meta"))
