"""Property tests of the shared cull rule (``render.cull``) and of both splatters on extreme Gaussians.

Gaussians are drawn from a mix of ordinary and extreme kinds: log-scales anywhere in [-80, 80], needles and
discs (one scale ~0, the others large), means behind the camera, on the near and far planes or at +-1e38,
quaternions zero, tiny, huge or NaN, and NaN / inf anywhere (where a splatter takes them).

- The rule keeps nothing whose parameters are non-finite or out of range, nothing outside (near, far), and
  keeps every Gaussian that an independent float64 projection finds clearly projectable and not a needle.
- The torch splatter (``check_finite=False``): image, alpha and every gradient finite; its radii are
  non-zero exactly where the rule keeps a Gaussian and its box ceil(3.33 sqrt(cov2d_ii)) around means2d
  overlaps the image.
- The preview splatter: ``render.preview_footprints.drawable`` is the rule, bit for bit; a frame is finite,
  its ids are exactly what the rule keeps with opacity above 1/255, and a frame that draws none is the
  background.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from render.cull import MAX_CONDITION, MAX_FOOTPRINT, QUAT_RANGE, SCALE_MAX, cull_mask
from render.projection import RADIUS_SIGMAS, project_gaussians
from render.splat import rasterize

W, H = 16, 12
NAN, INF = float("nan"), float("inf")


@st.composite
def camera(draw):
    """viewmat [4, 4] (a rotation about y and a translation that adds 0.2 to z), K [3, 3] with a focal length
    of 2 to 2000 pixels and maybe skew, as float32 numpy."""
    yaw = draw(st.sampled_from([0.0, 0.1, 2.0]))
    c, s = math.cos(yaw), math.sin(yaw)
    V = np.eye(4, dtype=np.float32)
    V[:3, :3] = [[c, 0, -s], [0, 1, 0], [s, 0, c]]
    V[:3, 3] = [0.1, -0.05, 0.2]
    f = draw(st.sampled_from([2.0, 20.0, 2000.0]))
    skew = draw(st.sampled_from([0.0, 0.3]))
    K = np.array([[f, skew, W / 2 + 0.4], [0, 1.05 * f, H / 2 - 0.3], [0, 0, 1]], np.float32)
    return V, K


@st.composite
def gaussian(draw, finite: bool):
    """One Gaussian (mean [3], quat [4], scales [3], opacity) of a random kind, float32 values."""
    f32 = dict(allow_nan=False, allow_infinity=False)  # rounded to float32 below
    kind = draw(st.sampled_from(["ordinary", "huge", "tiny", "needle", "disc", "plane", "behind", "wild"]))
    mean = [draw(st.floats(-1.5, 1.5, **f32)), draw(st.floats(-1.5, 1.5, **f32)), draw(st.floats(0.5, 6, **f32))]
    lo, hi = {"ordinary": (-5, -1), "huge": (10, 80), "tiny": (-80, -10)}.get(kind, (-80, 80))
    scales = [math.exp(draw(st.floats(lo, hi, **f32))) for _ in range(3)]
    if kind in ("needle", "disc"):  # one (needle: two) scale ~0, the others large
        small = 2 if kind == "needle" else 1
        for i in range(3):
            scales[i] = math.exp(draw(st.floats(-80, -12, **f32)) if i < small else draw(st.floats(-3, 40, **f32)))
    if kind == "plane":  # on or beside the near or far plane (the camera adds 0.2 to z)
        mean[2] = draw(st.sampled_from([0.01, 0.5, 10.0])) - 0.2 + draw(st.sampled_from([0.0, -1e-6, 1e-6]))
    if kind == "behind":
        mean[2] = draw(st.floats(-5, -0.2, **f32))
    if kind == "wild":
        mean = [draw(st.floats(-3e38, 3e38, **f32)) for _ in range(3)]
    q = [draw(st.floats(-1, 1, **f32)) for _ in range(4)]
    qscale = draw(st.sampled_from([1.0, 1.0, 0.0, 1e-12, 1e-30, 1e14, 1e30]))
    quat = [v * qscale for v in q]
    if not finite and draw(st.integers(0, 5)) == 0:  # a NaN or inf in one field
        field = draw(st.sampled_from([mean, quat, scales]))
        field[draw(st.integers(0, len(field) - 1))] = draw(st.sampled_from([NAN, INF, -INF]))
    opacity = draw(st.sampled_from([0.0, 0.003, 0.5, 0.99]))
    return mean, quat, scales, opacity


@st.composite
def scene(draw, finite: bool = False):
    """((means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colours [N, 3]) float32, N in 1..5,
    (near, far), (viewmat, K))."""
    gs = draw(st.lists(gaussian(finite), min_size=1, max_size=5))
    with np.errstate(over="ignore"):  # e^80 is inf in float32: an overflow, as a user's file could hold
        arrays = [np.array([g[i] for g in gs], np.float32) for i in range(4)]
    colors = np.random.default_rng(len(gs)).uniform(size=(len(gs), 3)).astype(np.float32)
    planes = (draw(st.sampled_from([0.01, 0.5])), draw(st.sampled_from([1e10, 10.0])))
    return (*arrays, colors), planes, draw(camera())


def _mask(arrays, near, far, V, K):
    means, quats, scales = (torch.from_numpy(a) for a in arrays[:3])
    return cull_mask(means, quats, scales, torch.from_numpy(V)[None], torch.from_numpy(K)[None], W, H,
                     near_plane=near, far_plane=far)[0].numpy()


def _float64_view(means, quats, scales, V, K):
    """An independent float64 projection -> (z, |u| + |v| bound, max |J W R S| entry, trace^2 / det) per
    Gaussian (eps2d 0.3, tangents clamped as gsplat)."""
    m, q, s = (np.asarray(a, np.float64) for a in (means, quats, scales))
    V, K = V.astype(np.float64), K.astype(np.float64)
    p = m @ V[:3, :3].T + V[:3, 3]
    x, y, z = p.T
    n = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(n > 0, q / np.where(n > 0, n, 1), [1, 0, 0, 0])
    w, a, b, c = q.T
    R = np.stack([1 - 2 * (b * b + c * c), 2 * (a * b - w * c), 2 * (a * c + w * b),
                  2 * (a * b + w * c), 1 - 2 * (a * a + c * c), 2 * (b * c - w * a),
                  2 * (a * c - w * b), 2 * (b * c + w * a), 1 - 2 * (a * a + b * b)], 1).reshape(-1, 3, 3)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tx = np.clip(x / z, -(cx / fx + 0.15 * W / fx), (W - cx) / fx + 0.15 * W / fx)
    ty = np.clip(y / z, -(cy / fy + 0.15 * H / fy), (H - cy) / fy + 0.15 * H / fy)
    J = np.zeros((len(z), 2, 3))
    J[:, 0, 0], J[:, 0, 2], J[:, 1, 1], J[:, 1, 2] = fx / z, -fx * tx / z, fy / z, -fy * ty / z
    F = J @ V[:3, :3] @ (R * s[:, None, :])
    cov = F @ F.transpose(0, 2, 1) + 0.3 * np.eye(2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    uv = (np.abs(fx * x) + np.abs(K[0, 1] * y) + np.abs(fy * y)) / np.abs(z)
    return z, uv, np.abs(F).max((1, 2)), (cov[:, 0, 0] + cov[:, 1, 1]) ** 2 / det


@given(scene())
def test_the_rule_keeps_exactly_what_it_states(sc):
    arrays, (near, far), (V, K) = sc
    means, quats, scales = arrays[:3]
    keep = _mask(arrays, near, far, V, K)
    finite = np.isfinite(means).all(1) & np.isfinite(quats).all(1) & np.isfinite(scales).all(1)
    qmax = np.abs(quats).max(1)
    params = finite & (np.abs(scales).max(1) <= SCALE_MAX) & ((qmax == 0) | ((qmax >= QUAT_RANGE[0]) &
                                                                          (qmax <= QUAT_RANGE[1])))
    assert not keep[~params].any()
    if not params.any():
        return
    i = np.flatnonzero(params)
    with np.errstate(all="ignore"):
        z, uv, fmax, kappa = _float64_view(means[i], quats[i], scales[i], V, K)
        tol = 1e-5 * (np.abs(means[i]) @ np.abs(V[2, :3]) + abs(V[2, 3])) + 1e-30  # float32 rounding of z
        outside = (z < near - tol) | (z > far + tol)
        clearly = ((z > near + tol) & (z < far - tol) & (uv < 1e36) & (fmax < 0.99 * MAX_FOOTPRINT)
                   & (kappa < 0.99 * MAX_CONDITION))
    assert not keep[i][outside].any(), "kept outside (near, far)"
    assert keep[i][clearly].all(), f"not kept though clearly drawable: z {z}, |F| {fmax}, kappa {kappa}"
    kept = keep[i]
    assert (kappa[kept] <= 1.01 * MAX_CONDITION).all() and (fmax[kept] < 1.01 * MAX_FOOTPRINT).all()


@given(scene())
def test_torch_splatter_is_finite_and_draws_what_the_rule_keeps(sc):
    """radii[n] > 0 exactly where the rule keeps n and its 3.33-sigma box around means2d overlaps the image."""
    arrays, (near, far), cam = sc
    leaves = [torch.from_numpy(a).requires_grad_(True) for a in arrays]
    V, K = (torch.from_numpy(a)[None] for a in cam)
    bg = torch.tensor([[0.2, 0.4, 0.6]])
    img, alpha, meta = rasterize(*leaves, V, K, W, H, backgrounds=bg, near_plane=near, far_plane=far,
                                 check_finite=False)
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    assert ((alpha >= 0) & (alpha <= 1)).all()
    weights = torch.linspace(-1, 1, img.numel()).view_as(img)
    grads = torch.autograd.grad((img * weights).sum() + alpha.sum(), leaves, allow_unused=True)
    for name, g in zip(("means", "quats", "scales", "opacities", "colors"), grads, strict=True):
        assert g is None or torch.isfinite(g).all(), f"non-finite gradient of {name}"
    keep = torch.from_numpy(_mask(arrays, near, far, *cam))
    with torch.no_grad():
        proj = project_gaussians(*leaves[:3], V, K, W, H, near_plane=near, far_plane=far)
    u, v = proj.means2d[0].unbind(-1)
    rx = torch.ceil(RADIUS_SIGMAS * proj.cov2d[0, :, 0].sqrt())
    ry = torch.ceil(RADIUS_SIGMAS * proj.cov2d[0, :, 2].sqrt())
    on_image = (u + rx > 0) & (u - rx < W) & (v + ry > 0) & (v - ry < H)
    drawn = (meta["radii"][0] > 0).all(-1)
    assert torch.equal(drawn, keep & on_image)
    assert torch.equal(meta["radii"], proj.radii)
    if not drawn.any():  # nothing drawn: the background, exactly
        assert torch.equal(img, bg.view(1, 1, 1, 3).expand_as(img)) and (alpha == 0).all()


@given(scene(finite=True))
def test_preview_drawable_is_the_rule(sc):
    from render.preview_footprints import drawable

    arrays, (near, far), (V, K) = sc
    np.testing.assert_array_equal(drawable(*arrays[:3], V, K, W, H, near, far, 0.3), _mask(arrays, near, far, V, K))


@pytest.fixture(scope="module")
def splatter():
    from tests.gl import gl_available, skip_without_gl

    if not gl_available():
        skip_without_gl("no headless OpenGL")
    from render.preview import PreviewSplatter

    yield lambda near, far: PreviewSplatter(W, H, near_plane=near, far_plane=far)


@given(sc=scene(finite=True))
def test_preview_draws_what_the_rule_keeps(splatter, sc):
    arrays, (near, far), (V, K) = sc
    s = splatter(near, far)
    try:
        bg = np.array([0.2, 0.4, 0.6], np.float32)
        img, alpha = s.render(*arrays, V, K, bg, return_alpha=True)
        ids = s.drawn
    finally:
        s.release()
    assert np.isfinite(img).all() and np.isfinite(alpha).all()
    assert alpha.min() >= 0 and alpha.max() <= 1
    want = np.flatnonzero(_mask(arrays, near, far, V, K) & (255.0 * arrays[3].astype(np.float64) > 1))
    np.testing.assert_array_equal(np.sort(ids), want)
    if ids.size == 0:
        np.testing.assert_array_equal(img, np.broadcast_to(bg, img.shape))
