"""Tet grids: orientation, coverage, conformity, cache, subdivision."""

from __future__ import annotations

import pytest
import torch

from geometry.tets import GRID_KINDS, grid_topology, signed_volumes, subdivide, tet_grid
from toolkit.errors import ToolkitError


def _faces(tets: torch.Tensor) -> torch.Tensor:
    """[4T, 3] sorted triangle faces of the tets."""
    f = torch.cat([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]])
    return f.sort(1).values


def _check_conforming(verts, tets, lo, hi):
    """Every triangle is shared by exactly two tets, except those on the box boundary (exactly one)."""
    f = _faces(tets)
    uniq, counts = torch.unique(f, dim=0, return_counts=True)
    assert int(counts.max()) <= 2
    single = uniq[counts == 1]
    p = verts[single]  # [S, 3, 3]: all three corners on one box face
    lo_t, hi_t = torch.as_tensor(lo).expand(3), torch.as_tensor(hi).expand(3)
    on_face = ((p - lo_t).abs() < 1e-6).all(1) | ((p - hi_t).abs() < 1e-6).all(1)
    assert bool(on_face.any(1).all()), "an interior face belongs to only one tet (non-conforming grid)"


@pytest.mark.parametrize("kind", GRID_KINDS)
@pytest.mark.parametrize("res", [1, 2, 3, 5])
def test_grid_positive_conforming_and_covers_box(kind, res, tmp_path):
    lo, hi = (-0.3, -1.0, 0.0), (0.5, 1.0, 0.25)
    v, t = tet_grid(kind, res, lo, hi, cache_dir=tmp_path, dtype=torch.float64)
    vol = signed_volumes(v.double(), t)
    assert bool((vol > 0).all())
    box = 0.8 * 2.0 * 0.25
    assert abs(float(vol.sum()) - box) < 1e-9
    assert int(t.min()) >= 0 and int(t.max()) < v.shape[0]
    assert torch.unique(t).numel() == v.shape[0]  # no unused vertices
    _check_conforming(v.double(), t, lo, hi)
    expected_t = 6 * res**3 if kind == "kuhn" else 12 * res**3
    assert t.shape[0] == expected_t
    assert float(v[:, 0].min()) == pytest.approx(lo[0]) and float(v[:, 2].max()) == pytest.approx(hi[2])


def test_cache_roundtrip_and_corrupt_rebuild(tmp_path):
    c1, t1 = grid_topology("bcc", 4, cache_dir=tmp_path)
    path = tmp_path / "bcc_4.safetensors"
    assert path.exists()
    c2, t2 = grid_topology("bcc", 4, cache_dir=tmp_path)
    assert torch.equal(c1, c2) and torch.equal(t1, t2) and t2.dtype == torch.long
    path.write_bytes(b"garbage")
    c3, t3 = grid_topology("bcc", 4, cache_dir=tmp_path)
    assert torch.equal(t1, t3)
    grid_topology("kuhn", 3, use_cache=False, cache_dir=tmp_path)
    assert not (tmp_path / "kuhn_3.safetensors").exists()


def test_unwritable_cache_only_costs_the_rebuild(tmp_path):
    """A cache folder that cannot be made (its parent is a file; as root, chmod would not stop the write)."""
    (tmp_path / "afile").write_text("")
    c1, t1 = grid_topology("kuhn", 3, cache_dir=tmp_path / "afile" / "cache")
    c2, t2 = grid_topology("kuhn", 3, use_cache=False)
    assert torch.equal(c1, c2) and torch.equal(t1, t2)


@pytest.mark.parametrize("bad", [0, -1, 2.5, 10_000, True])
def test_bad_res(bad):
    with pytest.raises(ToolkitError, match="res"):
        tet_grid("kuhn", bad, use_cache=False)


def test_bad_kind_and_box():
    with pytest.raises(ToolkitError, match="kind"):
        tet_grid("hex", 2, use_cache=False)
    with pytest.raises(ToolkitError, match="box"):
        tet_grid("kuhn", 2, 1.0, -1.0, use_cache=False)
    with pytest.raises(ToolkitError, match="box"):
        tet_grid("kuhn", 2, float("nan"), 1.0, use_cache=False)


@pytest.mark.parametrize("kind", GRID_KINDS)
def test_subdivide(kind, tmp_path):
    v, t = tet_grid(kind, 2, cache_dir=tmp_path, dtype=torch.float64)
    f = v @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64) + 0.3  # a linear field stays exact
    v2, t2, f2 = subdivide(v, t, f)
    assert t2.shape[0] == 8 * t.shape[0]
    vol = signed_volumes(v2, t2)
    assert bool((vol > 0).all())
    assert abs(float(vol.sum()) - 8.0) < 1e-9
    torch.testing.assert_close(f2, v2 @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64) + 0.3)
    assert torch.equal(v2[: v.shape[0]], v)
    # Midpoints are unique (edges shared by several tets produce one vertex).
    assert torch.unique(v2, dim=0).shape[0] == v2.shape[0]
    _check_conforming(v2, t2, -1.0, 1.0)
    # Multi-channel features, and twice in a row.
    v3, t3, f3 = subdivide(v2, t2, torch.stack([f2, -f2], 1))
    assert f3.shape == (v3.shape[0], 2) and bool((signed_volumes(v3, t3) > 0).all())


def test_subdivide_keeps_orientation_on_deformed_grid():
    """Children orientation comes from the template, so a sheared (still positive) grid stays positive."""
    v, t = tet_grid("kuhn", 2, use_cache=False, dtype=torch.float64)
    A = torch.tensor([[1.0, 0.9, 0.0], [0.0, 1.0, 0.9], [0.0, 0.0, 0.05]], dtype=torch.float64)
    v = v @ A.T
    assert bool((signed_volumes(v, t) > 0).all())
    v2, t2, _ = subdivide(v, t)
    assert bool((signed_volumes(v2, t2) > 0).all())


def test_subdivide_differentiable_and_bad_input():
    v, t = tet_grid("kuhn", 1, use_cache=False)
    v = v.clone().requires_grad_(True)
    s = torch.randn(v.shape[0], requires_grad=True)
    v2, _, s2 = subdivide(v, t, s)
    (v2.sum() + s2.square().sum()).backward()
    assert torch.isfinite(v.grad).all() and torch.isfinite(s.grad).all()
    with pytest.raises(ToolkitError, match="features"):
        subdivide(v.detach(), t, torch.zeros(3))
    with pytest.raises(ToolkitError, match="tets"):
        subdivide(v.detach(), t[:, :3])


def test_unique_inverse_matches_torch():
    from geometry.tets import unique_inverse

    g = torch.Generator().manual_seed(0)
    for n in (0, 1, 7, 5000):
        k = torch.randint(0, 50, (n,), generator=g) * 1_000_003
        u, inv = unique_inverse(k)
        u2, inv2 = torch.unique(k, return_inverse=True)
        assert torch.equal(u, u2) and torch.equal(inv, inv2)


def test_orientation_triple_product_exact_on_integers_and_matches_det():
    from geometry.tets import _orient, _triple

    g = torch.Generator().manual_seed(4)
    coords = torch.randint(-1000, 1000, (40, 3), generator=g)
    t = torch.randint(0, 40, (3000, 4), generator=g)
    vi = _triple(coords, t)  # integer path: exact int64
    vd = torch.linalg.det(torch.stack([coords[t[:, i]] - coords[t[:, 0]] for i in (1, 2, 3)], -1).double())
    assert vi.dtype == torch.long and torch.equal(vi, vd.round().long())
    o = _orient(coords, t)
    vo = _triple(coords, o)
    assert bool((vo >= 0).all()) and torch.equal(vo, vi.abs())
    assert torch.equal(o[:, :2], t[:, :2]) and torch.equal(o.sort(1).values, t.sort(1).values)
