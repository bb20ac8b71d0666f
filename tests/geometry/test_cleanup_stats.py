"""Mesh cleanup (pymeshlab) on broken meshes, and mesh inspection / comparison."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from geometry.cleanup import CleanupConfig, clean_mesh
from geometry.mesh_files import load_mesh, save_mesh
from geometry.mesh_stats import compare_meshes, inspect_mesh
from toolkit.errors import ToolkitError


def _sphere(sub=3, r=1.0, c=(0, 0, 0)):
    m = trimesh.creation.icosphere(sub, radius=r)
    return torch.tensor(m.vertices + np.array(c), dtype=torch.float32), torch.tensor(m.faces, dtype=torch.long)


def _broken_mesh():
    """A sphere with: duplicated vertices (unwelded seam), a duplicate face, a null face, a hole, a
    non-manifold fin, and a tiny island."""
    v, f = _sphere(3)
    f = f[3:]  # a hole (3 faces removed)
    # Unweld: duplicate the vertices used by the first 50 faces and point those faces at the copies.
    sub = f[:50]
    ids = torch.unique(sub)
    remap = torch.full((v.shape[0],), -1, dtype=torch.long)
    remap[ids] = torch.arange(ids.numel()) + v.shape[0]
    v = torch.cat([v, v[ids]])
    f = torch.cat([remap[sub], f[50:]])
    f = torch.cat([f, f[100:101], torch.tensor([[5, 5, 6]])])  # duplicate face, null face
    # A fin: a third face on an existing edge, with a new vertex off the surface.
    a, b = int(f[200, 0]), int(f[200, 1])
    v = torch.cat([v, (v[a] + v[b])[None] * 0.8])
    f = torch.cat([f, torch.tensor([[a, b, v.shape[0] - 1]])])
    # A small island (tetrahedron) away from the sphere.
    iv, i_f = _sphere(0, 0.05, (3, 0, 0))
    f = torch.cat([f, i_f + v.shape[0]])
    v = torch.cat([v, iv])
    return v, f


def test_cleanup_repairs_broken_mesh_and_reports_each_step():
    v, f = _broken_mesh()
    before = inspect_mesh(v, f)
    assert not before["watertight"] and before["components"] >= 2 and before["non_manifold_edges"] >= 1
    lines = []
    v2, f2, rep = clean_mesh(v, f, CleanupConfig(taubin_steps=5, target_faces=600), log=lines.append)
    names = [r.name for r in rep]
    assert names.index("weld_vertices") < names.index("remove_duplicate_faces")
    assert {"drop_small_components", "repair_non_manifold_edges", "close_holes", "taubin_smooth", "decimate"} <= set(names)
    by = {r.name: r for r in rep}
    assert by["weld_vertices"].vertices_after < by["weld_vertices"].vertices_before
    assert by["remove_duplicate_faces"].faces_after < by["remove_duplicate_faces"].faces_before
    assert by["drop_small_components"].faces_after < by["drop_small_components"].faces_before
    assert by["close_holes"].faces_after > by["close_holes"].faces_before
    assert by["decimate"].faces_after < by["decimate"].faces_before
    assert len(lines) == len(rep) and "->" in lines[0]
    after = inspect_mesh(v2, f2)
    assert after["watertight"] and after["components"] == 1 and after["non_manifold_edges"] == 0
    assert after["faces"] <= 620


def test_decimation_that_does_nothing_is_an_error(monkeypatch):
    import pymeshlab

    v, f = _sphere(2)
    monkeypatch.setattr(pymeshlab.MeshSet, "meshing_decimation_quadric_edge_collapse", lambda self, **kw: None)
    with pytest.raises(ToolkitError, match="did not reduce"):
        clean_mesh(v, f, CleanupConfig(taubin_steps=0, target_faces=100))
    monkeypatch.undo()
    _, f2, rep = clean_mesh(v, f, CleanupConfig(taubin_steps=0, target_faces=10_000))
    assert "skipped" in rep[-1].note and f2.shape == f.shape


@pytest.mark.parametrize("bad", ["empty", "nan", "index"])
def test_cleanup_bad_input(bad):
    v, f = _sphere(1)
    if bad == "empty":
        f = f[:0]
    elif bad == "nan":
        v[3, 1] = float("nan")
    else:
        f[0, 0] = 10_000
    match = {"empty": "the mesh is empty", "nan": "NaN/inf coordinates", "index": "face indices must be in"}[bad]
    with pytest.raises(ToolkitError, match=match):
        clean_mesh(v, f)


def test_inspect_sphere_torus_and_open_mesh():
    v, f = _sphere(2)
    s = inspect_mesh(v, f)
    assert s["watertight"] and s["genus"] == 0 and s["orientation"] == "outward" and s["euler_characteristic"] == 2
    assert s["volume"] == pytest.approx(4 / 3 * np.pi, rel=0.05) and s["boundary_edges"] == 0
    s_in = inspect_mesh(v, f[:, [0, 2, 1]])
    assert s_in["orientation"] == "inward"
    t = trimesh.creation.torus(1.0, 0.3)
    s = inspect_mesh(torch.tensor(t.vertices, dtype=torch.float32), torch.tensor(t.faces))
    assert s["genus"] == 1
    s = inspect_mesh(v, f[1:])
    assert not s["watertight"] and s["boundary_edges"] == 3 and s["genus"] is None and s["volume"] is None


def test_compare_meshes():
    va, fa = _sphere(4, 1.0)
    same = compare_meshes(va, fa, va, fa, n_samples=4000)
    assert same["chamfer"] < 1e-5 and same["normal_consistency"] > 0.999
    vb, fb = _sphere(4, 1.02)
    d = compare_meshes(va, fa, vb, fb, n_samples=4000)
    assert d["chamfer"] == pytest.approx(0.02, rel=0.1) and d["hausdorff"] == pytest.approx(0.02, rel=0.2)
    vc, fc = _sphere(4, 1.0, (0.3, 0, 0))
    assert compare_meshes(va, fa, vc, fc, n_samples=4000)["hausdorff"] > 0.25


def test_mesh_io_roundtrip_and_errors(tmp_path):
    v, f = _sphere(1)
    for ext in (".ply", ".obj"):
        p = tmp_path / f"m{ext}"
        save_mesh(p, v, f)
        v2, f2 = load_mesh(p)
        assert torch.allclose(v, v2, atol=1e-5) and torch.equal(f, f2)
    with pytest.raises(ToolkitError, match="no such"):
        load_mesh(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat garbage\n")
    with pytest.raises(ToolkitError):
        load_mesh(tmp_path / "junk.ply")
    with pytest.raises(ToolkitError, match="extension"):
        save_mesh(tmp_path / "m.xyz", v, f)
    bad = v.clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ToolkitError, match="NaN/inf"):
        save_mesh(tmp_path / "bad.ply", bad, f)
