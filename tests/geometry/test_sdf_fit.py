"""SDF network, sphere pre-training, differentiable extraction and the three fitting entry points."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from geometry.fit import FitConfig, fit_mesh, fit_points, fit_sdf_to_targets, fit_silhouettes
from geometry.mesh_stats import compare_meshes
from geometry.sdf import SDFNet, SDFNetConfig, SphereInit, extract_mesh, pretrain_sphere
from geometry.silhouettes import Views, mask_signed_distance, visual_hull_sdf
from toolkit.cameras import orbit_rig
from toolkit.errors import ToolkitError

SMALL = SDFNetConfig(hidden=32, n_freqs=3, feature_dim=8)


def _tiny(**kw) -> FitConfig:
    base = dict(steps=80, batch=512, pool=10_000, extract_res=32, pretrain_steps=40, lr=3e-3, eikonal_batch=128, net=SMALL)
    base.update(kw)
    return FitConfig(**base)


def _ellipsoid(sub=3):
    m = trimesh.creation.icosphere(sub)
    m.vertices = m.vertices * np.array([0.075, 0.10, 0.09]) + np.array([0.0, 0.01, 0.0])
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.long)


def test_network_shapes_bounds_and_checkpoint(tmp_path):
    net = SDFNet(SDFNetConfig(grid_res=16, box_min=(-2, -1, -1), box_max=(0, 1, 1)))
    assert net.in_dim == 27 and len(net.layers) == 5 and net.layers[3].in_features == 256 + 27
    x = torch.randn(100, 3) * 5  # far outside the box too
    with torch.no_grad():
        net.head.weight.mul_(1e4)  # saturate the tanh
        sdf, off, feat = net(x)
    assert sdf.shape == (100,) and off.shape == (100, 3) and feat.shape == (100, 128)
    assert float(off.abs().max()) <= 1.0 / 16 + 1e-6  # half-size 1 -> bound 1 / grid_res
    net.save(tmp_path / "n.safetensors", {"note": "t"})
    net2 = SDFNet.load(tmp_path / "n.safetensors")
    assert net2.config == net.config
    torch.testing.assert_close(net2(x)[0], net(x)[0])
    from toolkit.io import save_checkpoint

    save_checkpoint(tmp_path / "other.safetensors", {"w": torch.zeros(2)}, {"kind": "something"})
    with pytest.raises(ToolkitError, match="not an SDF network"):
        SDFNet.load(tmp_path / "other.safetensors")
    with pytest.raises(ToolkitError, match="box_min"):
        SDFNetConfig(box_min=(1, 1, 1), box_max=(0, 2, 2)).validate()


def test_pretrain_sphere_and_extract_differentiable():
    net = SDFNet(SDFNetConfig(hidden=32, n_freqs=3, feature_dim=4, grid_res=20))
    err = pretrain_sphere(net, SphereInit((0.1, 0.0, -0.1), 0.5, steps=200, batch=512, lr=3e-3))
    assert err < 0.03
    v, f, feat = extract_mesh(net, 20, with_features=True)
    assert feat.shape == (v.shape[0], 4)
    m = trimesh.Trimesh(v.numpy(), f.numpy(), process=False)
    assert m.is_watertight and m.volume > 0
    r = np.linalg.norm(m.vertices - [0.1, 0, -0.1], axis=1)
    assert abs(r.mean() - 0.5) < 0.03
    vd, fd, _ = extract_mesh(net, 20, differentiable=True)
    assert torch.equal(fd, f) and torch.allclose(vd.detach(), v, atol=1e-5)
    vd.square().sum().backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads) and any(g.abs().sum() > 0 for g in grads)


def test_fit_mesh_and_points():
    v, f = _ellipsoid()
    res = fit_mesh(v, f, _tiny())
    cmp = compare_meshes(v, f, res.verts, res.faces, n_samples=5000)
    assert cmp["chamfer_rel_diag"] < 0.01, cmp
    assert res.skipped_steps == 0 and res.history and np.isfinite(res.history[-1]["loss"])
    m = trimesh.Trimesh(res.verts.numpy(), res.faces.numpy(), process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    from geometry.mesh_stats import sample_surface

    pts, nrm = sample_surface(v, f, 4000)
    for normals in (nrm.float(), None):  # given outward normals, then estimated by open3d
        r2 = fit_points(pts.float(), normals, _tiny(steps=60))
        assert compare_meshes(v, f, r2.verts, r2.faces, n_samples=3000)["chamfer_rel_diag"] < 0.015


def test_fit_errors_and_nan_guard(monkeypatch):
    v, f = _ellipsoid(2)
    bad = v.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ToolkitError, match="NaN"):
        fit_mesh(bad, f, _tiny())
    with pytest.raises(ToolkitError, match="zero extent"):
        fit_points(torch.zeros(10, 3), torch.ones(10, 3), _tiny())
    pts = torch.rand(100, 3)
    with pytest.raises(ToolkitError, match="finite"):
        fit_sdf_to_targets(pts, torch.full((100,), float("nan")), _tiny())
    # A network that starts producing NaN: steps are skipped, then a clear error (no silent NaN mesh).
    orig = SDFNet.sdf

    def nan_sdf(self, x):
        return orig(self, x) * float("nan")

    monkeypatch.setattr(SDFNet, "sdf", nan_sdf)
    with pytest.raises(ToolkitError, match="non-finite steps"):
        fit_sdf_to_targets(pts, (pts - 0.5).norm(dim=-1) - 0.3, _tiny(max_bad_steps=3, pretrain_steps=0))


def _raycast_masks(v, f, cams):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(v.numpy())
    mesh.triangle.indices = o3d.core.Tensor(f.numpy().astype(np.int32))
    scene.add_triangles(mesh)
    out = []
    for c in cams:
        jj, ii = np.meshgrid(np.arange(c.width) + 0.5, np.arange(c.height) + 0.5)
        d = np.stack([jj, ii, np.ones_like(jj)], -1).reshape(-1, 3) @ np.linalg.inv(c.K.numpy()).T
        R, t = c.viewmat[:3, :3].numpy(), c.viewmat[:3, 3].numpy()
        rays = np.concatenate([np.broadcast_to(-R.T @ t, d.shape), d @ R], 1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        out.append(torch.from_numpy(np.isfinite(hit).reshape(c.height, c.width)))
    return torch.stack(out)


def test_visual_hull_sdf_and_silhouette_fit():
    v, f = _ellipsoid()
    cams = orbit_rig(5, 3, radius=0.6, yaw_range_deg=80, pitch_range_deg=40, fov_y_deg=30, width=64, height=64,
                     target=(0, 0.01, 0))
    views = Views(_raycast_masks(v, f, cams), torch.stack([c.K for c in cams]), torch.stack([c.viewmat for c in cams]))
    # Hull SDF: negative at the centre, positive well outside, and roughly metric near the surface.
    q = torch.tensor([[0.0, 0.01, 0.0], [0.0, 0.01, -0.2], [0.12, 0.01, 0.0]])
    d = visual_hull_sdf(q, views)
    assert d[0] < -0.05 and d[1] > 0.05 and d[2] == pytest.approx(0.045, abs=0.01)
    hold = [2, 7, 12]
    train = views.subset([i for i in range(len(views)) if i not in hold])
    lmk = v[torch.tensor([0, 5, 9, 20])]  # surface points standing in for landmarks
    res = fit_silhouettes(train, _tiny(steps=100, extract_res=40), landmarks=lmk)
    cmp = compare_meshes(v, f, res.verts, res.faces, n_samples=4000)
    assert cmp["chamfer_rel_diag"] < 0.02, cmp
    from geometry.silhouettes import silhouette_iou
    from tests.gl import require_gl

    require_gl()  # only a missing GL skips: a NaN or empty fitted mesh fails below
    ious = silhouette_iou(res.verts, res.faces, views.subset(hold))
    assert min(ious) > 0.9, ious  # 64 px images: a 1 px boundary error costs ~5 %


def test_mask_signed_distance():
    m = np.zeros((9, 9), bool)
    m[3:6, 3:6] = True
    sd = mask_signed_distance(m)
    assert sd[4, 4] < 0 and sd[0, 0] > 0 and sd[3, 4] == pytest.approx(-0.5) and sd[2, 4] == pytest.approx(0.5)
    with pytest.raises(ToolkitError, match="empty"):
        mask_signed_distance(np.zeros((4, 4), bool))
    with pytest.raises(ToolkitError, match="Views"):
        Views(torch.zeros(2, 4, 4), torch.eye(3)[None], torch.eye(4)[None].expand(2, 4, 4))


def test_network_extreme_inputs_finite_grads():
    net = SDFNet(SDFNetConfig(hidden=32, feature_dim=4, box_min=(-0.1,) * 3, box_max=(0.1,) * 3))
    x = torch.tensor([[1e6, -1e6, 3e5], [0.0, 0.0, 0.0], [1e-30, 0, 0], [0.1, 0.1, 0.1]], requires_grad=True)
    sdf, off, feat = net(x)
    (sdf.sum() + off.sum() + feat.sum()).backward()
    assert torch.isfinite(sdf).all() and torch.isfinite(off).all() and torch.isfinite(feat).all()
    assert torch.isfinite(x.grad).all() and all(torch.isfinite(p.grad).all() for p in net.parameters())


def test_laplacian_term_runs_and_is_finite():
    from geometry.fit import _laplacian_loss

    v, f = _ellipsoid(3)
    noisy = v + torch.randn_like(v) * 0.003
    assert _laplacian_loss(noisy, f) > 2 * _laplacian_loss(v, f)
    pts = (torch.rand(4000, 3) * 2 - 1) * 0.15
    target = (pts / torch.tensor([0.075, 0.10, 0.09])).norm(dim=-1).sub(1) * 0.075
    box = SDFNetConfig(hidden=32, n_freqs=3, feature_dim=8, box_min=(-0.15,) * 3, box_max=(0.15,) * 3)
    cfg = _tiny(steps=13, w_laplacian=0.1, laplacian_every=4, laplacian_res=12, pretrain_steps=40, extract_res=16, net=box)
    res = fit_sdf_to_targets(pts, target, cfg, sphere=SphereInit((0, 0, 0), 0.08))
    assert "laplacian" in res.history[-1] and all(np.isfinite(h["laplacian"]) for h in res.history if "laplacian" in h)
    assert res.skipped_steps == 0 and torch.isfinite(res.verts).all()


def test_offsets_stay_within_half_a_cell_of_a_finer_extraction_grid(monkeypatch):
    """Offsets are bounded for the network's grid_res; on a finer grid they would cross whole cells and invert
    tets, so extraction clamps them to half a cell of its own grid."""
    import geometry.sdf as sdf_mod
    from geometry.tets import tet_grid

    net = SDFNet(SDFNetConfig(hidden=16, feature_dim=2, box_min=(-1, -1, -1), box_max=(1, 1, 1), grid_res=8))
    real = net.evaluate
    monkeypatch.setattr(net, "evaluate", lambda x, chunk=65536: (lambda s, o, f: (
        s, torch.ones_like(o) * net.half_size / net.config.grid_res, f))(*real(x)))  # every offset at its bound
    seen = {}
    real_mt = sdf_mod.marching_tets
    monkeypatch.setattr(sdf_mod, "marching_tets", lambda v, t, s, f: seen.update(v=v) or real_mt(v, t, s, f))
    for res in (4, 8, 32):
        extract_mesh(net, res)
        grid_v, _ = tet_grid("kuhn", res, net.config.box_min, net.config.box_max)
        shift = float((seen["v"] - grid_v).abs().max())
        assert shift == pytest.approx(1 / max(res, 8), rel=1e-5)  # half a cell: the box is 2 wide
