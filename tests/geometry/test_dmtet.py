"""Marching tetrahedra: closed, outward, consistently wound meshes; gradients; every failure mode."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from geometry.dmtet import marching_tets
from geometry.tets import GRID_KINDS, subdivide, tet_grid
from toolkit.errors import ToolkitError


def _mesh(v, f):
    return trimesh.Trimesh(v.detach().double().numpy(), f.numpy(), process=False)


def _sphere_sdf(v, c=(0.1, -0.05, 0.07), r=0.55):
    return (v - torch.tensor(c, dtype=v.dtype)).norm(dim=-1) - r


def _torus_sdf(v, R=0.5, r=0.2):
    q = torch.stack([torch.sqrt(v[:, 0] ** 2 + v[:, 2] ** 2) - R, v[:, 1]], -1)
    return q.norm(dim=-1) - r


@pytest.mark.parametrize("kind", GRID_KINDS)
def test_sphere_closed_outward_consistent(kind):
    v, t = tet_grid(kind, 12, use_cache=False)
    mv, mf, feat = marching_tets(v, t, _sphere_sdf(v))
    assert feat is None and mf.dtype == torch.long
    m = _mesh(mv, mf)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0  # outward normals
    assert abs(m.volume - 4 / 3 * math.pi * 0.55**3) < 0.07 * 4 / 3 * math.pi * 0.55**3
    assert m.euler_number == 2
    # One vertex per cut edge: no duplicates, no unreferenced vertices.
    assert torch.unique(mv, dim=0).shape[0] == mv.shape[0]
    assert torch.unique(mf).numel() == mv.shape[0]
    # Normals point away from the centre everywhere.
    n = torch.tensor(np.array(m.face_normals), dtype=torch.float32)
    cdir = torch.tensor(np.array(m.triangles_center), dtype=torch.float32) - torch.tensor([0.1, -0.05, 0.07])
    assert bool(((n * cdir).sum(-1) > 0).all())


@pytest.mark.parametrize("kind", GRID_KINDS)
def test_torus_genus_one_and_subdivided(kind):
    v, t = tet_grid(kind, 10, use_cache=False)
    v, t, _ = subdivide(v, t)
    mv, mf, _ = marching_tets(v, t, _torus_sdf(v))
    m = _mesh(mv, mf)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert m.euler_number == 0  # genus 1


def test_second_order_convergence():
    errs = []
    for res in (8, 16, 32):
        v, t = tet_grid("kuhn", res, use_cache=False, dtype=torch.float64)
        mv, _, _ = marching_tets(v, t, _sphere_sdf(v))
        errs.append(float((_sphere_sdf(mv).abs()).max()))
    assert errs[1] < errs[0] / 3 and errs[2] < errs[1] / 3, errs


def test_features_interpolated_exactly_for_linear_fields():
    v, t = tet_grid("bcc", 6, use_cache=False, dtype=torch.float64)
    feats = torch.stack([v[:, 0] * 2 + 1, v[:, 1] - v[:, 2]], 1)
    mv, mf, mfeat = marching_tets(v, t, _sphere_sdf(v), feats)
    torch.testing.assert_close(mfeat, torch.stack([mv[:, 0] * 2 + 1, mv[:, 1] - mv[:, 2]], 1))


def test_gradients_match_finite_differences():
    v, t = tet_grid("kuhn", 3, use_cache=False, dtype=torch.float64)
    v = v.clone().requires_grad_(True)
    s = _sphere_sdf(v.detach()).clone().requires_grad_(True)
    f = torch.randn(v.shape[0], 2, dtype=torch.float64, requires_grad=True)

    def fn(vv, ss, ff):
        mv, _, mfeat = marching_tets(vv, t, ss, ff)
        return mv, mfeat

    assert torch.autograd.gradcheck(fn, (v, s, f), eps=1e-6, atol=1e-5)


def test_all_positive_all_negative_nan_messages():
    v, t = tet_grid("kuhn", 3, use_cache=False)
    with pytest.raises(ToolkitError, match="all positive"):
        marching_tets(v, t, torch.ones(v.shape[0]))
    with pytest.raises(ToolkitError, match="all negative"):
        marching_tets(v, t, -torch.ones(v.shape[0]))
    with pytest.raises(ToolkitError, match="all positive"):
        marching_tets(v, t, torch.zeros(v.shape[0]))  # zeros count as outside
    s = _sphere_sdf(v)
    s[3] = float("nan")
    with pytest.raises(ToolkitError, match="1 NaN"):
        marching_tets(v, t, s)
    s[3] = float("inf")
    with pytest.raises(ToolkitError, match="NaN/inf"):
        marching_tets(v, t, s)


def test_bad_shapes_and_ids():
    v, t = tet_grid("kuhn", 2, use_cache=False)
    s = _sphere_sdf(v)
    with pytest.raises(ToolkitError, match="sdf must have shape"):
        marching_tets(v, t, s[:-1])
    with pytest.raises(ToolkitError, match="verts"):
        marching_tets(v[:, :2], t, s)
    with pytest.raises(ToolkitError, match="tets"):
        marching_tets(v, t.float(), s)
    with pytest.raises(ToolkitError, match="features"):
        marching_tets(v, t, s, torch.zeros(3, 2))
    bad = t.clone()
    bad[0, 0] = v.shape[0] + 5
    with pytest.raises(ToolkitError, match="vertex ids"):
        marching_tets(v, bad, s)
    with pytest.raises(ToolkitError, match="floating point"):
        marching_tets(v, t, (s > 0).long())


def test_exact_zeros_on_many_vertices():
    """A plane through a grid layer and a sphere through lattice points: no duplicates, no zero-area faces."""
    v, t = tet_grid("kuhn", 8, use_cache=False)  # lattice spacing 0.25: z = 0 is a grid plane
    for sdf in (v[:, 2].clone(), (v.abs().max(1).values - 0.5)):  # plane; cube surface through grid points
        n_zero = int((sdf == 0).sum())
        assert n_zero >= 81
        mv, mf, _ = marching_tets(v, t, sdf)
        assert torch.isfinite(mv).all()
        assert torch.unique(mv, dim=0).shape[0] == mv.shape[0]
        area = torch.linalg.cross(mv[mf[:, 1]] - mv[mf[:, 0]], mv[mf[:, 2]] - mv[mf[:, 0]]).norm(dim=-1)
        assert float(area.min()) > 0
    m = _mesh(mv, mf)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0


def test_single_tet_every_case():
    """Each of the 14 sign patterns on one tet: right triangle count, outward winding, vertices on edges."""
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    t = torch.tensor([[0, 1, 2, 3]])
    for case in range(1, 15):
        inside = torch.tensor([(case >> i) & 1 for i in range(4)], dtype=torch.bool)
        s = torch.where(inside, -torch.rand(4, dtype=torch.float64) - 0.1, torch.rand(4, dtype=torch.float64) + 0.1)
        mv, mf, _ = marching_tets(v, t, s)
        k = int(inside.sum())
        assert mf.shape[0] == (2 if k == 2 else 1) and mv.shape[0] == (4 if k == 2 else 3)
        # Winding: normals point from the inside vertices' centroid towards the outside ones.
        d = v[~inside].mean(0) - v[inside].mean(0)
        n = torch.linalg.cross(mv[mf[:, 1]] - mv[mf[:, 0]], mv[mf[:, 2]] - mv[mf[:, 0]])
        assert bool(((n @ d) > 0).all()), case
        assert torch.isfinite(mv).all()


def test_near_degenerate_tets_after_large_offsets_finite_grads():
    g = torch.Generator().manual_seed(1)
    v0, t = tet_grid("kuhn", 6, use_cache=False)
    cell = 2 / 6
    for scale in (0.49, 3.0, 50.0):  # half a cell (DMTet's bound), then far beyond (inverted tets)
        off = (torch.rand(v0.shape, generator=g) * 2 - 1) * cell * scale
        v = (v0 + off).requires_grad_(True)
        s = (_sphere_sdf(v0) + torch.randn(v0.shape[0], generator=g) * 1e-7).requires_grad_(True)
        s.data[::7] = 0.0  # exact zeros too
        s.data[1::11] = 1e-30  # and denormal-small values
        feats = torch.randn(v0.shape[0], 4, generator=g, requires_grad=True)
        mv, mf, mfeat = marching_tets(v, t, s, feats)
        loss = mv.square().sum() + mfeat.sum() + (mv[mf].mean(1)).sum()
        loss.backward()
        for x in (mv, mfeat, v.grad, s.grad, feats.grad):
            assert torch.isfinite(x).all()
    # Collapse a whole region of vertices onto one point (zero-volume tets).
    v = v0.clone()
    v[v0.norm(dim=-1) < 0.8] = 0.0
    v.requires_grad_(True)
    s = _sphere_sdf(v0).requires_grad_(True)
    mv, _, _ = marching_tets(v, t, s)
    mv.sum().backward()
    assert torch.isfinite(mv).all() and torch.isfinite(v.grad).all() and torch.isfinite(s.grad).all()


def test_surface_leaving_box_is_open_not_broken():
    v, t = tet_grid("kuhn", 6, use_cache=False)
    mv, mf, _ = marching_tets(v, t, _sphere_sdf(v, c=(0.9, 0, 0), r=0.5))
    m = _mesh(mv, mf)
    assert not m.is_watertight and m.is_winding_consistent
    assert np.isfinite(m.vertices).all()


def test_int32_tets_and_float64():
    v, t = tet_grid("bcc", 5, use_cache=False, dtype=torch.float64)
    a = marching_tets(v, t, _sphere_sdf(v))
    b = marching_tets(v, t.int(), _sphere_sdf(v))
    assert torch.equal(a[1], b[1]) and a[0].dtype == torch.float64



# ------------------------------------------------------------------ optimized path vs a plain reference
def _canonical(tri):
    """A triangle as its vertex ids rotated so the smallest comes first (winding kept)."""
    r = tri.index(min(tri))
    return tuple(tri[r:] + tri[:r])


def _reference_marching_tets(verts, tets, sdf, features=None):
    """Plain per-tet DMTet (python loops, a dict for edge dedup): the spec the vectorized path must meet.

    Returns verts [M, 3] float64 ordered by edge key min * V + max, the sorted list of canonical faces and
    features [M, C] float64 (or None).
    """
    from geometry.dmtet import _TRI_COUNT, _TRI_TABLE
    from geometry.tets import TET_EDGES

    V = verts.shape[0]
    inside = (sdf < 0).tolist()
    tris = []
    for tet in tets.long().tolist():
        case = sum(int(inside[v]) << i for i, v in enumerate(tet))
        for k in range(int(_TRI_COUNT[case])):
            tri = []
            for le in _TRI_TABLE[case, k].tolist():
                a, b = tet[int(TET_EDGES[le, 0])], tet[int(TET_EDGES[le, 1])]
                assert inside[a] != inside[b]
                tri.append((min(a, b), max(a, b)))
            tris.append(tri)
    edges = sorted({e for tri in tris for e in tri}, key=lambda e: e[0] * V + e[1])
    vid = {e: i for i, e in enumerate(edges)}
    out_v, out_feat = [], []
    for a, b in edges:
        sa, sb = float(sdf[a]), float(sdf[b])
        t = min(max(-sa / (sb - sa), 1e-4), 1 - 1e-4)
        out_v.append((verts[a].double() * (1 - t) + verts[b].double() * t).tolist())
        if features is not None:
            out_feat.append((features[a].double() * (1 - t) + features[b].double() * t).tolist())
    faces = sorted(_canonical([vid[e] for e in tri]) for tri in tris)
    feats = torch.tensor(out_feat, dtype=torch.float64) if features is not None else None
    return torch.tensor(out_v, dtype=torch.float64).reshape(-1, 3), faces, feats


def _random_sdf(v, g, mode):
    if mode == "noise":  # many tiny disconnected components: every case pattern occurs
        return torch.randn(v.shape[0], generator=g, dtype=v.dtype)
    if mode == "zeros":  # values in {-1, 0, 1}: a third of the vertices exactly zero
        return torch.randint(-1, 2, (v.shape[0],), generator=g).to(v.dtype)
    if mode == "plane":  # a zero set through a whole grid layer
        return v[:, 2] - v[0, 2] - (v[:, 2].max() - v[0, 2]) / 2
    return (v - torch.rand(3, generator=g, dtype=v.dtype) * 0.4).norm(dim=-1) - 0.5 + torch.randn(
        v.shape[0], generator=g, dtype=v.dtype) * 0.05


@pytest.mark.parametrize("kind", GRID_KINDS)
@pytest.mark.parametrize("mode", ["noise", "zeros", "plane", "bumpy"])
def test_vectorized_path_equals_plain_reference(kind, mode):
    g = torch.Generator().manual_seed(GRID_KINDS.index(kind) * 10 + len(mode))
    for res in (1, 2, 5):
        v, t = tet_grid(kind, res, use_cache=False, dtype=torch.float64)
        v = v + (torch.rand(v.shape, generator=g, dtype=torch.float64) - 0.5) * 0.3 / res  # deformed grid
        s = _random_sdf(v, g, mode)
        f = torch.randn(v.shape[0], 2, generator=g, dtype=torch.float64)
        if not bool((s < 0).any()) or bool((s < 0).all()):
            continue
        rv, rf, rfeat = _reference_marching_tets(v, t, s, f)
        assert rf  # mixed signs on a connected grid: some tet is crossed
        mv, mf, mfeat = marching_tets(v, t, s, f)
        torch.testing.assert_close(mv, rv, rtol=0, atol=1e-12)
        torch.testing.assert_close(mfeat, rfeat, rtol=0, atol=1e-12)
        assert sorted(_canonical(tri) for tri in mf.tolist()) == rf, (kind, mode, res)


def test_crossing_scan_across_chunk_boundaries(monkeypatch):
    """Tiny chunks (and odd tails) give the same crossed tets as one plain nonzero over all tets."""
    import geometry.dmtet as dm

    g = torch.Generator().manual_seed(3)
    v, t = tet_grid("bcc", 4, use_cache=False)
    s = torch.randn(v.shape[0], generator=g)
    s[::5] = 0.0
    inside = s < 0
    flags = inside[t]
    want = ((flags.any(1)) & ~(flags.all(1))).nonzero().squeeze(1)
    full = marching_tets(v, t, s)
    for chunk in (1, 3, 8, 13, 1000, 1 << 18):
        monkeypatch.setattr(dm, "_CHUNK", chunk)
        ids, corner = dm._crossing_tets(inside, t, v.shape[0])
        assert torch.equal(ids, want), chunk
        assert torch.equal(corner.bool(), flags[want]), chunk
        for x, y in zip(marching_tets(v, t, s)[:2], full[:2]):
            assert torch.equal(x, y), chunk


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 64, 1001])
def test_nonzero_sparse_matches_nonzero(n):
    from geometry.dmtet import _nonzero_sparse

    g = torch.Generator().manual_seed(n)
    for p in (0.0, 0.01, 0.5, 1.0):
        m = torch.rand(n, generator=g) < p
        assert torch.equal(_nonzero_sparse(m), m.nonzero().squeeze(1)), (n, p)


def test_vectorized_path_gradients_finite_with_exact_zeros():
    g = torch.Generator().manual_seed(5)
    v0, t = tet_grid("kuhn", 5, use_cache=False)
    v = v0.clone().requires_grad_(True)
    s = torch.randint(-1, 2, (v0.shape[0],), generator=g).float().requires_grad_(True)
    f = torch.randn(v0.shape[0], 3, generator=g, requires_grad=True)
    mv, mf, mfeat = marching_tets(v, t, s, f)
    (mv.square().sum() + mfeat.sum()).backward()
    for x in (mv, mfeat, v.grad, s.grad, f.grad):
        assert torch.isfinite(x).all()
    assert float(s.grad.abs().sum()) > 0 and float(v.grad.abs().sum()) > 0
    assert torch.unique(mv, dim=0).shape[0] == mv.shape[0]  # zeros nudged: no duplicate vertices


def test_benchmark_runs_with_and_without_scikit_image(monkeypatch, tmp_path, capsys):
    """benchmarks/dmtet.py on tiny grids: Kuhn decays at second order, MC rows or a clear skip line, a PNG."""
    import benchmarks.dmtet as bench

    monkeypatch.setattr(bench, "OUT_DIR", tmp_path)
    monkeypatch.setattr(bench, "have_skimage", lambda: False)
    assert bench.main(["--res", "8", "16", "--repeats", "1", "--shapes", "sphere"]) == 0
    out = capsys.readouterr().out
    assert "skipped: scikit-image not installed" in out and "mc-skimage" not in out
    assert (tmp_path / "dmtet_sphere.png").stat().st_size > 0
    kuhn16 = [ln for ln in out.splitlines() if ln.startswith("| sphere |") and "|        kuhn |  16 |" in ln]
    assert len(kuhn16) == 1 and 1.7 < float(kuhn16[0].split("|")[-2]) < 2.5  # the order column
    monkeypatch.undo()
    pytest.importorskip("skimage.measure")
    monkeypatch.setattr(bench, "OUT_DIR", tmp_path)
    r = bench.run_mc(bench.sphere, 16, 1)
    assert r["samples"] == 17**3 and r["faces"] > 0 and r["face_err_mean"] < 0.1 * 2 / 16
    occ = bench.run_mc(bench.sphere, 16, 1, "trimesh")
    assert occ["faces"] > 0 and occ["face_err_mean"] > r["face_err_mean"]  # binary occupancy: worse


def test_benchmark_rows_name_the_lattice_meshed_and_orders_follow_any_res_ratio(monkeypatch, tmp_path, capsys):
    """An odd --res: the subdivided grid meshes res - 1, and its row says so; orders use the actual ratio."""
    import benchmarks.dmtet as bench

    monkeypatch.setattr(bench, "OUT_DIR", tmp_path)
    monkeypatch.setattr(bench, "have_skimage", lambda: False)
    assert bench.main(["--res", "6", "11", "--repeats", "1", "--shapes", "sphere"]) == 0
    rows = [[c.strip() for c in ln.split("|")[1:-1]] for ln in capsys.readouterr().out.splitlines()
            if ln.startswith("| sphere |")]
    res = {(r[1], r[2]) for r in rows}
    assert {("kuhn", "6"), ("kuhn", "11"), ("kuhn+subdiv", "6"), ("kuhn+subdiv", "10")} <= res
    kuhn11 = next(r for r in rows if r[1] == "kuhn" and r[2] == "11")
    assert 1.85 < float(kuhn11[-1]) < 2.3  # second order over an 11/6 step (log2 of the error ratio reads 1.75)


@pytest.mark.parametrize("argv, msg", [(["--repeats", "0"], "--repeats: expected an integer >= 1, got '0'"),
                                       (["--threads", "-1"], "--threads: expected an integer >= 0, got '-1'"),
                                       (["--res", "8", "3"], "--res: expected an integer >= 4, got '3'")])
def test_benchmark_bad_counts_are_one_line_errors(capsys, argv, msg):
    """The benchmarks' shared flag types (benchmarks.common.count): exit 2, one line naming the flag."""
    import benchmarks.dmtet as bench
    from toolkit.errors import run_cli

    assert run_cli(bench.main, argv) == 2
    err = capsys.readouterr().err
    assert err == f"error: {msg}\n"
