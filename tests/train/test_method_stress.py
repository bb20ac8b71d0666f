"""Stress tests for the renderer stack: bf16 autocast, extreme and degenerate codes and inputs, batch of 1,
seeded determinism -- finite outputs and finite gradients everywhere."""

from __future__ import annotations

import math

import pytest
import torch

from tests.train.threads import single_thread  # noqa: F401  (autouse)
from train.model.baseline_renderer import BaselineConfig, BaselineRenderer
from train.model.codec import AutoencoderConfig, KLAutoencoder, PixelCodec, train_autoencoder
from train.model.diffusion import DiffusionConfig, GaussianDiffusion
from train.model.dit import make_dit
from train.model.renderer import DiTRenderer
from train.training.gaze_sampler import GazeSampler, GazeSamplerConfig

AE = AutoencoderConfig(downsample=4, base_channels=8, max_channels=16)


def perturbed(module: torch.nn.Module, seed: int = 0, scale: float = 0.05) -> torch.nn.Module:
    """Nudge every weight off its (partly zero) initialization so every path carries signal and gradient."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g))
    return module


def assert_finite_grads(module: torch.nn.Module) -> None:
    grads = [(n, p.grad) for n, p in module.named_parameters() if p.requires_grad]
    assert grads and all(g is not None for _, g in grads), [n for n, g in grads if g is None]
    bad = [n for n, g in grads if not torch.isfinite(g).all()]
    assert not bad, bad


def dit_renderer(codec=None, seed=0) -> DiTRenderer:
    torch.manual_seed(seed)
    codec = codec or KLAutoencoder(AE)
    dit = make_dit("DiT-Gaze-tiny", input_size=4, latent_channels=codec.latent_channels, gaze_dim=2, pose_dim=6)
    return DiTRenderer(perturbed(dit, seed), codec, GaussianDiffusion(), upscale=4)


CODES = {
    "zero": (torch.zeros(1, 144), torch.zeros(1, 2), torch.zeros(1, 6)),
    "huge": (torch.full((1, 144), 1e6), torch.full((1, 2), 1e6), torch.full((1, 6), -1e6)),
    "extreme_gaze": (torch.randn(1, 144), torch.tensor([[math.radians(89), -math.radians(89)]]), torch.randn(1, 6)),
    "mixed_sign_huge": (torch.randn(1, 144) * 1e8, torch.tensor([[-math.radians(89), math.radians(89)]]),
                        torch.randn(1, 6) * 1e8),
}


@pytest.mark.parametrize("name", list(CODES))
def test_dit_renderer_extreme_codes_batch_of_one(name):
    code, gaze, pose = CODES[name]
    r = dit_renderer()
    f = torch.randn(1, 32, 4, 4)
    out = r.training_forward(f, code, torch.rand(1, 3, 16, 16), gaze=gaze, pose=pose,
                             t=torch.tensor([999]) if name == "zero" else None)
    assert torch.isfinite(out.image).all() and torch.isfinite(out.aux_loss)
    (out.image.mean() + out.aux_loss).backward()
    assert_finite_grads(r.dit)
    with torch.no_grad():
        for steps in (1, 3):
            img = r.render(f, code, gaze=gaze, pose=pose, steps=steps)
            assert torch.isfinite(img).all() and img.shape == (1, 3, 16, 16)


@pytest.mark.parametrize("name", list(CODES))
def test_baseline_extreme_codes_batch_of_one(name):
    code = CODES[name][0]
    r = perturbed(BaselineRenderer(BaselineConfig(upscale=4)))
    img = r(torch.randn(1, 32, 4, 4), code)
    assert torch.isfinite(img).all()
    img.mean().backward()
    assert_finite_grads(r)


@pytest.mark.parametrize("feats", ["zeros", "huge"])
def test_degenerate_feature_maps(feats):
    f = torch.zeros(2, 32, 4, 4) if feats == "zeros" else torch.full((2, 32, 4, 4), 1e4)
    r = dit_renderer()
    out = r.training_forward(f, torch.randn(2, 144), torch.rand(2, 3, 16, 16), gaze=torch.zeros(2, 2),
                             pose=torch.zeros(2, 6))
    (out.image.mean() + out.aux_loss).backward()
    assert torch.isfinite(out.image).all()
    assert_finite_grads(r.dit)
    b = perturbed(BaselineRenderer())
    img = b(f, torch.randn(2, 144))
    img.sum().backward()
    assert torch.isfinite(img).all()
    assert_finite_grads(b)


def test_bf16_autocast_forward_backward_on_cpu():
    r = dit_renderer()
    b = perturbed(BaselineRenderer())
    f, c, gz, ps = torch.randn(2, 32, 4, 4), torch.randn(2, 144), torch.zeros(2, 2), torch.zeros(2, 6)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = r.training_forward(f, c, torch.rand(2, 3, 16, 16), gaze=gz, pose=ps)
        img_b = b(f, c)
        with torch.no_grad():
            inf = r.render(f, c, gaze=gz, pose=ps, steps=2)
    loss = out.image.float().mean() + out.aux_loss.float() + img_b.float().mean()
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(inf).all()
    assert_finite_grads(r.dit)
    assert_finite_grads(b)


def test_bf16_autoencoder_training_step():
    ae = perturbed(KLAutoencoder(AE), scale=0.01)
    x = torch.rand(2, 3, 16, 16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mean, logvar = ae.moments(x)
        recon = ae.decoder(mean)
    loss = (recon.float() - x).abs().mean() + logvar.float().mean()
    loss.backward()
    assert torch.isfinite(loss)
    assert_finite_grads(ae)


@pytest.mark.parametrize("cfg", [DiffusionConfig(), DiffusionConfig(prediction="eps", zero_terminal_snr=False)])
@pytest.mark.parametrize("t", [0, 1, 998, 999])
def test_extreme_timesteps(cfg, t):
    d = GaussianDiffusion(cfg)
    x0, noise = torch.randn(1, 4, 2, 2), torch.randn(1, 4, 2, 2)
    w = torch.ones((), requires_grad=True)
    out = d.training_step(lambda x, tt: w * x, x0, t=torch.tensor([t]), noise=noise)
    (out["loss"] + out["x0_pred"].sum()).backward()
    assert torch.isfinite(out["x0_pred"]).all() and torch.isfinite(w.grad)


def test_pixel_space_renderer_extreme_inputs():
    torch.manual_seed(0)
    dit = perturbed(make_dit("DiT-Gaze-tiny", input_size=8, latent_channels=3))
    r = DiTRenderer(dit, PixelCodec(), upscale=2)
    out = r.training_forward(torch.full((1, 32, 4, 4), -1e4), torch.full((1, 144), 1e9), torch.ones(1, 3, 8, 8))
    (out.image.sum() + out.aux_loss).backward()
    assert torch.isfinite(out.image).all()
    assert_finite_grads(r.dit)


def test_autoencoder_on_constant_images():
    ae, hist = train_autoencoder(torch.ones(4, 3, 8, 8), AE, steps=2, batch_size=2)
    assert all(math.isfinite(h) for h in hist)
    z = ae.encode(torch.ones(1, 3, 8, 8))
    assert math.isfinite(float(ae.scale_factor)) and torch.isfinite(ae.decode(z)).all()


def test_seeds_give_identical_models_and_renders():
    f, c = torch.randn(2, 32, 4, 4), torch.randn(2, 144)
    gz, ps = torch.zeros(2, 2), torch.zeros(2, 6)
    a, b = dit_renderer(seed=3), dit_renderer(seed=3)
    assert torch.equal(a.render(f, c, gaze=gz, pose=ps, steps=4, seed=5), b.render(f, c, gaze=gz, pose=ps, steps=4, seed=5))
    ta = a.training_forward(f, c, torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0)), gaze=gz,
                            pose=ps, generator=torch.Generator().manual_seed(1))
    tb = b.training_forward(f, c, torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0)), gaze=gz,
                            pose=ps, generator=torch.Generator().manual_seed(1))
    assert torch.equal(ta.image, tb.image) and torch.equal(ta.aux_loss, tb.aux_loss)
    assert not torch.equal(dit_renderer(seed=4).render(f, c, gaze=gz, pose=ps), a.render(f, c, gaze=gz, pose=ps))


@pytest.mark.parametrize("progress", [-1.0, 0.0, 1.0, 5.0])
def test_gaze_sampler_extremes(progress):
    s = GazeSampler(GazeSamplerConfig(mode="mixed", range_deg=89, progressive=True, grid_size=2, grid_fraction=1.0))
    gz = s.sample(1, progress)
    assert gz.shape == (1, 2) and torch.isfinite(gz).all() and gz.abs().max() <= math.radians(89) + 1e-6
    s2 = GazeSampler(GazeSamplerConfig(mode="biased_center", center_std=1e-6))
    assert torch.isfinite(s2.sample(64, progress)).all()
