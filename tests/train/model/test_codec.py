"""Latent codecs: pixel identity, the project's KL autoencoder (training, scale, I/O), the SD VAE wrapper."""

from __future__ import annotations

import sys
import types

import pytest
import torch

from tests.train.threads import single_thread  # noqa: F401  (autouse)
from toolkit import ToolkitError
from toolkit.io import save_checkpoint
from train.model.codec import (
    SD_VAE_SCALING,
    AutoencoderConfig,
    KLAutoencoder,
    PixelCodec,
    SDVAECodec,
    eye_weights,
    load_autoencoder,
    load_codec,
    save_autoencoder,
    train_autoencoder,
)

TINY = AutoencoderConfig(downsample=4, base_channels=8, max_channels=16, latent_channels=4)


def smooth_images(n: int, size: int = 16, seed: int = 0) -> torch.Tensor:
    """Low-frequency colour images in [0, 1]: sums of a few random 2D cosines per channel."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    freq = torch.randint(0, 2, (n, 3, 2, 2), generator=g).float()
    phase = torch.rand(n, 3, 2, generator=g) * 6.28
    img = sum(torch.cos(6.28 * (freq[:, :, k, 0, None, None] * xx + freq[:, :, k, 1, None, None] * yy)
                        + phase[:, :, k, None, None]) for k in range(2))
    return (0.5 + 0.2 * img).clamp(0, 1)


@pytest.fixture(scope="module")
def trained():
    images = smooth_images(512)
    model, history = train_autoencoder(images, TINY, steps=100, batch_size=8, lr=1e-2, seed=0)
    return images, model, history


def test_pixel_codec_round_trip():
    codec = PixelCodec()
    img = torch.rand(2, 3, 8, 8)
    z = codec.encode(img)
    assert z.shape == img.shape and z.min() >= -1 and z.max() <= 1
    assert torch.equal(codec.decode(z), img)
    assert (codec.latent_channels, codec.downsample) == (3, 1)


@pytest.mark.parametrize("f", [1, 2, 4, 8])
def test_autoencoder_shapes(f):
    ae = KLAutoencoder(AutoencoderConfig(downsample=f, base_channels=8, max_channels=16))
    img = torch.rand(2, 3, 16, 24)
    z = ae.encode(img)
    assert z.shape == (2, 4, 16 // f, 24 // f)
    assert ae.decode(z).shape == img.shape
    assert len(AutoencoderConfig(downsample=f).channels()) == {1: 1, 2: 2, 4: 3, 8: 4}[f]


def test_training_reduces_reconstruction_error(trained):
    images, model, history = trained
    held_out = smooth_images(16, seed=1)
    fresh = KLAutoencoder(TINY)
    with torch.no_grad():
        before = (fresh.decode(fresh.encode(held_out)) - held_out).abs().mean()
        after = (model.decode(model.encode(held_out)) - held_out).abs().mean()
    mean_predictor = (held_out - images.mean()).abs().mean()  # what a model that ignores its input scores
    assert after < 0.6 * before and after < 0.75 * mean_predictor, (float(before), float(after), float(mean_predictor))
    assert sum(history[-10:]) < 0.7 * sum(history[:10])


def test_scale_factor_gives_unit_variance_latents(trained):
    images, model, _ = trained
    z = model.encode(images)
    assert model.scale_factor != 1.0
    assert z.std().item() == pytest.approx(1.0, rel=0.05)


def test_frozen_but_differentiable_through_decode(trained):
    _, model, _ = trained
    assert not any(p.requires_grad for p in model.parameters()) and not model.training
    z = torch.randn(1, 4, 4, 4, requires_grad=True)
    model.decode(z).mean().backward()
    assert z.grad is not None and z.grad.abs().sum() > 0


def test_training_is_deterministic_from_seed():
    images = smooth_images(8)
    _, h1 = train_autoencoder(images, TINY, steps=3, batch_size=4, seed=5)
    _, h2 = train_autoencoder(images, TINY, steps=3, batch_size=4, seed=5)
    assert h1 == h2


def test_save_load_round_trip(trained, tmp_path):
    images, model, _ = trained
    path = tmp_path / "ae.safetensors"
    save_autoencoder(path, model, info={"step": 60})
    loaded = load_codec(path)
    assert isinstance(loaded, KLAutoencoder) and float(loaded.scale_factor) == float(model.scale_factor)
    assert torch.equal(loaded.decode(loaded.encode(images[:2])), model.decode(model.encode(images[:2])))
    assert not any(p.requires_grad for p in loaded.parameters())


def test_load_errors(tmp_path):
    other = tmp_path / "other.safetensors"
    save_checkpoint(other, {"w": torch.zeros(2)}, {"kind": "dit"})
    with pytest.raises(ToolkitError, match="not a KL autoencoder"):
        load_autoencoder(other)
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"not safetensors at all")
    with pytest.raises(ToolkitError, match="garbage.safetensors"):
        load_codec(garbage)
    wrong = tmp_path / "wrong.safetensors"
    save_checkpoint(wrong, KLAutoencoder(TINY).state_dict(),
                    {"kind": "kl_autoencoder", "config": {**TINY.__dict__, "base_channels": 16}})
    with pytest.raises(ToolkitError, match="do not match"):
        load_autoencoder(wrong)
    with pytest.raises(ToolkitError, match="expected 'pixel'"):
        load_codec(tmp_path / "missing.ckpt")
    with pytest.raises(ToolkitError, match="no such"):
        load_codec(tmp_path / "missing.safetensors")


def test_eye_weights_dilate_the_mask():
    m = torch.zeros(1, 1, 9, 9)
    m[0, 0, 4, 4] = 1
    w = eye_weights(m, 10.0, dilate=1)
    assert w.shape == m.shape and float(w.sum()) == 81 + 9 * 10.0
    assert w[0, 0, 3:6, 3:6].eq(11).all() and w[0, 0, 0, 0] == 1


def test_pixel_weights_buy_detail_where_they_are_high():
    """A small patch with a dark dot at a varying place (a pupil in the eye of a face crop) on smooth images:
    weighting the patch makes the codec reconstruct it better than the plain L1 does in the same steps."""
    images = smooth_images(256, seed=3)
    g = torch.Generator().manual_seed(4)
    images[:, :, 4:8, 4:8] = 0.9
    for i, (r, c) in enumerate(torch.randint(0, 3, (256, 2), generator=g).tolist()):
        images[i, :, 4 + r:6 + r, 4 + c:6 + c] = 0.1
    region = torch.zeros(256, 1, 16, 16)
    region[:, :, 4:8, 4:8] = 1
    errors = []
    for weights in (None, eye_weights(region, 100.0, dilate=0)):
        model, _ = train_autoencoder(images, TINY, steps=100, batch_size=8, lr=3e-3, seed=0, pixel_weights=weights)
        with torch.no_grad():
            rec = model.decode(model.encode(images[:64]))
        errors.append(float((rec - images[:64]).abs()[:, :, 4:8, 4:8].mean()))
    assert errors[1] < 0.8 * errors[0], errors


def test_bad_inputs():
    ae = KLAutoencoder(TINY)
    with pytest.raises(ToolkitError, match="multiple of"):
        ae.encode(torch.rand(1, 3, 10, 16))
    with pytest.raises(ToolkitError, match="image"):
        ae.encode(torch.rand(1, 4, 16, 16))
    with pytest.raises(ToolkitError, match="latent"):
        ae.decode(torch.rand(1, 3, 4, 4))
    with pytest.raises(ToolkitError, match="power of two"):
        AutoencoderConfig(downsample=6).validate()
    with pytest.raises(ToolkitError, match="NaN"):
        train_autoencoder(torch.full((2, 3, 8, 8), float("nan")), TINY, steps=1)
    for bad, msg in ((torch.ones(2, 1, 8, 4), "pixel_weights: expected shape"),
                     (torch.full((2, 1, 8, 8), -1.0), "pixel_weights: expected finite weights >= 0"),
                     (torch.full((2, 1, 8, 8), float("inf")), "pixel_weights: expected finite weights >= 0")):
        with pytest.raises(ToolkitError, match=msg):
            train_autoencoder(torch.rand(2, 3, 8, 8), TINY, steps=1, pixel_weights=bad)


def test_sd_vae_missing_path_and_missing_diffusers(tmp_path, monkeypatch):
    with pytest.raises(ToolkitError, match="no such directory"):
        SDVAECodec(tmp_path / "nope")
    with pytest.raises(ToolkitError, match="config.json"):
        SDVAECodec(tmp_path)
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "diffusion_pytorch_model.bin").write_bytes(b"a pickle")
    with pytest.raises(ToolkitError, match="no .safetensors weights"):  # never unpickled
        SDVAECodec(tmp_path)
    (tmp_path / "diffusion_pytorch_model.safetensors").write_bytes(b"")
    monkeypatch.setitem(sys.modules, "diffusers", None)  # import diffusers -> ImportError
    with pytest.raises(ToolkitError, match="diffusers"):
        load_codec(tmp_path)


def test_sd_vae_wrapper_scaling_and_range(tmp_path, monkeypatch):
    """With a stand-in for diffusers' AutoencoderKL: [0,1] <-> [-1,1], 8x down, latents times 0.18215."""
    class FakeVAE(torch.nn.Module):
        dtype = torch.float32
        config = types.SimpleNamespace(scaling_factor=None)

        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(()))
            self.seen = None

        @classmethod
        def from_pretrained(cls, path, torch_dtype=None, local_files_only=False, use_safetensors=None):
            assert local_files_only and use_safetensors  # never a download, never a pickle
            return cls()

        def encode(self, x):
            self.seen = x
            mean = torch.nn.functional.avg_pool2d(x, 8).repeat(1, 2, 1, 1)[:, :4] * self.w
            return types.SimpleNamespace(latent_dist=types.SimpleNamespace(mean=mean))

        def decode(self, z):
            return types.SimpleNamespace(sample=torch.nn.functional.interpolate(z[:, :3], scale_factor=8.0))

    monkeypatch.setitem(sys.modules, "diffusers", types.SimpleNamespace(AutoencoderKL=FakeVAE))
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "diffusion_pytorch_model.safetensors").write_bytes(b"")
    codec = SDVAECodec(tmp_path)
    assert not any(p.requires_grad for p in codec.parameters())
    img = torch.full((1, 3, 16, 16), 0.75)
    z = codec.encode(img)
    assert codec.vae.seen.min() == pytest.approx(0.5)  # the VAE saw [-1, 1]
    assert z.shape == (1, 4, 2, 2) and torch.allclose(z, torch.full_like(z, 0.5 * SD_VAE_SCALING))
    torch.testing.assert_close(codec.decode(z), img)


def test_sd_vae_real_diffusers_folder_round_trip(tmp_path):
    """The real diffusers AutoencoderKL, SD's architecture (4 blocks: 8x down, 4 latent channels) at tiny
    widths, saved with save_pretrained and read back through SDVAECodec: the exact code path a user's
    local ``vae/`` folder takes (no hub)."""
    diffusers = pytest.importorskip("diffusers")
    torch.manual_seed(0)
    vae = diffusers.AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, layers_per_block=1, norm_num_groups=4,
        down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(4, 8, 8, 8), scaling_factor=SD_VAE_SCALING)
    vae.save_pretrained(tmp_path / "vae")
    codec = load_codec(tmp_path / "vae")
    assert isinstance(codec, SDVAECodec) and codec.scaling == pytest.approx(SD_VAE_SCALING)
    assert not any(p.requires_grad for p in codec.parameters())
    img = torch.rand(2, 3, 32, 32)
    z = codec.encode(img)
    assert z.shape == (2, 4, 4, 4) and torch.isfinite(z).all()
    with torch.no_grad():
        mean = vae.encode(img * 2 - 1).latent_dist.mean
    torch.testing.assert_close(z, mean * SD_VAE_SCALING)
    out = codec.decode(z)
    assert out.shape == img.shape and torch.isfinite(out).all()
    (tmp_path / "vae" / "diffusion_pytorch_model.safetensors").write_bytes(b"truncated")
    with pytest.raises(ToolkitError, match="could not load"):
        SDVAECodec(tmp_path / "vae")


def test_a_diverging_autoencoder_stops_naming_the_step():
    """Never a silent NaN codec: a non-finite loss mid-training (here from weights already NaN) stops it."""
    model = KLAutoencoder(TINY)
    with torch.no_grad():
        next(model.decoder.parameters()).fill_(float("nan"))
    with pytest.raises(ToolkitError, match=r"train_autoencoder: non-finite loss at step 0 \(reconstruction nan"):
        train_autoencoder(torch.rand(4, 3, 16, 16), TINY, steps=2, batch_size=2, model=model)
