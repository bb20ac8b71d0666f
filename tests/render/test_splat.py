"""render.splat against an independent dense reference, hand-computed projections and gradcheck."""

from __future__ import annotations

import math

import pytest
import torch

from render.projection import project_gaussians
from render.splat import rasterize, render_scene
from tests.render import dense_reference as ref
from toolkit.errors import ToolkitError


def _agree(a: torch.Tensor, b: torch.Tensor, tol=1e-5, frac=0.999, max_diff=1e-2):
    diff = (a - b).abs().amax(-1)
    ok = (diff <= tol).float().mean().item()
    assert ok >= frac, f"only {ok:.5f} of pixels agree to {tol} (max diff {diff.max().item():.3g})"
    assert diff.max().item() <= max_diff


# ---------------------------------------------------------------------------------------------- projection
def test_projection_matches_hand_computed_values():
    means = torch.tensor([[0.1, -0.2, 2.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    scales = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    K = torch.tensor([[[100.0, 0, 32], [0, 120.0, 24], [0, 0, 1]]], dtype=torch.float64)
    V = torch.eye(4, dtype=torch.float64)[None]
    p = project_gaussians(means, quats, scales, V, K, 64, 48)
    # u = fx x / z + cx, v = fy y / z + cy
    assert torch.allclose(p.means2d[0, 0], torch.tensor([37.0, 12.0], dtype=torch.float64))
    # J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] = [[50, 0, -2.5], [0, 60, 6]], Sigma = diag(s^2)
    xx = 50**2 * 0.01 + 2.5**2 * 0.09 + 0.3
    xy = -2.5 * 6 * 0.09
    yy = 60**2 * 0.04 + 6**2 * 0.09 + 0.3
    det = xx * yy - xy * xy
    expect = torch.tensor([yy / det, -xy / det, xx / det], dtype=torch.float64)
    assert torch.allclose(p.conics[0, 0], expect, rtol=1e-12)
    assert p.radii[0, 0].tolist() == [math.ceil(3.33 * math.sqrt(xx)), math.ceil(3.33 * math.sqrt(yy))]
    assert p.depths[0, 0].item() == 2.0


def test_projection_tangent_clamp_and_culling():
    # Mean at x/z = 5, far right of a 64-px image (fx = 100, cx = 32): J is evaluated at the clamped tangent
    # lim = (W - cx)/fx + 0.3 * (W / 2) / fx = 0.32 + 0.096 = 0.416, but means2d uses the true position.
    means = torch.tensor([[10.0, 0.0, 2.0], [0, 0, -1.0], [0, 0, 0.01], [0, 0, 0.0100001], [0, 0, 2e10]],
                         dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 5, dtype=torch.float64)
    scales = torch.full((5, 3), 5.0, dtype=torch.float64)
    K = torch.tensor([[[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]], dtype=torch.float64)
    p = project_gaussians(means, quats, scales, torch.eye(4, dtype=torch.float64)[None], K, 64, 48)
    lim = (64 - 32) / 100 + 0.3 * 32 / 100
    j0, j2 = 100 / 2.0, -100 * lim / 2.0
    xx = (j0**2 + j2**2) * 25.0 + 0.3
    assert abs(p.cov2d[0, 0, 0].item() - xx) < 1e-9
    assert p.means2d[0, 0, 0].item() == pytest.approx(100 * 5 + 32)
    assert p.radii[0, 0].tolist() != [0, 0]  # a huge footprint still overlaps the image
    assert p.radii[0, 1].tolist() == [0, 0]  # behind the camera
    assert p.radii[0, 2].tolist() == [0, 0]  # on the near plane (z <= near is culled)
    assert p.radii[0, 3].tolist() != [0, 0]
    assert p.radii[0, 4].tolist() == [0, 0]  # beyond the far plane


# ---------------------------------------------------------------------------------------------- forward
@pytest.mark.parametrize("seed,n,d,w,h", [(0, 80, 3, 48, 40), (1, 150, 5, 37, 29), (2, 40, 1, 64, 16)])
def test_forward_matches_dense_reference(seed, n, d, w, h):
    means, quats, scales, opac, feats = ref.random_cloud(n, d, seed=seed)
    V, K = ref.camera(w, h)
    bg = torch.rand(1, d)
    img, alpha, meta = rasterize(means, quats, scales, opac, feats, V, K, w, h, backgrounds=bg)
    rimg, ralpha = ref.render(means, quats, scales, opac, feats, V, K, w, h, backgrounds=bg)
    assert img.shape == (1, h, w, d) and alpha.shape == (1, h, w, 1)
    _agree(img, rimg)
    _agree(alpha, ralpha)
    c = meta["counters"]
    assert c["visible"] > 0 and c["intersections"] <= c["candidate_intersections"]
    assert meta["radii"].shape == (1, n, 2) and meta["radii"].dtype == torch.int32
    assert meta["means2d"].shape == (1, n, 2) and meta["depths"].shape == (1, n)
    assert meta["conics"].shape == (1, n, 3)


def test_forward_opaque_scene_terminates_early_and_matches():
    means, quats, scales, opac, feats = ref.random_cloud(300, 3, seed=3, opacity=(0.9, 0.999),
                                                         log_scale=(-2.3, -1.5))
    V, K = ref.camera(40, 32)
    img, alpha, meta = rasterize(means, quats, scales, opac, feats, V, K, 40, 32, chunk=8)
    rimg, ralpha = ref.render(means, quats, scales, opac, feats, V, K, 40, 32)
    _agree(img, rimg)
    _agree(alpha, ralpha)
    assert meta["counters"]["pixels_terminated"] > 100
    assert meta["counters"]["tiles_terminated"] > 0


def test_multi_camera_and_per_camera_features():
    means, quats, scales, opac, _ = ref.random_cloud(60, 2, seed=4)
    V1, K1 = ref.camera(32, 24)
    V2, K2 = ref.camera(32, 24, yaw=0.2)
    V, K = torch.cat([V1, V2]), torch.cat([K1, K2])
    feats = torch.rand(2, 60, 2)
    img, alpha, _ = rasterize(means, quats, scales, opac, feats, V, K, 32, 24, backgrounds=torch.ones(2))
    rimg, ralpha = ref.render(means, quats, scales, opac, feats, V, K, 32, 24, backgrounds=torch.ones(2, 2))
    _agree(img, rimg)
    _agree(alpha, ralpha)


@pytest.mark.parametrize("kw", [dict(tile_size=16), dict(tile_size=5, chunk=3), dict(chunk=2, max_elements=1024),
                                dict(tile_size=1, chunk=64), dict(chunk=32)])
def test_knobs_do_not_change_the_result(kw):
    means, quats, scales, opac, feats = ref.random_cloud(120, 3, seed=5, dtype=torch.float64)
    V, K = ref.camera(36, 28, dtype=torch.float64)
    feats.requires_grad_(True)
    means.requires_grad_(True)
    a, aa, _ = rasterize(means, quats, scales, opac, feats, V, K, 36, 28)
    b, bb, _ = rasterize(means, quats, scales, opac, feats, V, K, 36, 28, **kw)
    assert torch.allclose(a, b, atol=1e-12) and torch.allclose(aa, bb, atol=1e-12)
    ga = torch.autograd.grad((a * a).sum() + aa.sum(), (means, feats))
    gb = torch.autograd.grad((b * b).sum() + bb.sum(), (means, feats))
    for x, y in zip(ga, gb):
        assert torch.allclose(x, y, atol=1e-10)


def test_auto_chunk_takes_fewer_rounds_on_small_images():
    """The default chunk grows on images with few tiles (fewer rounds, same pixels); big images keep 32."""
    from render._raster import MIN_CHUNK, auto_chunk

    means, quats, scales, opac, feats = ref.random_cloud(400, 3, seed=7)
    V, K = ref.camera(32, 32)
    auto, _, meta_auto = rasterize(means, quats, scales, opac, feats, V, K, 32, 32)
    fixed, _, meta_fixed = rasterize(means, quats, scales, opac, feats, V, K, 32, 32, chunk=MIN_CHUNK)
    assert meta_auto["counters"]["rounds"] < meta_fixed["counters"]["rounds"]
    assert torch.allclose(auto, fixed, atol=1e-6)
    assert auto_chunk(16, 64) == 256 and auto_chunk(1024, 64) == MIN_CHUNK and auto_chunk(0, 64) >= MIN_CHUNK


def test_return_depth_is_weighted_camera_depth():
    means, quats, scales, opac, feats = ref.random_cloud(50, 3, seed=6, dtype=torch.float64)
    V, K = ref.camera(30, 20, dtype=torch.float64)
    _, _, meta = rasterize(means, quats, scales, opac, feats, V, K, 30, 20, return_depth=True)
    z = (means @ V[0, :3, :3].T + V[0, :3, 3])[:, 2:]
    rdepth, _ = ref.render(means, quats, scales, opac, z, V, K, 30, 20)
    assert meta["depth"].shape == (1, 20, 30, 1)
    assert torch.allclose(meta["depth"], rdepth, atol=1e-9)


def test_sh_colors_degree_0_and_1():
    from render.sh import _C0, _C1

    means, quats, scales, opac, _ = ref.random_cloud(40, 3, seed=7, dtype=torch.float64)
    V, K = ref.camera(24, 20, dtype=torch.float64)
    sh = torch.randn(40, 4, 3, dtype=torch.float64) * 0.3
    img, _, _ = rasterize(means, quats, scales, opac, sh, V, K, 24, 20, sh_degree=1)
    center = -V[0, :3, :3].T @ V[0, :3, 3]
    d = means - center
    x, y, z = (d / d.norm(dim=-1, keepdim=True)).unbind(-1)
    col = (_C0 * sh[:, 0] - _C1 * y[:, None] * sh[:, 1] + _C1 * z[:, None] * sh[:, 2]
           - _C1 * x[:, None] * sh[:, 3] + 0.5).clamp_min(0)
    rimg, _ = ref.render(means, quats, scales, opac, col, V, K, 24, 20)
    assert torch.allclose(img, rimg, atol=1e-9)
    img0, _, _ = rasterize(means, quats, scales, opac, sh, V, K, 24, 20, sh_degree=0)
    rimg0, _ = ref.render(means, quats, scales, opac, (_C0 * sh[:, 0] + 0.5).clamp_min(0), V, K, 24, 20)
    assert torch.allclose(img0, rimg0, atol=1e-9)


@pytest.mark.parametrize("degree", [2, 3])
def test_sh_basis_is_orthonormal_on_the_sphere(degree):
    """Each of the (degree + 1)^2 basis functions (a one-hot coefficient) integrates against every other to
    delta_ij over the unit sphere: wrong constants or a wrong polynomial in degrees 2-3 break this."""
    from render.sh import eval_sh, num_sh_bases

    n = 200_000  # a Fibonacci lattice: near-uniform points, each of area 4 pi / n
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    r = (1 - z * z).sqrt()
    dirs = torch.stack([r * phi.cos(), r * phi.sin(), z], -1)
    k = num_sh_bases(degree)
    basis = eval_sh(degree, torch.eye(k, dtype=torch.float64)[None].expand(n, k, k), dirs)  # [n, k]
    gram = basis.T @ basis * (4 * math.pi / n)
    assert torch.allclose(gram, torch.eye(k, dtype=torch.float64), atol=1e-4), (gram - torch.eye(k)).abs().max()
    # And one value by hand: Y_2^0 at the pole is sqrt(5 / (4 pi)) (3 cos^2 - 1) / 2 = 0.6308.
    pole = eval_sh(2, torch.eye(9, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert pole[6].item() == pytest.approx(math.sqrt(5 / (4 * math.pi)), rel=1e-12)


# ---------------------------------------------------------------------------------------------- gradients
def _loss_weights(shape_img, shape_alpha, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape_img, generator=g, dtype=dtype), torch.randn(shape_alpha, generator=g, dtype=dtype)


@pytest.mark.parametrize("seed,opacity", [(0, (0.2, 0.9)), (1, (0.9, 0.99)), (2, (0.95, 0.9999))])
def test_gradients_match_autograd_through_reference(seed, opacity):
    dt = torch.float64
    means, quats, scales, opac, feats = ref.random_cloud(70, 4, seed=seed, dtype=dt, opacity=opacity,
                                                         log_scale=(-2.6, -1.8))
    V, K = ref.camera(28, 22, dtype=dt)
    bg = torch.rand(1, 4, dtype=dt)
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats, bg)]
    img, alpha, meta = rasterize(*leaves[:5], V, K, 28, 22, backgrounds=leaves[5], chunk=8)
    wi, wa = _loss_weights(img.shape, alpha.shape, dt)
    mine = torch.autograd.grad((img * wi).sum() + (alpha * wa).sum(), leaves)
    rleaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats, bg)]
    rimg, ralpha = ref.render(*rleaves[:5], V, K, 28, 22, backgrounds=rleaves[5])
    assert torch.allclose(img, rimg, atol=1e-10)
    theirs = torch.autograd.grad((rimg * wi).sum() + (ralpha * wa).sum(), rleaves)
    for name, a, b in zip(["means", "quats", "scales", "opacities", "features", "backgrounds"], mine, theirs):
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-8), f"{name}: max diff {(a - b).abs().max().item():.3g}"
    if opacity[0] >= 0.9:
        assert meta["counters"]["pixels_terminated"] > 0


def test_camera_batch_gradients_and_depth_match_reference_and_single_camera_calls():
    """Cameras are swept together: per-camera features, backgrounds and depth must still follow their own
    camera, gradients included, and equal one call per camera."""
    dt = torch.float64
    means, quats, scales, opac, _ = ref.random_cloud(50, 3, seed=11, dtype=dt, log_scale=(-2.6, -1.8))
    cams = [ref.camera(26, 18, yaw=y, dtype=dt) for y in (0.0, 0.25, -0.15)]
    V, K = torch.cat([c[0] for c in cams]), torch.cat([c[1] for c in cams])
    g = torch.Generator().manual_seed(3)
    feats, bg = torch.rand(3, 50, 3, generator=g, dtype=dt), torch.rand(3, 3, generator=g, dtype=dt)
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats, bg)]
    img, alpha, meta = rasterize(*leaves[:5], V, K, 26, 18, backgrounds=leaves[5], chunk=4, return_depth=True)
    wi, wa = _loss_weights(img.shape, alpha.shape, dt, seed=1)
    loss = (img * wi).sum() + (alpha * wa).sum() + 0.1 * meta["depth"].sum()
    mine = torch.autograd.grad(loss, leaves)
    rleaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats, bg)]
    rimg, ralpha = ref.render(*rleaves[:5], V, K, 26, 18, backgrounds=rleaves[5])
    assert torch.allclose(img, rimg, atol=1e-10) and torch.allclose(alpha, ralpha, atol=1e-10)
    rloss = (rimg * wi).sum() + (ralpha * wa).sum()
    for c in range(3):  # depth: the reference composites each camera's z as a feature
        z = (rleaves[0] @ V[c, :3, :3].T + V[c, :3, 3])[:, 2:3]
        rd, _ = ref.render(*rleaves[:4], z, V[c:c + 1], K[c:c + 1], 26, 18)
        assert torch.allclose(meta["depth"][c], rd[0], atol=1e-10)
        rloss = rloss + 0.1 * rd.sum()
    theirs = torch.autograd.grad(rloss, rleaves)
    for name, a, b in zip(["means", "quats", "scales", "opacities", "features", "backgrounds"], mine, theirs):
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-8), f"{name}: max diff {(a - b).abs().max().item():.3g}"
    single = [rasterize(means, quats, scales, opac, feats[c], V[c:c + 1], K[c:c + 1], 26, 18,
                        backgrounds=bg[c:c + 1], chunk=4) for c in range(3)]
    # (equal up to summation order: the rounds' chunk lengths differ once tiles leave the sweep)
    assert torch.allclose(img.detach(), torch.cat([s[0] for s in single]), atol=1e-12)
    assert meta["counters"]["visible"] == sum(s[2]["counters"]["visible"] for s in single)
    assert meta["counters"]["rounds"] <= sum(s[2]["counters"]["rounds"] for s in single)


def test_per_camera_gaussian_sets_match_one_call_per_camera():
    """means [C, N, 3] etc.: camera c renders set c (a batch of posed heads in one call), gradients included."""
    dt = torch.float64
    clouds = [ref.random_cloud(40, 3, seed=s, dtype=dt) for s in (21, 22)]
    means, quats, scales, opac, feats = (torch.stack(t) for t in zip(*clouds))
    cams = [ref.camera(24, 20, yaw=y, dtype=dt) for y in (0.1, -0.2)]
    V, K = torch.cat([c[0] for c in cams]), torch.cat([c[1] for c in cams])
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
    img, alpha, meta = rasterize(*leaves, V, K, 24, 20, backgrounds=torch.ones(3, dtype=dt))
    assert meta["means2d"].shape == (2, 40, 2)
    wi, wa = _loss_weights(img.shape, alpha.shape, dt, seed=2)
    mine = torch.autograd.grad((img * wi).sum() + (alpha * wa).sum(), leaves)
    for c in range(2):
        one = [t[c].clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
        rimg, ralpha = ref.render(*one, V[c:c + 1], K[c:c + 1], 24, 20, backgrounds=torch.ones(1, 3, dtype=dt))
        assert torch.allclose(img[c], rimg[0], atol=1e-10) and torch.allclose(alpha[c], ralpha[0], atol=1e-10)
        theirs = torch.autograd.grad((rimg[0] * wi[c]).sum() + (ralpha[0] * wa[c]).sum(), one)
        for a, b in zip(mine, theirs):
            assert torch.allclose(a[c], b, rtol=1e-6, atol=1e-8)
    with pytest.raises(ToolkitError, match="means"):
        rasterize(means[:1], quats[:1], scales[:1], opac[:1], feats[:1], V, K, 24, 20)
    with pytest.raises(ToolkitError, match="features"):
        rasterize(means, quats, scales, opac, feats[0], V, K, 24, 20)
    with pytest.raises(ToolkitError, match="sh_degree"):
        rasterize(means, quats, scales, opac, feats[:, :, None], V, K, 24, 20, sh_degree=0)


def test_gradcheck_float64_tiny_scene():
    dt = torch.float64
    means, quats, scales, opac, feats = ref.random_cloud(5, 2, seed=11, dtype=dt, log_scale=(-2.0, -1.6))
    V, K = ref.camera(10, 8, dtype=dt)
    bg = torch.rand(1, 2, dtype=dt)

    wi, wa = _loss_weights((1, 8, 10, 2), (1, 8, 10, 1), dt, seed=3)

    def f(m, q, s, o, c, b):
        img, alpha, _ = rasterize(m, q, s, o, c, V, K, 10, 8, backgrounds=b, chunk=2, tile_size=4)
        # Random projections of the image and alpha: one backward each instead of one per pixel.
        return torch.stack([(img * wi).sum(), (alpha * wa).sum(), img[0, 3, 4, 1]])

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats, bg))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_float32_gradients_close_to_float64():
    means, quats, scales, opac, feats = ref.random_cloud(100, 3, seed=12, dtype=torch.float64)
    V, K = ref.camera(32, 32, dtype=torch.float64)
    outs = []
    for dt in (torch.float32, torch.float64):
        leaves = [t.to(dt).requires_grad_(True) for t in (means, quats, scales, opac, feats)]
        img, alpha, _ = rasterize(*leaves, V.to(dt), K.to(dt), 32, 32)
        outs.append(torch.autograd.grad(img.sum() + alpha.sum(), leaves))
    for a, b in zip(*outs):
        scale = b.abs().max().item() + 1e-12
        assert (a.double() - b).abs().max().item() <= 2e-3 * scale


# ---------------------------------------------------------------------------------------------- API
def test_render_scene_matches_rasterize(scene_factory):
    from toolkit.cameras import Camera, intrinsics_from_fov, look_at

    scene = scene_factory(200, d=4)
    cams = [Camera(intrinsics_from_fov(60, 32, 24), look_at(torch.tensor([0.3 * i, 0.0, -4.0]), torch.zeros(3)),
                   32, 24) for i in range(2)]
    img, alpha, meta = render_scene(scene, cams)
    V = torch.stack([c.viewmat for c in cams])
    K = torch.stack([c.K for c in cams])
    img2, alpha2, _ = rasterize(scene.means, scene.unit_quats, scene.scales, scene.opacities, scene.features, V, K,
                                32, 24)
    assert torch.equal(img, img2) and torch.equal(alpha, alpha2)
    assert img.shape == (2, 24, 32, 4) and meta["counters"]["visible"] > 0
    sh_scene = scene_factory(50, d=3, sh_degree=2)
    img_sh, _, _ = render_scene(sh_scene, cams[0])
    img_f, _, _ = render_scene(sh_scene, cams[0], use_sh=False)
    assert img_sh.shape == img_f.shape == (1, 24, 32, 3) and not torch.equal(img_sh, img_f)
    with pytest.raises(ToolkitError, match="one image size"):
        render_scene(scene, [cams[0], cams[1].resized(16, 12)])


def test_bad_inputs_raise_toolkit_error():
    means, quats, scales, opac, feats = ref.random_cloud(10, 3)
    V, K = ref.camera(8, 8)
    with pytest.raises(ToolkitError, match="quats"):
        rasterize(means, quats[:, :3], scales, opac, feats, V, K, 8, 8)
    with pytest.raises(ToolkitError, match="Ks"):
        rasterize(means, quats, scales, opac, feats, V, K[0], 8, 8)
    with pytest.raises(ToolkitError, match="width"):
        rasterize(means, quats, scales, opac, feats, V, K, 0, 8)
    for name, idx, val in [("means", 0, float("nan")), ("scales", 2, float("inf")), ("features", 4, float("nan"))]:
        args = [t.clone() for t in (means, quats, scales, opac, feats)]
        args[idx][3, 0] = val
        with pytest.raises(ToolkitError, match=name):
            rasterize(*args, V, K, 8, 8)
    bad_bg = torch.full((1, 3), float("nan"))
    with pytest.raises(ToolkitError, match="backgrounds"):
        rasterize(means, quats, scales, opac, feats, V, K, 8, 8, backgrounds=bad_bg)
    # switched off: no error raised (the caller takes responsibility)
    rasterize(means, quats, scales, opac, feats, V, K, 8, 8, backgrounds=bad_bg, check_finite=False)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(monkeypatch):
    monkeypatch.setenv("DITGAZE_SPLAT", "torch")  # the torch path on both devices (gsplat: test_gsplat_backend.py)
    means, quats, scales, opac, feats = ref.random_cloud(300, 8, seed=13)
    V, K = ref.camera(64, 48)
    cpu = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
    gpu = [t.cuda().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
    a, aa, _ = rasterize(*cpu, V, K, 64, 48)
    b, bb, _ = rasterize(*gpu, V.cuda(), K.cuda(), 64, 48)
    _agree(a, b.cpu())
    ga = torch.autograd.grad(a.sum() + aa.sum(), cpu)
    gb = torch.autograd.grad(b.sum() + bb.sum(), gpu)
    for x, y in zip(ga, gb):
        assert torch.allclose(x, y.cpu(), rtol=1e-3, atol=1e-4)
    # Cameras left on the CPU are moved to the Gaussians' device, the finiteness check included.
    c, _, _ = rasterize(*gpu, V, K, 64, 48)
    assert c.is_cuda and torch.equal(b, c)


def test_binning_in_candidate_groups_is_identical(monkeypatch):
    import render._tiles as tiles

    means, quats, scales, opac, feats = ref.random_cloud(90, 3, seed=14)
    V, K = ref.camera(40, 30)
    a, aa, ma = rasterize(means, quats, scales, opac, feats, V, K, 40, 30)
    monkeypatch.setattr(tiles, "_CANDIDATE_BUDGET", 7)  # many groups, some Gaussians alone in theirs
    b, bb, mb = rasterize(means, quats, scales, opac, feats, V, K, 40, 30)
    assert torch.equal(a, b) and torch.equal(aa, bb)
    assert ma["counters"] == mb["counters"]


@pytest.mark.parametrize("alpha_min", [0.5 / 255, 4 / 255])
def test_alpha_threshold_knob_matches_reference(alpha_min):
    means, quats, scales, opac, feats = ref.random_cloud(80, 3, seed=15)
    V, K = ref.camera(40, 30)
    img, alpha, _ = rasterize(means, quats, scales, opac, feats, V, K, 40, 30, alpha_min=alpha_min, t_min=1e-3)
    rimg, ralpha = ref.render(means, quats, scales, opac, feats, V, K, 40, 30, alpha_min=alpha_min, t_min=1e-3)
    _agree(img, rimg)
    _agree(alpha, ralpha)


def test_camera_batch_benchmark_row_compares_equal_renders():
    from benchmarks.splat import camera_batch_row

    row = camera_batch_row(2, 16, 300, "cpu", repeats=1)
    assert row["cameras"] == 2 and row["one_call_s"] > 0 and row["per_camera_calls_s"] > 0
    assert row["max_abs_diff"] < 1e-5
