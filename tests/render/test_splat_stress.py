"""Degenerate and extreme inputs: outputs and gradients stay finite and the documented behaviour holds."""

from __future__ import annotations

import math

import pytest
import torch

from render.splat import rasterize
from tests.render import dense_reference as ref


def _run(means, quats, scales, opac, feats, V, K, w, h, bg=None, **kw):
    """Render, backprop a random projection of image and alpha, assert everything finite; return outputs."""
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]
    if bg is not None:
        bg = bg.clone().requires_grad_(True)
        leaves.append(bg)
    img, alpha, meta = rasterize(*leaves[:5], V, K, w, h, backgrounds=bg, **kw)
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    assert ((alpha >= 0) & (alpha <= 1)).all()
    g = torch.Generator().manual_seed(0)
    loss = (img * torch.randn(img.shape, generator=g, dtype=img.dtype)).sum() + alpha.sum()
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    for name, gr, leaf in zip(["means", "quats", "scales", "opacities", "features", "backgrounds"], grads, leaves):
        gr = torch.zeros_like(leaf) if gr is None else gr
        assert gr.shape == leaf.shape and torch.isfinite(gr).all(), f"non-finite gradient for {name}"
    return img, alpha, meta, grads


@pytest.mark.parametrize("log_scale", [-16.1, -7.0, 0.0, 3.0, 6.9])  # scales 1e-7 .. 1e3
def test_uniform_extreme_scales(log_scale):
    means, quats, _, opac, feats = ref.random_cloud(30, 3, seed=1)
    scales = torch.full((30, 3), float(torch.exp(torch.tensor(log_scale))))
    V, K = ref.camera(24, 20)
    img, alpha, meta, _ = _run(means, quats, scales, opac, feats, V, K, 24, 20, bg=torch.rand(1, 3))
    if log_scale >= 3.0:  # huge blobs cover the whole image
        assert (alpha > 0.5).all()


@pytest.mark.parametrize("huge", [1e10, 1e20, 1e30])
def test_absurdly_large_gaussians_are_culled_with_finite_gradients(huge):
    """Footprints whose covariance minors would overflow float32 are culled; their 0 * inf must not reach
    the gradients of the others or their own."""
    means, quats, scales, opac, feats = ref.random_cloud(30, 3, seed=4)
    V, K = ref.camera(24, 20)
    scales = scales.clone()
    scales[[3, 17]] = huge
    img, _, _, _ = _run(means, quats, scales, opac, feats, V, K, 24, 20)
    keep = torch.ones(30, dtype=torch.bool)
    keep[[3, 17]] = False
    without, _, _ = rasterize(means[keep], quats[keep], scales[keep], opac[keep], feats[keep], V, K, 24, 20)
    assert torch.allclose(img, without, atol=1e-6)


def test_mixed_needles_discs_and_blobs_match_reference():
    means, quats, scales, opac, feats = ref.random_cloud(40, 3, seed=2)
    scales[0:10] = torch.tensor([1e-7, 1e-7, 0.5])  # needles
    scales[10:20] = torch.tensor([0.3, 0.3, 1e-7])  # flat discs
    scales[20:23] = torch.tensor([1e3, 1e3, 1e3])  # blobs far larger than the view
    scales[23:26] = torch.tensor([1e-7, 1e-7, 1e-7])  # points
    V, K = ref.camera(32, 24)
    img, alpha, meta, _ = _run(means, quats, scales, opac, feats, V, K, 32, 24)
    rimg, ralpha = ref.render(means, quats, scales, opac, feats, V, K, 32, 24)
    assert ((img - rimg).abs().amax(-1) <= 1e-4).float().mean() >= 0.99


def test_tiny_and_zero_quaternions_normalize():
    means, quats, scales, opac, feats = ref.random_cloud(20, 3, seed=3)
    q = quats / quats.norm(dim=-1, keepdim=True)
    tiny = q * 1e-12
    tiny[:3] = 0.0  # zero quaternion means identity
    _, _, _, _ = _run(means, tiny, scales, opac, feats, *ref.camera(16, 16), 16, 16)
    a, _, _ = rasterize(means[3:], tiny[3:], scales[3:], opac[3:], feats[3:], *ref.camera(16, 16), 16, 16)
    b, _, _ = rasterize(means[3:], q[3:], scales[3:], opac[3:], feats[3:], *ref.camera(16, 16), 16, 16)
    assert torch.allclose(a, b, atol=1e-5)


def test_behind_camera_on_near_plane_and_far_away():
    V, K = ref.camera(16, 16)
    tz = V[0, 2, 3].item()
    means = torch.tensor([[0.0, 0.0, -1.0 - tz], [0.0, 0.0, 0.01 - tz], [0.0, 0.0, 1e8], [0.0, 0.0, 2.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]] * 4)
    scales = torch.tensor([[0.3] * 3, [0.3] * 3, [1e6] * 3, [0.1] * 3])
    opac = torch.full((4,), 0.8)
    feats = torch.rand(4, 3)
    img, alpha, meta, grads = _run(means, quats, scales, opac, feats, V, K, 16, 16)
    radii = meta["radii"][0]
    assert radii[0].tolist() == [0, 0] and radii[1].tolist() == [0, 0]
    assert radii[2].tolist() != [0, 0] and radii[3].tolist() != [0, 0]
    assert (grads[0][:2] == 0).all() and (grads[4][:2] == 0).all()  # culled Gaussians get no gradient


def test_empty_scene_and_everything_culled_render_background():
    V, K = ref.camera(12, 10)
    bg = torch.tensor([[0.2, 0.5, 0.7]])
    e = torch.zeros(0, 3)
    img, alpha, meta, grads = _run(e, torch.zeros(0, 4), e, torch.zeros(0), e, V, K, 12, 10, bg=bg)
    assert torch.allclose(img, bg.view(1, 1, 1, 3).expand_as(img)) and (alpha == 0).all()
    assert meta["counters"]["visible"] == 0 and meta["counters"]["intersections"] == 0
    bgl = bg.clone().requires_grad_(True)
    img, _, _ = rasterize(e, torch.zeros(0, 4), e, torch.zeros(0), e, V, K, 12, 10, backgrounds=bgl)
    img.sum().backward()
    assert torch.allclose(bgl.grad, torch.full((1, 3), 120.0))  # d(sum of image)/d(bg) = H * W per channel
    means, quats, scales, opac, feats = ref.random_cloud(10, 3, seed=4)
    means[:, 2] = -5.0  # all behind the camera
    img, alpha, meta, _ = _run(means, quats, scales, opac, feats, V, K, 12, 10, bg=bg)
    assert meta["counters"]["visible"] == 0 and torch.allclose(img, bg.view(1, 1, 1, 3).expand_as(img))


def test_opacity_zero_and_almost_one():
    means, quats, scales, _, feats = ref.random_cloud(30, 3, seed=5, log_scale=(-2.0, -1.5))
    V, K = ref.camera(20, 16)
    zero = torch.zeros(30)
    img, alpha, meta, _ = _run(means, quats, scales, zero, feats, V, K, 20, 16)
    assert (img == 0).all() and (alpha == 0).all() and meta["counters"]["intersections"] == 0
    one = torch.full((30,), 1 - 1e-7)
    img, alpha, meta, _ = _run(means, quats, scales, one, feats, V, K, 20, 16)
    rimg, ralpha = ref.render(means, quats, scales, one, feats, V, K, 20, 16)
    assert ((img - rimg).abs().amax(-1) <= 1e-5).float().mean() >= 0.99
    assert alpha.max() <= 1 and meta["counters"]["pixels_terminated"] > 0


@pytest.mark.parametrize("d", [1, 128])
def test_feature_widths(d):
    means, quats, scales, opac, feats = ref.random_cloud(25, d, seed=6)
    img, _, _, _ = _run(means, quats, scales, opac, feats, *ref.camera(16, 12), 16, 12, bg=torch.rand(1, d))
    assert img.shape == (1, 12, 16, d)


def test_float64_end_to_end():
    means, quats, scales, opac, feats = ref.random_cloud(25, 3, seed=7, dtype=torch.float64)
    img, alpha, _, grads = _run(means, quats, scales, opac, feats, *ref.camera(16, 12, dtype=torch.float64), 16, 12)
    assert img.dtype == alpha.dtype == torch.float64 and all(g.dtype == torch.float64 for g in grads if g is not None)


def test_one_by_one_image_matches_reference():
    means, quats, scales, opac, feats = ref.random_cloud(30, 3, seed=8, log_scale=(-1.5, -1.0))
    V, K = ref.camera(1, 1, f=2.0)
    img, alpha, _, _ = _run(means, quats, scales, opac, feats, V, K, 1, 1)
    rimg, ralpha = ref.render(means, quats, scales, opac, feats, V, K, 1, 1)
    assert img.shape == (1, 1, 1, 3) and torch.allclose(img, rimg, atol=1e-5)


def test_large_image_with_three_gaussians():
    means = torch.tensor([[0.0, 0.0, 3.0], [0.3, -0.2, 2.5], [-0.5, 0.4, 4.0]])
    quats = torch.randn(3, 4)
    scales = torch.tensor([[0.05, 0.02, 0.03], [0.2, 0.2, 0.01], [1e-4, 1e-4, 1e-4]])
    opac = torch.tensor([0.9, 0.5, 0.99])
    V, K = ref.camera(1024, 1024)
    img, alpha, meta, _ = _run(means, quats, scales, opac, torch.rand(3, 3), V, K, 1024, 1024)
    assert img.shape == (1, 1024, 1024, 3)
    assert meta["counters"]["tiles_skipped"] > 0.5 * (1024 // 8) ** 2  # empty tiles cost nothing
    assert (alpha > 0).any()


def test_long_diagonal_needles_take_the_negative_sigma_path(monkeypatch):
    import render.splat as splat

    seen = []
    apply = splat.RasterizeTiles.apply
    monkeypatch.setattr(splat.RasterizeTiles, "apply", lambda *a: seen.append(a[9]) or apply(*a))
    dt = torch.float64
    means = torch.tensor([[0.0, 0.0, 3.0], [0.2, -0.1, 3.5], [-0.3, 0.2, 2.5]], dtype=dt)
    c, s = torch.cos(torch.tensor(0.3927)), torch.sin(torch.tensor(0.3927))  # 45 degrees about z
    quats = torch.tensor([[c, 0, 0, s], [c, 0, 0, -s], [1.0, 0, 0, 0]], dtype=dt)
    scales = torch.tensor([[3.0, 1e-7, 1e-7], [2.0, 1e-6, 1e-7], [0.1, 0.1, 0.1]], dtype=dt)
    opac = torch.tensor([0.7, 0.9, 0.5], dtype=dt)
    feats = torch.rand(3, 3, dtype=dt)
    V, K = ref.camera(64, 48, dtype=dt)
    rimg, _ = ref.render(means, quats, scales, opac, feats, V, K, 64, 48)
    img64, _, _, _ = _run(means, quats, scales, opac, feats, V, K, 64, 48)
    assert torch.allclose(img64, rimg, atol=1e-10)
    # float32: such needles are ill-conditioned (b^2 ~ a c), so agreement is only to ~1e-4 on a few pixels.
    img32, _, _, _ = _run(*(t.float() for t in (means, quats, scales, opac, feats, V, K)), 64, 48)
    assert (img32.double() - rimg).abs().max() <= 1e-3
    assert seen == [True, True]  # correlation b^2 / (a c) > 0.999: the per-pixel sigma < 0 test is on


# ------------------------------------------------------------------ the shared cull rule (render.cull)
def _keep(means, quats, scales, V, K, w, h, **kw):
    from render.cull import cull_mask

    return cull_mask(means, quats, scales, V, K, w, h, **kw)


@pytest.mark.parametrize("log_scale", [-80.0, -40.0, 10.0, 20.0, 40.0, 80.0])
def test_log_scales_from_minus_80_to_80_draw_what_the_rule_keeps(log_scale):
    """e^80 = 5.5e34 is finite in float32: every log-scale renders finite, and only what the rule keeps is
    drawn; from ~20 on (footprints beyond 1e9 px, or scales above 1e18) nothing is, and the image is the
    background."""
    means, quats, _, opac, feats = ref.random_cloud(30, 3, seed=9)
    scales = torch.full((30, 3), math.exp(log_scale))
    V, K = ref.camera(24, 20)
    bg = torch.tensor([[0.3, 0.6, 0.1]])
    img, alpha, meta, _ = _run(means, quats, scales, opac, feats, V, K, 24, 20, bg=bg)
    drawn = (meta["radii"] > 0).all(-1)
    keep = _keep(means, quats, scales, V, K, 24, 20)
    assert not (drawn & ~keep).any()
    if log_scale <= 10:
        assert drawn.all()
    else:
        assert not keep.any() and torch.equal(img, bg.view(1, 1, 1, 3).expand_as(img)) and (alpha == 0).all()


def test_scene_log_scales_beyond_float32_are_culled_not_refused(scene_factory):
    """A finite log-scale of 100 activates to inf in float32: render_scene culls that Gaussian like any huge
    one (instead of refusing the scene for an inf it does not hold), and draws the rest unchanged."""
    from render.splat import render_scene
    from toolkit.cameras import Camera, intrinsics_from_fov, look_at

    scene = scene_factory(40, d=3)
    cam = Camera(intrinsics_from_fov(60, 32, 24), look_at(torch.tensor([0.0, 0, -6]), torch.zeros(3)), 32, 24)
    before, _, _ = render_scene(scene, cam)
    big = scene.select(torch.ones(40, dtype=torch.bool))
    big.log_scales = big.log_scales.clone()
    big.log_scales[[4, 11]] = 100.0
    after, _, meta = render_scene(big, cam)
    assert torch.isfinite(after).all() and (meta["radii"][0, [4, 11]] == 0).all()
    keep = torch.ones(40, dtype=torch.bool)
    keep[[4, 11]] = False
    without, _, _ = render_scene(scene.select(keep), cam)
    assert torch.allclose(after, without, atol=1e-6) and not torch.equal(after, before)


def test_non_finite_parameters_are_culled_with_zero_gradients():
    """With the input check off (check_finite=False), NaN / inf means, quats or scales, and means that
    project beyond float32, are culled; no NaN reaches the image or any gradient."""
    means, quats, scales, opac, feats = ref.random_cloud(12, 3, seed=10)
    means[0, 0], quats[1, 2], scales[2, 1], scales[3, 0] = float("nan"), float("inf"), float("nan"), float("inf")
    means[4] = torch.tensor([3e38, 3e38, 3.0])  # finite, but f x / z overflows
    V, K = ref.camera(16, 12)
    img, alpha, meta, grads = _run(means, quats, scales, opac, feats, V, K, 16, 12, check_finite=False)
    assert (meta["radii"][0, :5] == 0).all() and (meta["radii"][0, 5:] > 0).all()
    for g in grads[:4]:
        assert (g[:5] == 0).all()
    assert not _keep(means, quats, scales, V, K, 16, 12)[0, :5].any()


def test_zero_quaternion_is_the_identity_and_degenerate_ones_are_culled():
    """Zero is the identity (toolkit.rotations); a non-zero quaternion whose largest component lies outside
    [1e-15, 1e15] is culled: its squared norm leaves float32's range, so normalizing it is not reliable."""
    means, quats, scales, opac, feats = ref.random_cloud(8, 3, seed=11)
    q = quats.clone()
    q[0] = 0.0
    q[1] = quats[1] * 1e-30
    q[2] = quats[2] * 1e30
    q[3] = quats[3] / quats[3].abs().max() * 1e-14  # tiny, but normalizes exactly
    V, K = ref.camera(16, 12)
    img, _, meta, _ = _run(means, q, scales, opac, feats, V, K, 16, 12)
    assert (meta["radii"][0, [0, 3]] > 0).all() and (meta["radii"][0, [1, 2]] == 0).all()
    ident = q.clone()
    ident[0] = torch.tensor([1.0, 0, 0, 0])
    ident[3] = quats[3]
    keep = torch.tensor([True, False, False, True, True, True, True, True])
    ref_img, _, _ = rasterize(means[keep], ident[keep], scales[keep], opac[keep], feats[keep], V, K, 16, 12)
    assert torch.allclose(img, ref_img, atol=1e-6)


def test_needles_beyond_the_condition_bound_are_culled():
    """A needle whose 2D footprint's trace^2 / det exceeds MAX_CONDITION is culled; a thinner bound on its
    length keeps it (and draws it as the dense reference does)."""
    from render.cull import MAX_CONDITION, footprints

    c, s = math.cos(0.3927), math.sin(0.3927)  # 45 degrees about z: a diagonal needle on screen
    means = torch.tensor([[0.0, 0.0, 3.0], [0.1, 0.1, 3.0]])
    quats = torch.tensor([[c, 0, 0, s], [c, 0, 0, s]])
    opac, feats = torch.tensor([0.8, 0.8]), torch.ones(2, 3)
    V, K = ref.camera(64, 48)
    for length, culled in ((0.3, False), (30.0, True)):
        scales = torch.tensor([[length, 1e-7, 1e-7], [0.05, 0.05, 0.05]])
        fp = footprints(means, quats, scales, V, K, 64, 48)
        kappa = float(((fp.sxx + fp.syy) ** 2 / fp.det)[0, 0])
        assert (kappa > MAX_CONDITION) == culled
        img, alpha, meta, _ = _run(means, quats, scales, opac, feats, V, K, 64, 48)
        assert (meta["radii"][0, 0] == 0).all() == culled and (meta["radii"][0, 1] > 0).all()
        if not culled:
            rimg, _ = ref.render(means, quats, scales, opac, feats, V, K, 64, 48)
            assert (img - rimg).abs().max() <= 1e-3


def test_near_and_far_planes_cull_by_camera_depth():
    V, K = ref.camera(16, 16)
    tz = V[0, 2, 3].item()  # the camera adds tz to z
    z = torch.tensor([0.5, 0.5 + 1e-4, 3.0, 10.0 - 1e-3, 10.0, 12.0]) - tz
    means = torch.stack([torch.zeros(6), torch.zeros(6), z], -1)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 6)
    scales = torch.full((6, 3), 0.01)
    img, _, meta, _ = _run(means, quats, scales, torch.full((6,), 0.8), torch.rand(6, 3), V, K, 16, 16,
                           near_plane=0.5, far_plane=10.0)
    assert ((meta["radii"][0] > 0).all(-1)).tolist() == [False, True, True, True, False, False]
    assert _keep(means, quats, scales, V, K, 16, 16, near_plane=0.5, far_plane=10.0)[0].tolist() == \
        [False, True, True, True, False, False]
