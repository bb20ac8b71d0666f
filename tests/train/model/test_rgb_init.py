"""Initial RGB channels from the training images: blending-weighted mean colours, exact occlusion via the
splatter's own weights, a fallback for unseen Gaussians."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from tests.train.helpers import model_inputs, small_model
from toolkit.procedural import demo_head_scene
from train.losses.metrics import psnr
from train.model.rgb_init import init_rgb_from_images, rgb_from_images


def _views(n: int = 4, res: int = 128):
    """Inputs for ``n`` views of the head turned by different yaws and pitches, with distinct gazes."""
    code, pose, gaze, vm, K = model_inputs(n, width=res, height=res)
    yaw = torch.linspace(-0.5, 0.5, n)
    pose[:, 1] = yaw
    pose[:, 0] = 0.2 * torch.cos(3 * yaw)
    return code, pose, gaze, vm, K


def _images(model, code, pose, gaze, vm, K, res: int = 128):
    """The model's own splat RGB and alpha at its render resolution, upsampled (nearest) to ``res``: the
    area-downsampling inside rgb_from_images gives back exactly the splat's pixels."""
    with torch.no_grad():
        maps = model(code, pose, gaze, vm, K, res, res, renders=("head",))
    up = lambda x: F.interpolate(x, size=(res, res), mode="nearest")  # noqa: E731
    return up(maps["rgb"]), up(maps["head_alpha"])


def test_recovers_the_colours_the_images_show():
    scene = demo_head_scene(600)
    truth = small_model(scene)
    views = _views()
    images, alpha = _images(truth, *views)
    model = small_model(scene)
    with torch.no_grad():
        model.face_features[:, :3] = torch.rand(model.num_face, 3, generator=torch.Generator().manual_seed(1))
        model.eye_features[:, :3] = 0.0
    before, _ = _images(model, *views)
    seen = init_rgb_from_images(model, images, alpha, *views)
    after, _ = _images(model, *views)
    assert 0.3 < seen <= 1.0  # the back of the head is never in view
    p_before, p_after = psnr(before, images).mean(), psnr(after, images).mean()
    assert p_after > 25.0 and p_after > p_before + 10.0, (p_before, p_after)
    # Well-seen Gaussians get (a smoothed version of) their own colour.
    out = rgb_from_images(model, images, alpha, *views)
    w = out["face_weight"]
    well = w > w.quantile(0.5)
    true = truth.face_features[well, :3].clamp(0, 1)
    err = (out["face"][well] - true).abs().mean()
    spread = (true - true.mean(0)).abs().mean()  # the error of the best single colour
    assert err < 0.5 * spread, (err, spread)


def test_unseen_gaussians_get_the_mean_colour_and_no_mask_gives_grey():
    scene = demo_head_scene(300)
    model = small_model(scene)
    views = _views(1)
    images, alpha = _images(model, *views)
    out = rgb_from_images(model, images, alpha, *views)
    unseen = out["face_weight"] <= 1e-4
    assert unseen.any() and (~unseen).any()
    seen_mean = out["face"][~unseen].mean(0)
    assert torch.allclose(out["face"][unseen], seen_mean.expand(int(unseen.sum()), 3), atol=0.05)
    empty = rgb_from_images(model, images, torch.zeros_like(alpha), *views)
    assert torch.equal(empty["face"], torch.full_like(empty["face"], 0.5))
    assert torch.equal(empty["eyes"], torch.full_like(empty["eyes"], 0.5))


def test_extreme_images_give_finite_colours_in_range():
    scene = demo_head_scene(300)
    model = small_model(scene)
    views = _views(2)
    _, alpha = _images(model, *views)
    for fill in (0.0, 1.0, 1e6):
        images = torch.full((2, 3, 128, 128), fill)
        out = rgb_from_images(model, images, alpha, *views)
        for k in ("face", "eyes"):
            assert torch.isfinite(out[k]).all() and out[k].min() >= 0 and out[k].max() <= 1


def test_eye_colours_are_read_at_full_resolution():
    """At the model's 1/4 resolution an eye is a few pixels and every eye Gaussian gets the same mixture; the
    initializer reads the eyes at the images' own resolution, where their own colours show."""
    import dataclasses
    import math

    scene = demo_head_scene(600)
    truth, model = small_model(scene), small_model(scene)
    with torch.no_grad():  # small eye Gaussians (the demo scene's are ~half an eyeball wide)
        for m in (truth, model):
            m.eye_log_scales.fill_(math.log(0.0015))
    with torch.no_grad():  # a dark iris within 30 degrees of each eyeball's front, white sclera around it
        d = truth.eye_means - truth.eye_centers[truth.eye_side.long()]
        iris = (-d[:, 2] / d.norm(dim=-1)) > 0.866
        truth.eye_features[:, :3] = torch.where(iris[:, None], 0.1, 0.9)
    truth.config = dataclasses.replace(truth.config, render_scale=1.0)
    views = _views()
    with torch.no_grad():
        maps = truth(*views, 128, 128, renders=("head",))
    images, alpha = maps["rgb"], maps["head_alpha"]
    assert model.config.render_scale < 1
    quarter = rgb_from_images(model, images, alpha, *views)
    init_rgb_from_images(model, images, alpha, *views)
    full = rgb_from_images(model, images, alpha, *views, render_scale=1.0)
    seen = full["eyes_weight"] > 1e-4
    contrast = lambda rgb: float((rgb[seen & ~iris].mean() - rgb[seen & iris].mean()).detach())  # noqa: E731
    assert contrast(model.eye_features[:, :3]) > 2 * contrast(quarter["eyes"]) > 0  # measured: 0.095 and 0.027
    torch.testing.assert_close(model.eye_features[:, :3], full["eyes"])


def test_a_parametric_eyeball_keeps_its_eye_features_and_skips_the_full_resolution_pass(monkeypatch):
    """With ``eyeball_colours`` the eyes' RGB columns are never drawn: the initializer leaves them as they were and
    reads the images once, at the model's resolution, for the face alone."""
    import train.model.rgb_init as ri

    model = small_model(demo_head_scene(600), eyeball_colours=True)
    assert model.config.render_scale < 1
    views = _views()
    images, masks = torch.rand(4, 3, 128, 128), torch.ones(4, 1, 128, 128)
    scales = []
    real = ri.rgb_from_images
    monkeypatch.setattr(ri, "rgb_from_images", lambda *a, **k: (scales.append(k.get("render_scale")), real(*a, **k))[1])
    before, face_before = model.eye_features.detach().clone(), model.face_features.detach().clone()
    seen = init_rgb_from_images(model, images, masks, *views)
    assert scales == [None] and 0 < seen <= 1
    assert torch.equal(model.eye_features.detach(), before)
    assert not torch.equal(model.face_features.detach()[:, :3], face_before[:, :3])  # the face is initialized
