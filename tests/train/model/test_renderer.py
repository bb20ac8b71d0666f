"""The DiT renderer behind the Renderer interface: training pass, DDIM inference, determinism, errors."""

from __future__ import annotations

import pytest
import torch

from tests.train.helpers import fit_renderer
from tests.train.threads import single_thread  # noqa: F401  (autouse)
from toolkit import ToolkitError
from train.model.codec import AutoencoderConfig, KLAutoencoder, PixelCodec
from train.model.diffusion import DiffusionConfig, GaussianDiffusion
from train.model.dit import make_dit
from train.model.renderer import DiTRenderer, make_renderer
from train.model.renderer_interface import Renderer, RenderOutput


def latent_renderer(**kw) -> DiTRenderer:
    codec = KLAutoencoder(AutoencoderConfig(downsample=4, base_channels=8, max_channels=16))
    return make_renderer("dit", codec, output_size=16, **kw)


def test_training_forward_shapes_and_gradients():
    r = latent_renderer()
    assert isinstance(r, Renderer)
    f, c, target = torch.randn(2, 32, 4, 4), torch.randn(2, 144), torch.rand(2, 3, 16, 16)
    out = r.training_forward(f, c, target, generator=torch.Generator().manual_seed(0))
    assert isinstance(out, RenderOutput) and out.image.shape == target.shape
    assert out.extras["latent_pred"].shape == (2, 4, 4, 4) and out.aux_loss.dim() == 0
    ((out.image - target).abs().mean() + out.aux_loss).backward()
    assert r.dit.final_layer.linear.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in r.codec.parameters())  # the codec stays frozen


def test_render_is_deterministic_from_seed_and_steps():
    torch.manual_seed(0)
    r = latent_renderer()
    with torch.no_grad():  # a nonzero network, as after training
        for p in r.dit.parameters():
            p.add_(0.02 * torch.randn_like(p))
    f, c = torch.randn(2, 32, 4, 4), torch.randn(2, 144)
    a = r.render(f, c, steps=1)
    assert a.shape == (2, 3, 16, 16) and a.min() >= 0 and a.max() <= 1
    assert torch.equal(a, r.render(f, c, steps=1))
    assert torch.equal(r.render(f, c, steps=4, seed=1), r.render(f, c, steps=4, seed=1))
    assert not torch.equal(r.render(f, c, steps=4, seed=1), r.render(f, c, steps=4, seed=2))
    assert torch.equal(r(f, c), a)  # forward = render with the default (1) step


def test_it_learns_to_render_from_features_in_pixel_space():
    """Short training on a fixed feature -> image map: the one-step render must get much closer to it."""
    torch.manual_seed(0)
    dit = make_dit("DiT-Gaze-tiny", input_size=8, latent_channels=3, patch_size=2)
    r = DiTRenderer(dit, PixelCodec(), GaussianDiffusion(DiffusionConfig()), upscale=2)
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(8, 32, 4, 4, generator=g)
    target = torch.sigmoid(2 * torch.nn.functional.interpolate(feats[:, :3], scale_factor=2.0, mode="nearest"))
    code = torch.zeros(8, 144)
    with torch.no_grad():
        before = (r.render(feats, code) - target).abs().mean()
    after = fit_renderer(r, feats, code, target, g, 150)
    assert after < 0.5 * before, (float(before), after)


def test_errors():
    r = latent_renderer()
    f, c = torch.randn(1, 32, 4, 4), torch.randn(1, 144)
    with pytest.raises(ToolkitError, match="target"):
        r.training_forward(f, c, torch.rand(1, 3, 8, 8))
    with pytest.raises(ToolkitError, match="multiple of"):
        r.render(torch.randn(1, 32, 3, 3), c)
    with pytest.raises(ToolkitError, match="noise"):
        r.render(f, c, noise=torch.randn(1, 4, 2, 2))
    with pytest.raises(ToolkitError, match="latent_channels"):
        DiTRenderer(make_dit("DiT-Gaze-tiny", input_size=4), PixelCodec())
    with pytest.raises(ToolkitError, match="codec is required"):
        make_renderer("dit")
    with pytest.raises(ToolkitError, match="renderer kind"):
        make_renderer("unet")


def test_renderer_arguments_no_render_can_use_are_named_when_it_is_built():
    """Not an interpolate error at the first render (upscale 0) or a DiT config error about input_size."""
    with pytest.raises(ToolkitError, match=r"DiTRenderer upscale: expected an integer >= 1 .*got 0"):
        make_renderer("dit", PixelCodec(), upscale=0)
    with pytest.raises(ToolkitError, match=r"make_renderer output_size: expected an image size >= the codec's "
                                           r"downsample factor 4, got -32"):
        make_renderer("dit", KLAutoencoder(AutoencoderConfig(downsample=4, base_channels=8, max_channels=16)),
                      output_size=-32)
    with pytest.raises(ToolkitError, match=r"make_renderer: \['input_size'\] follow from the codec and output_size"):
        make_renderer("dit", PixelCodec(), input_size=8)  # was a duplicate-keyword TypeError
    r = make_renderer("dit", PixelCodec(), output_size=16)
    with pytest.raises(ToolkitError, match=r"renderer feats: expected \[B, \d+, h >= 1, w >= 1\], got \[1, \d+, 0, 0\]"):
        r.render(torch.zeros(1, r.dit.config.feature_channels, 0, 0), torch.zeros(1, r.dit.config.shape_dim))


def test_render_refuses_non_finite_conditioning_and_eta():
    """A NaN in the features or codes, or eta = NaN, is named instead of returning a NaN image."""
    r = latent_renderer(gaze_dim=2, pose_dim=6)
    f, c, gaze, pose = torch.rand(1, 32, 4, 4), torch.randn(1, 144), torch.zeros(1, 2), torch.zeros(1, 6)
    nan = float("nan")
    with torch.no_grad():
        good = r.render(f, c, gaze=gaze, pose=pose)
    assert torch.isfinite(good).all()
    for name, kw in (("feats", dict(feats=f.index_fill(2, torch.tensor([1]), nan))),
                     ("shape_code", dict(shape_code=torch.full_like(c, nan))),
                     ("gaze", dict(gaze=torch.full_like(gaze, nan))),
                     ("pose", dict(pose=pose.index_fill(1, torch.tensor([4]), float("inf")))),
                     ("noise", dict(noise=torch.full((1, 4, 4, 4), nan)))):
        args = {"feats": f, "shape_code": c, "gaze": gaze, "pose": pose, **kw}
        with pytest.raises(ToolkitError, match=rf"renderer {name}: expected finite values, found NaN or inf"):
            r.render(args.pop("feats"), args.pop("shape_code"), **args)
    with pytest.raises(ToolkitError, match=r"DiTRenderer eta: expected a finite number"):
        r.render(f, c, gaze=gaze, pose=pose, steps=2, eta=nan)
