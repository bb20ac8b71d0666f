"""The residual DiT renderer: x0 = z_base + r0_hat around the encoded, upsampled splat RGB."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from tests.train.helpers import fit_renderer
from tests.train.threads import single_thread  # noqa: F401  (autouse)
from toolkit import ToolkitError
from train.model.codec import AutoencoderConfig, KLAutoencoder, PixelCodec
from train.model.diffusion import DiffusionConfig, GaussianDiffusion
from train.model.dit import make_dit
from train.model.renderer import DiTRenderer, make_renderer

AE = AutoencoderConfig(downsample=4, base_channels=8, max_channels=16)


def residual_renderer(seed: int = 0, **kw) -> DiTRenderer:
    torch.manual_seed(seed)
    return make_renderer("dit", KLAutoencoder(AE), output_size=16, gaze_dim=2, pose_dim=6, **kw)


def perturb(module: torch.nn.Module, seed: int = 0, scale: float = 0.05) -> None:
    """Nudge every weight off its (partly zero) initialization, as after some training."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g))


def inputs(B: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(B, 32, 4, 4, generator=g), torch.randn(B, 144, generator=g), 0.3 * torch.randn(B, 2, generator=g),
            0.1 * torch.randn(B, 6, generator=g))


def splat_reference(r: DiTRenderer, feats: torch.Tensor) -> torch.Tensor:
    up = F.interpolate(feats[:, :3], scale_factor=float(r.upscale), mode="bilinear", align_corners=False)
    return r.codec.decode(r.codec.encode(up.clamp(0, 1)))


def test_untrained_one_step_render_is_the_decoded_splat_rgb():
    r = residual_renderer()
    assert r.residual and r.dit.config.base_channels == r.codec.latent_channels
    f, c, gz, ps = inputs()
    ref = splat_reference(r, f)
    with torch.no_grad():
        img = r.render(f, c, gaze=gz, pose=ps, steps=1, seed=3)
        train_img = r.training_forward(f, c, torch.rand(2, 3, 16, 16), gaze=gz, pose=ps,
                                       t=torch.full((2,), r.diffusion.num_timesteps - 1)).image
    torch.testing.assert_close(img, ref.clamp(0, 1), atol=1e-5, rtol=0)
    torch.testing.assert_close(train_img, ref, atol=1e-5, rtol=0)  # the training pass's decoded x0 estimate too


def test_plain_dit_does_not_start_from_the_splat():
    """The switch: residual=False is the old renderer (no base input), whose untrained render ignores the splat."""
    torch.manual_seed(0)
    r = make_renderer("dit", KLAutoencoder(AE), output_size=16, residual=False)
    assert not r.residual and r.dit.config.base_channels == 0
    f, c, _, _ = inputs()
    with torch.no_grad():
        a = r.render(f, c)
        b = r.render(torch.rand_like(f), c)
    torch.testing.assert_close(a, b)  # zero output layer: the same image whatever the features
    assert (a - splat_reference(r, f).clamp(0, 1)).abs().max() > 1e-3


def test_gradients_reach_the_dit_and_the_features():
    r = residual_renderer()
    perturb(r.dit)
    f, c, gz, ps = inputs()
    f.requires_grad_(True)
    out = r.training_forward(f, c, torch.rand(2, 3, 16, 16), gaze=gz, pose=ps, generator=torch.Generator().manual_seed(0))
    assert "latent_base" in out.extras
    ((out.image - 0.5).abs().mean() + out.aux_loss).backward()
    grads = {n: p.grad for n, p in r.dit.named_parameters()}
    assert all(g is not None and torch.isfinite(g).all() for g in grads.values()), [n for n, g in grads.items() if g is None]
    assert grads["x_embedder.proj.weight"][:, -r.codec.latent_channels:].abs().sum() > 0  # the base-latent input
    assert f.grad is not None and torch.isfinite(f.grad).all()
    assert f.grad[:, :3].abs().sum() > 0 and f.grad[:, 3:].abs().sum() > 0  # RGB via z_base, all via the encoder
    assert all(p.grad is None for p in r.codec.parameters())  # the codec stays frozen


def test_untrained_image_loss_trains_the_splat_rgb_through_the_base():
    """At initialization the DiT's correction is 0, yet the image loss must still reach the splat's RGB."""
    r = residual_renderer()
    f, c, gz, ps = inputs()
    f.requires_grad_(True)
    out = r.training_forward(f, c, torch.rand(2, 3, 16, 16), gaze=gz, pose=ps, t=torch.full((2,), 999))
    (out.image - 0.5).abs().mean().backward()
    assert f.grad[:, :3].abs().sum() > 0


def test_ddim_multi_step_is_finite_and_deterministic():
    r = residual_renderer()
    perturb(r.dit)
    f, c, gz, ps = inputs()
    with torch.no_grad():
        for steps in (1, 2, 4, 8):
            a = r.render(f, c, gaze=gz, pose=ps, steps=steps, seed=5)
            assert a.shape == (2, 3, 16, 16) and torch.isfinite(a).all()
            assert torch.equal(a, r.render(f, c, gaze=gz, pose=ps, steps=steps, seed=5))
        assert not torch.equal(r.render(f, c, gaze=gz, pose=ps, steps=4, seed=5),
                               r.render(f, c, gaze=gz, pose=ps, steps=4, seed=6))


def test_ddim_adds_the_base_to_the_sampled_residual():
    """With a known network output the sampler's latent is exactly z_base + the plain sampler's residual."""
    r = residual_renderer()
    perturb(r.dit)
    f, c, gz, ps = inputs()
    shape = r.latent_shape(f)
    noise = torch.randn(shape, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        base = r.base_latent(f)
        fn = r._model_fn(f, c, gz, ps, shape[2:], base)
        resid = r.diffusion.ddim_sample(fn, noise, 3)
        expected = r.codec.decode(base + resid).clamp(0, 1)
        torch.testing.assert_close(r.render(f, c, gaze=gz, pose=ps, steps=3, noise=noise), expected)


@pytest.mark.parametrize("prediction,zt", [("v", True), ("v", False), ("eps", False)])
def test_training_x0_estimate_is_base_plus_residual_for_each_target(prediction, zt):
    """eps or v: the losses see x0 = z_base + predict_x0(residual diffusion); the regression target is the residual's."""
    torch.manual_seed(0)
    dit = make_dit("DiT-Gaze-tiny", input_size=8, latent_channels=3, base_channels=3)
    diff = GaussianDiffusion(DiffusionConfig(prediction=prediction, zero_terminal_snr=zt))
    perturb(dit)
    r = DiTRenderer(dit, PixelCodec(), diff, upscale=2)
    f, c = torch.rand(2, 32, 4, 4), torch.randn(2, 144)
    target = torch.rand(2, 3, 8, 8)
    t = torch.tensor([10, 500])
    noise = torch.randn(2, 3, 8, 8, generator=torch.Generator().manual_seed(2))
    torch.manual_seed(7)
    out = r.training_forward(f, c, target, t=t, generator=torch.Generator().manual_seed(3))
    base, z0 = out.extras["latent_base"], out.extras["latent_target"]
    g = torch.Generator().manual_seed(3)
    noise = torch.randn(z0.shape, generator=g)
    x_t = diff.q_sample(z0 - base, t, noise)
    with torch.no_grad():
        o = r.dit(x_t, t, f, c, base=base)
        torch.testing.assert_close(out.extras["latent_pred"], base + diff.predict_x0(o, x_t, t), atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(out.aux_loss, diff.loss(o, z0 - base, noise, t), atol=1e-6, rtol=1e-5)


def test_learns_the_missing_detail_faster_than_from_nothing():
    """Target = splat RGB + a fixed detail: the residual renderer starts closer and stays ahead after training."""
    errs = {}
    g0 = torch.Generator().manual_seed(0)
    feats = torch.rand(8, 32, 4, 4, generator=g0)
    up = F.interpolate(feats[:, :3], scale_factor=2.0, mode="bilinear", align_corners=False)
    detail = 0.15 * torch.sin(torch.arange(8.0) * math.pi / 2).view(1, 1, 1, 8)
    target = (up + detail).clamp(0, 1)
    code = torch.zeros(8, 144)
    for residual in (True, False):
        torch.manual_seed(0)
        dit = make_dit("DiT-Gaze-tiny", input_size=8, latent_channels=3, base_channels=3 if residual else 0)
        r = DiTRenderer(dit, PixelCodec(), GaussianDiffusion(DiffusionConfig()), upscale=2, residual=residual)
        errs[residual] = fit_renderer(r, feats, code, target, torch.Generator().manual_seed(0), 60)
    assert errs[True] < errs[False], errs


def test_errors():
    with pytest.raises(ToolkitError, match="base_channels"):
        DiTRenderer(make_dit("DiT-Gaze-tiny", input_size=4, base_channels=4), KLAutoencoder(AE), residual=False)
    with pytest.raises(ToolkitError, match="base_channels"):
        DiTRenderer(make_dit("DiT-Gaze-tiny", input_size=4, base_channels=3), KLAutoencoder(AE))
    with pytest.raises(ToolkitError, match="base_channels"):
        make_dit("DiT-Gaze-tiny", base_channels=-1)
    r = residual_renderer()
    f, c, gz, ps = inputs(1)
    with pytest.raises(ToolkitError, match="DiT base"):
        r.dit(torch.randn(1, 4, 4, 4), torch.tensor([0]), f, c, gz, ps)  # base latent missing


# ----------------------------------------------------------------------------- stress
EXTREME_FEATS = {
    "zeros": lambda: torch.zeros(1, 32, 4, 4),
    "huge": lambda: torch.full((1, 32, 4, 4), 1e4),
    "huge_negative": lambda: torch.full((1, 32, 4, 4), -1e4),
    "mixed_huge": lambda: torch.randn(1, 32, 4, 4, generator=torch.Generator().manual_seed(0)) * 1e6,
}
EXTREME_CODES = {
    "zero": (torch.zeros(1, 144), torch.zeros(1, 2), torch.zeros(1, 6)),
    "huge": (torch.full((1, 144), 1e6), torch.full((1, 2), 1e6), torch.full((1, 6), -1e6)),
    "extreme_gaze": (torch.randn(1, 144), torch.tensor([[math.radians(89), -math.radians(89)]]), torch.randn(1, 6)),
}


@pytest.mark.parametrize("feats", list(EXTREME_FEATS))
@pytest.mark.parametrize("codes", list(EXTREME_CODES))
def test_extreme_inputs_batch_of_one_finite(feats, codes):
    r = residual_renderer()
    perturb(r.dit)
    f = EXTREME_FEATS[feats]().requires_grad_(True)
    c, gz, ps = EXTREME_CODES[codes]
    for t in (torch.tensor([0]), torch.tensor([999]), None):
        out = r.training_forward(f, c, torch.rand(1, 3, 16, 16), gaze=gz, pose=ps, t=t,
                                 generator=torch.Generator().manual_seed(0))
        assert torch.isfinite(out.image).all() and torch.isfinite(out.aux_loss)
        r.dit.zero_grad()
        f.grad = None
        (out.image.mean() + out.aux_loss).backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in r.dit.parameters())
        assert torch.isfinite(f.grad).all()
    with torch.no_grad():
        for steps in (1, 3):
            img = r.render(f, c, gaze=gz, pose=ps, steps=steps)
            assert torch.isfinite(img).all() and img.shape == (1, 3, 16, 16)


def test_bf16_autocast_forward_backward_on_cpu():
    r = residual_renderer()
    perturb(r.dit)
    f, c, gz, ps = inputs()
    f.requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = r.training_forward(f, c, torch.rand(2, 3, 16, 16), gaze=gz, pose=ps,
                                 generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            imgs = [r.render(f, c, gaze=gz, pose=ps, steps=s) for s in (1, 2)]
    loss = out.image.float().mean() + out.aux_loss.float()
    loss.backward()
    assert torch.isfinite(loss) and all(torch.isfinite(i).all() for i in imgs)
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in r.dit.parameters())
    assert torch.isfinite(f.grad).all() and f.grad[:, :3].abs().sum() > 0


def test_seeded_models_and_renders_are_identical():
    f, c, gz, ps = inputs()
    a, b = residual_renderer(seed=4), residual_renderer(seed=4)
    perturb(a.dit, 1)
    perturb(b.dit, 1)
    with torch.no_grad():
        assert torch.equal(a.render(f, c, gaze=gz, pose=ps, steps=4, seed=2), b.render(f, c, gaze=gz, pose=ps, steps=4, seed=2))
    g1, g2 = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
    oa = a.training_forward(f, c, torch.full((2, 3, 16, 16), 0.5), gaze=gz, pose=ps, generator=g1)
    ob = b.training_forward(f, c, torch.full((2, 3, 16, 16), 0.5), gaze=gz, pose=ps, generator=g2)
    assert torch.equal(oa.image, ob.image) and torch.equal(oa.aux_loss, ob.aux_loss)
