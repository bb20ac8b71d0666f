"""The moderngl preview splatter: exactness against a dense reference and the torch splatter, stress inputs
and bad input (the frames that skip work: tests/render/test_preview_frames.py; the ``ctx`` fixture:
tests/render/conftest.py)."""

from __future__ import annotations

import math

import moderngl
import numpy as np
import pytest
import torch

from toolkit.errors import ToolkitError


# ------------------------------------------------------------------ an independent dense reference
def dense_reference(means, quats, scales, opacities, colors, viewmat, K, W, H, bg=None):
    """Every pixel x every Gaussian in float64; same conventions, no tiles, no early stop."""
    m, q, s = (np.asarray(a, np.float64) for a in (means, quats, scales))
    o, c = np.asarray(opacities, np.float64), np.asarray(colors, np.float64)
    V, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(qn > 1e-12, q / np.maximum(qn, 1e-12), [1, 0, 0, 0])
    w, x, y, z = q.T
    Rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]).transpose(2, 0, 1)
    cov = Rq @ (s[:, :, None] ** 2 * Rq.transpose(0, 2, 1))
    R, t = V[:3, :3], V[:3, 3]
    p = m @ R.T + t
    covc = R @ cov @ R.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tanx, tany = W / (2 * fx), H / (2 * fy)
    out_rgb = np.zeros((H, W, 3))
    T = np.ones((H, W))
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    order = np.argsort(p[:, 2], kind="stable")  # front to back
    for g in order:
        zc = p[g, 2]
        if zc <= 0.01 or zc >= 1e10:
            continue
        u = min(max(p[g, 0] / zc, -(cx / fx + 0.3 * tanx)), (W - cx) / fx + 0.3 * tanx) * zc
        v = min(max(p[g, 1] / zc, -(cy / fy + 0.3 * tany)), (H - cy) / fy + 0.3 * tany) * zc
        J = np.array([[fx / zc, 0, -fx * u / zc**2], [0, fy / zc, -fy * v / zc**2]])
        c2 = J @ covc[g] @ J.T + 0.3 * np.eye(2)
        det = np.linalg.det(c2)
        if det <= 0:
            continue
        conic = np.linalg.inv(c2)
        dx = fx * p[g, 0] / zc + K[0, 1] * p[g, 1] / zc + cx - jj
        dy = fy * p[g, 1] / zc + cy - ii
        sig = 0.5 * (conic[0, 0] * dx**2 + conic[1, 1] * dy**2) + conic[0, 1] * dx * dy
        a = np.minimum(0.99, o[g] * np.exp(-sig))
        a = np.where((sig >= 0) & (a >= 1 / 255), a, 0.0)
        out_rgb += (a * T)[..., None] * c[g]
        T = T * (1 - a)
    if bg is not None:
        out_rgb += T[..., None] * np.asarray(bg)
    return out_rgb.astype(np.float32), (1 - T).astype(np.float32)[..., None]


def random_gaussians(n, seed=0, spread=1.0):
    g = np.random.default_rng(seed)
    means = g.normal(size=(n, 3)) * [0.5 * spread, 0.5 * spread, 0.3] + [0, 0, 3.0]
    quats = g.normal(size=(n, 4))
    scales = np.exp(g.uniform(-4.0, -1.5, size=(n, 3)))
    opacities = g.uniform(0.05, 1.0, size=n)
    colors = g.uniform(0, 1, size=(n, 3))
    return [a.astype(np.float32) for a in (means, quats, scales, opacities, colors)]


def camera(W=64, H=48, yaw=0.0):
    c, s = math.cos(yaw), math.sin(yaw)
    V = np.eye(4, dtype=np.float32)
    V[:3, :3] = [[c, 0, -s], [0, 1, 0], [s, 0, c]]
    V[:3, 3] = -(V[:3, :3] @ np.array([0, 0, 3.0])) + [0, 0, 3.0]
    K = np.array([[60.0, 0.8, W / 2 + 1.3], [0, 62.0, H / 2 - 0.7], [0, 0, 1]], np.float32)  # a little skew
    return V, K


def _agree(img, ref, tol=1e-4, frac=0.999, worst=1e-2):
    err = np.abs(img - ref).max(-1)
    assert (err <= tol).mean() >= frac, f"only {(err <= tol).mean():.4%} of pixels within {tol}"
    assert err.max() <= worst, f"max error {err.max()}"


# ------------------------------------------------------------------ exactness
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_dense_reference(ctx, seed):
    from render.preview import PreviewSplatter

    W, H = 64, 48
    gs = random_gaussians(300, seed, spread=1.6)  # some Gaussians off-screen: the tangent clamp matters
    V, K = camera(W, H, yaw=0.2 * seed)
    bg = np.array([0.2, 0.3, 0.9], np.float32)
    s = PreviewSplatter(W, H, ctx=ctx)
    img, alpha = s.render(*gs, V, K, bg, return_alpha=True)
    ref, ref_alpha = dense_reference(*gs, V, K, W, H, bg)
    assert img.shape == (H, W, 3) and img.dtype == np.float32 and alpha.shape == (H, W, 1)
    _agree(img, ref)
    _agree(alpha, ref_alpha)
    assert alpha.max() > 0.9 and alpha.min() < 0.1  # the scene is neither empty nor full


def test_one_shot_and_torch_inputs(ctx):
    from render.preview import render_preview

    gs = random_gaussians(100, 3)
    V, K = camera()
    a = render_preview(*gs, V, K, 64, 48)
    b = render_preview(*(torch.from_numpy(x) for x in gs), torch.from_numpy(V), torch.from_numpy(K), 64, 48)
    np.testing.assert_array_equal(a, b)
    _agree(a, dense_reference(*gs, V, K, 64, 48)[0])


def test_quads_are_cut_at_the_opacity_ellipse(ctx):
    """A faint Gaussian's footprint ends where o exp(-sigma) = 1/255, well inside 3.33 sigma."""
    from render.preview import PreviewSplatter

    W = H = 96
    V, K = np.eye(4, dtype=np.float32), np.array([[100.0, 0, 48], [0, 100.0, 48], [0, 0, 1]], np.float32)
    for o in (0.02, 0.5, 0.99):
        gs = [np.array([[0, 0, 2.0]], np.float32), np.array([[1, 0, 0, 0]], np.float32),
              np.array([[0.2, 0.1, 0.1]], np.float32), np.array([o], np.float32), np.ones((1, 3), np.float32)]
        img, alpha = PreviewSplatter(W, H, ctx=ctx).render(*gs, V, K, return_alpha=True)
        ref_alpha = dense_reference(*gs, V, K, W, H)[1]
        _agree(alpha, ref_alpha, tol=1e-5, frac=0.998)
        assert (alpha > 0).sum() == pytest.approx((ref_alpha > 0).sum(), abs=4)


def _demo(n=3000, size=128):
    from toolkit.procedural import demo_camera, demo_head_scene

    return demo_head_scene(n, seed=1), demo_camera(size, size, distance=0.45)


def _two_overlapping(red_z: float, blue_z: float):
    """Two large half-transparent Gaussians over the image centre: red (id 0) and blue (id 1)."""
    means = np.array([[0, 0, red_z], [0, 0, blue_z]], np.float32)
    quats = np.tile(np.array([1, 0, 0, 0], np.float32), (2, 1))
    scales = np.full((2, 3), 0.3, np.float32)
    return [means, quats, scales, np.array([0.8, 0.8], np.float32), np.eye(3, dtype=np.float32)[[0, 2]]]


def test_equal_depths_blend_in_the_torch_splatters_order(ctx):
    """Ties in depth (clones, planar patches facing the camera): the lower id is in front in both splatters,
    whether the frame sorts everything or only the Gaussians near a changed eye."""
    import render.splat as splat
    from render.preview import PreviewSplatter

    V, K = camera()
    gs = _two_overlapping(3.0, 3.0)
    ref, _, _ = splat.rasterize(*[torch.from_numpy(a) for a in gs], torch.from_numpy(V)[None],
                                torch.from_numpy(K)[None], 64, 48)
    centre = ref[0, 24, 32].numpy()
    assert centre[0] > centre[2] + 0.3  # red, id 0, in front
    _agree(PreviewSplatter(64, 48, ctx=ctx).render(*gs, V, K), ref[0].numpy(), tol=1e-4, worst=1e-3)
    # The incremental path sorts its mid-range subset on its own: blue is dynamic and moves within the tie.
    s = PreviewSplatter(64, 48, ctx=ctx)
    dyn = np.array([False, True])
    s.draw(*gs, V, K, dynamic=dyn)
    gs[0] = gs[0].copy()
    gs[0][1, 0] = 0.01
    s.draw(*gs, V, K, dynamic=dyn)
    assert s.stats["path"] == "incremental"
    ref, _, _ = splat.rasterize(*[torch.from_numpy(a) for a in gs], torch.from_numpy(V)[None],
                                torch.from_numpy(K)[None], 64, 48)
    _agree(s.read()[..., :3], ref[0].numpy(), tol=1e-4, worst=1e-3)


def test_feature_maps_for_any_width(ctx):
    from render.preview import render_scene
    from render.preview_scene import FeatureColors
    from tests.conftest import random_scene

    for n, d in ((0, 8), (1, 8), (2, 8)):  # fewer Gaussians than colour axes
        f = np.random.default_rng(n).normal(size=(n, d)).astype(np.float32)
        cols = FeatureColors(f)(f)
        assert cols.shape == (n, 3) and np.isfinite(cols).all()
    for d in (1, 2, 3, 32):
        scene = random_scene(200, d=d, seed=d)
        cols = FeatureColors(scene.features)(scene.features)
        assert cols.shape == (200, 3) and np.isfinite(cols).all()
        if d != 3:
            assert cols.min() >= 0 and cols.max() <= 1 and cols.std(0)[:min(d, 3)].min() > 0.05
        # Fixed per scene: moving Gaussians never changes their colours.
        fmap = FeatureColors(scene.features)
        np.testing.assert_array_equal(fmap(scene.features[:50]), cols[:50])
    scene = random_scene(300, d=32)
    from toolkit.cameras import Camera, intrinsics_from_fov, look_at

    cam = Camera(intrinsics_from_fov(60, 48, 40), look_at(torch.tensor([0.0, 0, -6]), torch.zeros(3)), 48, 40)
    img = render_scene(scene, cam)
    assert img.shape == (40, 48, 3) and np.isfinite(img).all() and img.max() > 0.1


# ------------------------------------------------------------------ stress and bad input
def test_stress_degenerate_and_extreme_inputs(ctx):
    from render.preview import PreviewSplatter

    V, K = camera()
    means = np.array([[0, 0, 3], [0.1, 0, 3], [0, 0.1, 3], [0, 0, -1], [0, 0, 3.01 - 3.0], [0, 0, 1e8],
                      [0.2, 0.2, 3], [0, 0, 3.5], [5, 5, 3]], np.float32)
    n = len(means)
    scales = np.array([[1e-7] * 3, [1e3] * 3, [1e-7, 1, 1e-7], [0.1] * 3, [0.1] * 3, [1e3] * 3,
                       [1e-3, 1e3, 1e-3], [0.05] * 3, [10.0] * 3], np.float32)
    quats = np.zeros((n, 4), np.float32)
    quats[1:, 0] = 1e-12  # zero and near-zero norms: identity / normalized
    opac = np.array([1 - 1e-7, 0.5, 1.0, 0.5, 0.5, 0.5, 0.0, 1e-4, 0.7], np.float32)
    cols = np.random.default_rng(0).uniform(size=(n, 3)).astype(np.float32)
    for W, H in ((64, 48), (1, 1)):
        Kw = K.copy()
        Kw[0, 2], Kw[1, 2] = W / 2, H / 2
        img, alpha = PreviewSplatter(W, H, ctx=ctx).render(means, quats, scales, opac, cols, V, Kw, return_alpha=True)
        assert np.isfinite(img).all() and np.isfinite(alpha).all()
        assert alpha.min() >= 0 and alpha.max() <= 1
    empty = PreviewSplatter(8, 8, ctx=ctx)
    img = empty.render(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), V, K, (1, 0, 0))
    np.testing.assert_array_equal(img, np.tile(np.float32([1, 0, 0]), (8, 8, 1)))
    behind = empty.render(means[3:4], quats[3:4], scales[3:4], opac[3:4], cols[3:4], V, K)
    assert behind.max() == 0


def test_bad_input_is_a_clear_error(ctx):
    from render.preview import PreviewSplatter

    gs = random_gaussians(10)
    V, K = camera()
    s = PreviewSplatter(64, 48, ctx=ctx)
    bad = [a.copy() for a in gs]
    bad[0][3, 1] = np.nan
    with pytest.raises(ToolkitError, match="means contains NaN"):
        s.render(*bad, V, K)
    with pytest.raises(ToolkitError, match="quats must have shape"):
        s.render(gs[0], gs[1][:, :3], *gs[2:], V, K)
    with pytest.raises(ToolkitError, match="dynamic must be"):
        s.render(*gs, V, K, dynamic=np.ones(3, bool))
    with pytest.raises(ToolkitError, match="width and height"):
        PreviewSplatter(0, 10, ctx=ctx)


def test_missing_egl_names_the_library(monkeypatch):
    import ctypes.util

    from render import gl_context

    def no_egl(*a, **k):
        raise Exception("libEGL.so.1: cannot open shared object file")

    monkeypatch.setattr(moderngl, "create_context", no_egl)
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None if name == "EGL" else f"lib{name}.so")
    with pytest.raises(ToolkitError, match=r"EGL.*libEGL\.so.*apt-get install libegl1"):
        gl_context.create_context()


# ------------------------------------------------------------------ parity with the torch splatter
def _psnr(a, b):
    return 10 * math.log10(1.0 / max(float(np.mean((a.astype(np.float64) - b) ** 2)), 1e-20))


def test_parity_with_torch_splatter_random_scenes(ctx):
    import render.splat as splat
    from render.preview import PreviewSplatter

    for seed in range(3):
        gs = random_gaussians(400, 20 + seed, spread=1.5)
        V, K = camera(80, 64, yaw=0.3 * seed)
        bg = np.array([0.1, 0.5, 0.2], np.float32)
        img = PreviewSplatter(80, 64, ctx=ctx).render(*gs, V, K, bg)
        t = [torch.from_numpy(a) for a in gs]
        ref, _, _ = splat.rasterize(*t, torch.from_numpy(V)[None], torch.from_numpy(K)[None], 80, 64,
                                    backgrounds=torch.from_numpy(bg)[None])
        assert _psnr(img, ref[0].numpy()) >= 45


def test_parity_with_torch_splatter_demo_head(ctx):
    import render.splat as splat
    from render.preview import PreviewSplatter
    from toolkit.eyes import redirect_eyes

    scene, cam = _demo(4000, 128)
    live = PreviewSplatter(cam.width, cam.height, ctx=ctx)
    for gaze in [(0.0, 0.0), (0.3, -0.4)]:
        moved = redirect_eyes(scene, gaze)
        img = live.render_scene(moved, cam, background=(1.0, 1.0, 1.0))  # the second frame is incremental
        ref, _, _ = splat.render_scene(moved, [cam], backgrounds=torch.ones(1, 3))
        assert _psnr(img, ref[0].numpy()) >= 45


# ------------------------------------------------------------------ the shared cull rule (render.cull)
def _torch_render(gs, V, K, W, H, bg, **kw):
    import render.splat as splat

    img, alpha, meta = splat.rasterize(*[torch.from_numpy(a) for a in gs], torch.from_numpy(V)[None],
                                       torch.from_numpy(K)[None], W, H, backgrounds=torch.from_numpy(bg)[None], **kw)
    return img[0].numpy(), alpha[0].numpy(), meta


def _culled(gs, V, K, W, H, **kw):
    from render.cull import cull_mask

    return ~cull_mask(*(torch.from_numpy(a) for a in gs[:3]), torch.from_numpy(V)[None], torch.from_numpy(K)[None],
                      W, H, **kw)[0].numpy()


@pytest.mark.parametrize("log_scale", [-80.0, -20.0, 0.0, 10.0, 20.0, 23.0, 44.0, 80.0])
def test_extreme_log_scales_draw_what_the_torch_splatter_draws(ctx, log_scale):
    """Large finite scales (e^80 = 5.5e34) gave NaN footprints and a blank frame, and scales beyond the
    torch splatter's footprint bound (log-scale >= ~20 here) were drawn by the preview only: both now draw
    exactly what render.cull keeps, and every frame is finite."""
    from render.preview import PreviewSplatter

    W, H = 32, 24
    V, K = camera(W, H)
    gs = random_gaussians(6, seed=5)
    gs[2] = np.full((6, 3), math.exp(log_scale), np.float32)
    gs[2][0] = 0.05  # one ordinary Gaussian among them
    bg = np.array([0.2, 0.3, 0.9], np.float32)
    s = PreviewSplatter(W, H, ctx=ctx)
    img, alpha = s.render(*gs, V, K, bg, return_alpha=True)
    assert np.isfinite(img).all() and np.isfinite(alpha).all()
    ref, ref_alpha, _ = _torch_render(gs, V, K, W, H, bg)
    _agree(img, ref, tol=1e-3, frac=0.99, worst=1e-2)
    _agree(alpha, ref_alpha, tol=1e-3, frac=0.99, worst=1e-2)
    want = np.flatnonzero(~_culled(gs, V, K, W, H) & (gs[3] > 1 / 255))
    np.testing.assert_array_equal(np.sort(s.drawn), want)


def test_needles_and_near_far_planes_cull_like_the_torch_splatter(ctx):
    from render.preview import PreviewSplatter

    W, H = 48, 40
    V, K = camera(W, H)  # camera z = world z
    c, s = math.cos(0.3927), math.sin(0.3927)
    means = np.array([[0, 0, 3], [0.1, 0, 3], [0, 0.1, 0.5], [0, 0, 0.5 + 1e-4], [0, 0, 10], [0, 0, 10 - 1e-3]],
                     np.float32)
    quats = np.tile(np.array([c, 0, 0, s], np.float32), (6, 1))
    scales = np.array([[30.0, 1e-7, 1e-7], [0.3, 1e-7, 1e-7]] + [[0.05] * 3] * 4, np.float32)
    gs = [means, quats, scales, np.full(6, 0.8, np.float32), np.eye(3, dtype=np.float32)[[0, 1, 2, 0, 1, 2]]]
    bg = np.zeros(3, np.float32)
    culled = _culled(gs, V, K, W, H, near_plane=0.5, far_plane=10.0)
    assert culled.tolist() == [True, False, True, False, True, False]  # a needle beyond the bound, the planes
    sp = PreviewSplatter(W, H, ctx=ctx, near_plane=0.5, far_plane=10.0)
    img = sp.render(*gs, V, K, bg)
    ref, _, meta = _torch_render(gs, V, K, W, H, bg, near_plane=0.5, far_plane=10.0)
    _agree(img, ref, tol=1e-3, frac=0.99, worst=2e-2)
    np.testing.assert_array_equal((meta["radii"][0] > 0).all(-1).numpy(), ~culled)
    np.testing.assert_array_equal(np.sort(sp.drawn), np.flatnonzero(~culled))


def test_a_scene_of_culled_gaussians_draws_the_background(ctx):
    from render.preview import PreviewSplatter

    V, K = camera()
    gs = random_gaussians(5)
    gs[2] = np.full((5, 3), 1e30, np.float32)  # every scale far above render.cull.SCALE_MAX
    bg = np.array([0.25, 0.5, 0.75], np.float32)
    s = PreviewSplatter(64, 48, ctx=ctx)
    img, alpha = s.render(*gs, V, K, bg, return_alpha=True)
    np.testing.assert_array_equal(img, np.broadcast_to(bg, img.shape))
    assert (alpha == 0).all() and s.drawn.size == 0 and s.stats["culled"] == 5
    assert s.culled_by_test(V, K) == {"scale": 5}


def test_sizes_beyond_the_gl_limits_are_clear_errors(ctx, monkeypatch):
    from render import preview_gl
    from render.preview import PreviewSplatter

    limit = preview_gl.max_texture_size(ctx)
    with pytest.raises(ToolkitError, match=f"exceed this OpenGL's limit of {limit}"):
        PreviewSplatter(limit + 1, 8, ctx=ctx)
    s = PreviewSplatter(8, 8, ctx=ctx)
    monkeypatch.setattr(preview_gl, "max_texture_size", lambda ctx: 1)  # one row: 1024 Gaussians
    gs = random_gaussians(1025)
    with pytest.raises(ToolkitError, match="1025 Gaussians need a data texture of 2 rows"):
        s.render(*gs, *camera(8, 8))
    for near, far in ((-1.0, 10.0), (1.0, 1.0), (float("nan"), 1.0)):
        with pytest.raises(ToolkitError, match="near_plane < far_plane"):
            PreviewSplatter(8, 8, ctx=ctx, near_plane=near, far_plane=far)
