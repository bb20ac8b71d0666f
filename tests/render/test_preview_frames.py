"""The preview splatter's frames that skip work (``render.preview``, ``render.preview_layers``,
``render.preview_gl``): gaze-only frames from the depth layers, re-sorts and uploads only when needed, the
``may_change`` hint; each equals a full redraw."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.render.test_preview import _demo, _two_overlapping, camera, random_gaussians
from toolkit.errors import ToolkitError


def test_gaze_only_frames_equal_full_redraws(ctx):
    from render.preview import PreviewSplatter
    from toolkit.eyes import redirect_eyes

    scene, cam = _demo()
    live = PreviewSplatter(cam.width, cam.height, ctx=ctx)
    prev = live.render_scene(scene, cam, background=(0.1, 0.2, 0.3)).copy()
    assert live.stats["path"] == "full"
    n_eye = int((scene.part > 0).sum())
    for k, gaze in enumerate([(0.3, 0.4), (-0.4, -0.5), (0.1, -0.6), (0.0, 0.0)]):
        moved = redirect_eyes(scene, gaze)
        img = live.render_scene(moved, cam, background=(0.1, 0.2, 0.3)).copy()
        st = live.stats
        assert st["path"] == "incremental" and st["uploaded"] == n_eye
        assert st["layers_built"] == (k == 0)  # the depth layers are built once per camera
        full = PreviewSplatter(cam.width, cam.height, ctx=ctx).render_scene(moved, cam, background=(0.1, 0.2, 0.3))
        np.testing.assert_allclose(img, full, atol=2e-6, rtol=0)
        # Outside the redrawn rectangle nothing changed; inside, the eyes did.
        x, y, w, h = live.last_rect
        assert w * h < 0.25 * cam.width * cam.height
        outside = np.ones(img.shape[:2], bool)
        outside[y:y + h, x:x + w] = False
        np.testing.assert_array_equal(img[outside], prev[outside])
        assert np.abs(img - prev).max() > 0.05
        prev = img
    live.render_scene(moved, cam)
    assert live.stats["path"] == "unchanged"
    # An empty frame frees the depth layers' GL textures, and the next frame builds them anew.
    layers = [live._layers[k] for k in ("back_tex", "front_tex", "back_fbo", "front_fbo")]
    e = np.zeros((0, 3), np.float32)
    live.render(e, np.zeros((0, 4)), e, np.zeros(0), e, cam.viewmat, cam.K)
    assert live._layers is None and all(type(x.mglo).__name__ == "InvalidObject" for x in layers)
    img = live.render_scene(moved, cam, background=(0.1, 0.2, 0.3))
    np.testing.assert_allclose(img, prev, atol=2e-6, rtol=0)


def test_generic_dynamic_set_without_spheres_rebuilds_layers(ctx):
    """Without eyeball spheres the cached depth range is a guess; moving past it must rebuild, not lie."""
    from render.preview import PreviewSplatter

    gs = random_gaussians(200, 5)
    V, K = camera()
    dyn = np.zeros(200, bool)
    dyn[:10] = True
    live = PreviewSplatter(64, 48, ctx=ctx)
    live.render(*gs, V, K, dynamic=dyn)
    for dz in (0.01, 0.6, -0.9):
        gs[0] = gs[0].copy()
        gs[0][:10, 2] += dz
        gs[0][:10, 0] += 0.05
        img = live.render(*gs, V, K, dynamic=dyn).copy()
        assert live.stats["path"] == "incremental"
        np.testing.assert_allclose(img, PreviewSplatter(64, 48, ctx=ctx).render(*gs, V, K), atol=2e-6, rtol=0)


def test_resort_and_upload_only_when_needed(ctx):
    from render.preview import PreviewSplatter

    gs = random_gaussians(400, 7)
    V, K = camera()
    s = PreviewSplatter(64, 48, ctx=ctx)
    s.render(*gs, V, K)
    assert s.stats["resorted"] and s.stats["uploaded"] == 400
    V2 = V.copy()
    V2[2, 3] += 0.05  # moving along the view axis keeps every depth order
    img = s.render(*gs, V2, K).copy()
    assert s.stats["path"] == "full" and not s.stats["resorted"] and s.stats["uploaded"] == 0
    np.testing.assert_array_equal(img, PreviewSplatter(64, 48, ctx=ctx).render(*gs, V2, K))
    V3, _ = camera(yaw=0.3)
    s.render(*gs, V3, K)
    assert s.stats["resorted"]
    gs[3] = gs[3].copy()
    gs[3][[5, 50, 399]] = 0.9  # three Gaussians changed: three uploaded, the picture still exact
    img = s.render(*gs, V3, K).copy()
    assert s.stats["uploaded"] == 3
    np.testing.assert_allclose(img, PreviewSplatter(64, 48, ctx=ctx).render(*gs, V3, K), atol=1e-6)


def test_resort_tolerance_keeps_order_for_small_orbits(ctx):
    from render.preview import PreviewSplatter

    gs = random_gaussians(300, 8)
    K = camera()[1]
    s = PreviewSplatter(64, 48, ctx=ctx, resort_tolerance=math.radians(1.0))
    s.render(*gs, camera(yaw=0.0)[0], K)
    s.render(*gs, camera(yaw=math.radians(0.5))[0], K)
    assert not s.stats["resorted"]
    s.render(*gs, camera(yaw=math.radians(5))[0], K)
    assert s.stats["resorted"]


def test_resort_tolerance_never_keeps_an_order_the_gaussians_left(ctx):
    """The tolerance is for a moving view: when Gaussians move under the same camera, the order is redone."""
    from render.preview import PreviewSplatter

    V, K = camera()
    gs = _two_overlapping(red_z=3.0, blue_z=3.2)
    s = PreviewSplatter(64, 48, ctx=ctx, resort_tolerance=math.radians(5.0))
    s.render(*gs, V, K)
    gs[0] = gs[0].copy()
    gs[0][0, 2] = 3.4  # red now behind blue
    img = s.render(*gs, V, K).copy()
    assert s.stats["resorted"]
    np.testing.assert_allclose(img, PreviewSplatter(64, 48, ctx=ctx).render(*gs, V, K), atol=1e-6)


def test_resort_tolerance_never_keeps_a_gaussian_the_cull_rule_drops(ctx):
    """A small move forward (within the tolerance) takes a Gaussian in front of the near plane: the order
    is redone without it, as a fresh frame draws."""
    from render.preview import PreviewSplatter

    V, K = camera()
    gs = _two_overlapping(red_z=0.6, blue_z=3.0)
    s = PreviewSplatter(64, 48, ctx=ctx, near_plane=0.5, resort_tolerance=math.radians(5.0))
    s.render(*gs, V, K)
    assert sorted(s.drawn.tolist()) == [0, 1]
    V2 = V.copy()
    V2[2, 3] -= 0.15  # the red Gaussian's camera z: 0.45 < near
    img = s.render(*gs, V2, K).copy()
    assert s.drawn.tolist() == [1] and s.stats["culled"] == 1
    np.testing.assert_allclose(img, PreviewSplatter(64, 48, ctx=ctx, near_plane=0.5).render(*gs, V2, K), atol=1e-6)


def test_may_change_hint_limits_the_comparison(ctx):
    from render.preview import PreviewSplatter

    gs = random_gaussians(300, 9)
    V, K = camera()
    dyn = np.zeros(300, bool)
    dyn[100:130] = True
    s = PreviewSplatter(64, 48, ctx=ctx)
    s.render(*gs, V, K, dynamic=dyn, may_change=np.arange(100, 130))
    gs[0] = gs[0].copy()
    gs[0][100:105, 0] += 0.1
    img = s.render(*gs, V, K, dynamic=dyn, may_change=np.arange(100, 130)).copy()
    assert s.stats["uploaded"] == 5 and s.stats["path"] == "incremental"
    np.testing.assert_allclose(img, PreviewSplatter(64, 48, ctx=ctx).render(*gs, V, K), atol=2e-6, rtol=0)
    with pytest.raises(ToolkitError, match="may_change holds ids outside"):
        s.render(*gs, V, K, may_change=[400])
    bad = gs[0].copy()
    bad[101, 1] = np.inf
    with pytest.raises(ToolkitError, match="means contains NaN"):
        s.render(bad, *gs[1:], V, K, may_change=np.arange(100, 130))
