"""Latent codecs for the DiT renderer: the Stable Diffusion VAE, the project's small KL autoencoder, pixels.

One interface, :class:`LatentCodec` (an ``nn.Module``):

* ``encode(image [B, 3, H, W] in [0, 1]) -> latent [B, C, H/f, W/f]``, scaled to roughly unit variance
  (the diffusion's assumption), deterministic (the posterior mean);
* ``decode(latent) -> image [B, 3, H, W]`` on the [0, 1] scale. Decoders do **not** clamp, so image losses
  on a decoded x0 estimate keep their gradients; renderers clamp at inference.
* ``latent_channels`` (C) and ``downsample`` (f) describe the latent grid; ``freeze()`` stops training
  the weights (gradients still flow through ``decode`` to the latent, which is how the DiT is trained).

Codecs: :class:`SDVAECodec` (diffusers ``AutoencoderKL`` from a local folder, 8x down, 4 channels, scaling
0.18215; optional extra ``sd-vae``), :class:`KLAutoencoder` (the project's own, trained by
:func:`train_autoencoder`, stored with :func:`save_autoencoder` as safetensors + JSON config) and
:class:`PixelCodec` (no codec: the "latent" is the image mapped to [-1, 1]). :func:`load_codec` picks one
from a user-facing spec.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.io import load_checkpoint, save_checkpoint

SD_VAE_SCALING = 0.18215  # Stable Diffusion v1's latent scale (Rombach et al., 2022)
LOGVAR_RANGE = (-30.0, 20.0)
INIT_LOGVAR = -6.0  # the posterior log-variance clamp of latent-diffusion's KL autoencoder


class LatentCodec(nn.Module):
    """Image <-> latent. Images are ``[B, 3, H, W]`` on the [0, 1] scale; latents ``[B, C, H/f, W/f]``."""

    latent_channels: int = 4
    downsample: int = 8

    def encode(self, image: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def freeze(self) -> "LatentCodec":
        """Stop training the weights and switch to eval mode; returns ``self``."""
        self.requires_grad_(False)
        return self.eval()

    def decoder_modules(self) -> list[nn.Module]:
        """The modules that map a latent to an image (what test-time fitting may tune); [] for no decoder."""
        return []

    def latent_size(self, height: int, width: int) -> tuple[int, int]:
        """Latent grid for an image size, or a ToolkitError when the size is not a multiple of ``downsample``."""
        f = self.downsample
        if height % f or width % f:
            raise ToolkitError(f"image size {height}x{width}: must be a multiple of the codec's downsample factor {f}")
        return height // f, width // f

    def _check_image(self, image: torch.Tensor) -> None:
        if image.dim() != 4 or image.shape[1] != 3:
            raise ToolkitError(f"codec encode: expected an image [B, 3, H, W], got {list(image.shape)}")
        self.latent_size(image.shape[2], image.shape[3])

    def _check_latent(self, latent: torch.Tensor) -> None:
        if latent.dim() != 4 or latent.shape[1] != self.latent_channels:
            raise ToolkitError(f"codec decode: expected a latent [B, {self.latent_channels}, h, w], got {list(latent.shape)}")


#################################################################################
#                               Pixel space (no codec)                          #
#################################################################################


class PixelCodec(LatentCodec):
    """The identity codec: latent = image mapped from [0, 1] to [-1, 1] (3 channels, no downsampling)."""

    latent_channels = 3
    downsample = 1

    def encode(self, image: torch.Tensor) -> torch.Tensor:
        self._check_image(image)
        return image * 2 - 1

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        self._check_latent(latent)
        return (latent + 1) * 0.5


#################################################################################
#                          The project's small KL autoencoder                   #
#################################################################################


@dataclass
class AutoencoderConfig:
    """A small KL-regularized convolutional autoencoder (latent-diffusion style, far fewer channels)."""

    downsample: int = 8
    """Spatial reduction factor, a power of two (one stride-2 stage per factor of two)."""
    latent_channels: int = 4
    base_channels: int = 32
    """Channels at full resolution; doubled per stage up to ``max_channels``."""
    max_channels: int = 128
    kl_weight: float = 1e-6
    """Weight of the KL term in training (small: the latent should mostly reconstruct)."""

    def validate(self) -> None:
        f = self.downsample
        if f < 1 or f & (f - 1):
            raise ToolkitError(f"AutoencoderConfig.downsample: expected a power of two, got {f}")
        for name in ("latent_channels", "base_channels", "max_channels"):
            if getattr(self, name) < 1:
                raise ToolkitError(f"AutoencoderConfig.{name}: expected a positive integer, got {getattr(self, name)}")

    def channels(self) -> list[int]:
        """Channels per stage, full resolution first: ``log2(downsample) + 1`` entries."""
        return [min(self.base_channels * 2**i, self.max_channels) for i in range(int(math.log2(self.downsample)) + 1)]


def _norm(ch: int) -> nn.GroupNorm:
    """GroupNorm with at least 4 channels per group (1-channel groups would be instance norm, which erases
    each image's per-channel brightness -- ruinous at the small widths used here), at most 32 groups."""
    groups = min(32, max(1, ch // 4))
    while ch % groups:
        groups -= 1
    return nn.GroupNorm(groups, ch, eps=1e-6)


class ResBlock(nn.Module):
    """Pre-activation residual block: (GroupNorm, SiLU, 3x3 conv) x 2 plus the identity."""

    def __init__(self, ch: int):
        super().__init__()
        self.norm1, self.conv1 = _norm(ch), nn.Conv2d(ch, ch, 3, padding=1)
        self.norm2, self.conv2 = _norm(ch), nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        return x + self.conv2(F.silu(self.norm2(h)))


class Encoder(nn.Module):
    """``[B, 3, H, W]`` in [-1, 1] -> posterior moments ``[B, 2C, H/f, W/f]`` (mean, log-variance)."""

    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        ch = cfg.channels()
        self.conv_in = nn.Conv2d(3, ch[0], 3, padding=1)
        self.stages = nn.ModuleList(
            nn.Sequential(ResBlock(ch[i]), nn.Conv2d(ch[i], ch[i + 1], 3, stride=2, padding=1)) for i in range(len(ch) - 1)
        )
        self.mid = ResBlock(ch[-1])
        self.norm_out = _norm(ch[-1])
        self.conv_out = nn.Conv2d(ch[-1], 2 * cfg.latent_channels, 3, padding=1)
        # Start with a narrow posterior (std ~0.05): unit-variance sampling noise would drown the untrained
        # means and stall reconstruction; the KL term widens it again where the decoder tolerates it.
        with torch.no_grad():
            self.conv_out.bias[cfg.latent_channels:].fill_(INIT_LOGVAR)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv_in(x)
        for stage in self.stages:
            x = stage(x)
        return self.conv_out(F.silu(self.norm_out(self.mid(x))))


class Decoder(nn.Module):
    """``[B, C, H/f, W/f]`` -> ``[B, 3, H, W]`` on the [-1, 1] scale (nearest upsampling + conv per stage)."""

    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        ch = cfg.channels()
        self.conv_in = nn.Conv2d(cfg.latent_channels, ch[-1], 3, padding=1)
        self.mid = ResBlock(ch[-1])
        self.stages = nn.ModuleList(
            nn.ModuleDict({"conv": nn.Conv2d(ch[i + 1], ch[i], 3, padding=1), "res": ResBlock(ch[i])})
            for i in reversed(range(len(ch) - 1))
        )
        self.norm_out = _norm(ch[0])
        self.conv_out = nn.Conv2d(ch[0], 3, 3, padding=1)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.mid(self.conv_in(z))
        for stage in self.stages:
            x = stage["res"](stage["conv"](F.interpolate(x, scale_factor=2.0, mode="nearest")))
        return self.conv_out(F.silu(self.norm_out(x)))


class KLAutoencoder(LatentCodec):
    """The project's own latent codec. ``encode`` returns ``scale_factor * posterior mean``."""

    def __init__(self, config: AutoencoderConfig | None = None):
        super().__init__()
        self.config = config or AutoencoderConfig()
        self.config.validate()
        self.latent_channels = self.config.latent_channels
        self.downsample = self.config.downsample
        self.encoder = Encoder(self.config)
        self.decoder = Decoder(self.config)
        # Set after training to 1/std of the latents (how SD's 0.18215 was chosen); saved in checkpoints.
        self.register_buffer("scale_factor", torch.tensor(1.0))

    def moments(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unscaled posterior ``(mean, logvar)``, each ``[B, C, H/f, W/f]``, of an image in [0, 1]."""
        self._check_image(image)
        mean, logvar = self.encoder(image * 2 - 1).chunk(2, dim=1)
        return mean, logvar.clamp(*LOGVAR_RANGE)

    def encode(self, image: torch.Tensor) -> torch.Tensor:
        return self.moments(image)[0] * self.scale_factor

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        self._check_latent(latent)
        return (self.decoder(latent / self.scale_factor) + 1) * 0.5

    def decoder_modules(self) -> list[nn.Module]:
        return [self.decoder]


def kl_divergence(mean: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """Mean per-element KL(N(mean, exp(logvar)) || N(0, 1))."""
    return 0.5 * (mean.pow(2) + logvar.exp() - 1 - logvar).mean()


def train_autoencoder(images: torch.Tensor, config: AutoencoderConfig | None = None, *, steps: int = 1000,
                      batch_size: int = 16, lr: float = 1e-3, seed: int = 0,
                      log: Callable[[int, dict[str, float]], None] | None = None,
                      model: KLAutoencoder | None = None,
                      pixel_weights: torch.Tensor | None = None,
                      device: str | torch.device | None = None) -> tuple[KLAutoencoder, list[float]]:
    """Train a :class:`KLAutoencoder` on ``images [N, 3, H, W]`` in [0, 1]; return it frozen and the losses.

    Loss: L1 reconstruction (weighted by ``pixel_weights [N, 1, H, W]`` >= 0 when given, normalized by the
    batch's total weight: see :func:`eye_weights`) + ``kl_weight`` * KL, Adam. Afterwards ``scale_factor`` is set to 1 / std of the
    posterior means over (up to 256 of) the images (std floored at 1e-3), so encoded latents have unit variance for the diffusion.
    Pass ``model`` to continue training an existing one. ``device``: where to train (default: the model's, CPU
    for a new one); ``images`` may stay on the CPU, batches move as they are drawn. Deterministic given ``seed``
    (on CPU; the weights are initialized on the CPU, so a CUDA run starts from the same ones).
    """
    if images.dim() != 4 or images.shape[1] != 3 or images.shape[0] == 0:
        raise ToolkitError(f"train_autoencoder images: expected [N>0, 3, H, W] in [0, 1], got {list(images.shape)}")
    # rows streamed from subject files (train.data.rows.RowImages) were checked when their files were read
    in_memory = isinstance(images, torch.Tensor)
    if in_memory and not torch.isfinite(images).all():
        raise ToolkitError("train_autoencoder images: contain NaN or infinite values")
    if pixel_weights is not None:
        if tuple(pixel_weights.shape) != (images.shape[0], 1, *images.shape[2:]):
            raise ToolkitError(f"train_autoencoder pixel_weights: expected shape {[images.shape[0], 1, *images.shape[2:]]}, "
                               f"got {list(pixel_weights.shape)}")
        if isinstance(pixel_weights, torch.Tensor) and (not torch.isfinite(pixel_weights).all()
                                                        or bool((pixel_weights < 0).any())):
            raise ToolkitError("train_autoencoder pixel_weights: expected finite weights >= 0 (found NaN, inf or < 0)")
    if steps < 0 or batch_size < 1:
        raise ToolkitError(f"train_autoencoder: expected steps >= 0 and batch_size >= 1, got {steps}, {batch_size}")
    g = torch.Generator().manual_seed(seed)
    if model is None:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model = KLAutoencoder(config)
    if device is not None:
        model = model.to(device)
    # Channels-last (NHWC) activations and weights: oneDNN's convolutions run ~1.4x faster in that layout
    # on CPU (a demo-size step: 0.61 -> 0.45 s). The model goes back to the default layout at the end.
    model.requires_grad_(True).train().to(memory_format=torch.channels_last)
    device = next(model.parameters()).device
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    history: list[float] = []
    for step in range(steps):
        idx = torch.randint(0, images.shape[0], (min(batch_size, images.shape[0]),), generator=g)
        x = images[idx].to(device).contiguous(memory_format=torch.channels_last)
        mean, logvar = model.moments(x)
        z = mean + torch.randn(mean.shape, generator=g).to(device) * (0.5 * logvar).exp()
        recon = (model.decoder(z) + 1) * 0.5
        if pixel_weights is None:
            rec = F.l1_loss(recon, x)
        else:
            w = pixel_weights[idx].to(device)
            rec = ((recon - x).abs() * w).sum() / (3 * w.sum()).clamp_min(1e-8)
        loss = rec + model.config.kl_weight * kl_divergence(mean, logvar)
        if not torch.isfinite(loss):  # never a silent NaN codec: the renderer would train on NaN latents
            raise ToolkitError(f"train_autoencoder: non-finite loss at step {step} (reconstruction {rec.detach().item():.4g}, "
                               f"total {loss.detach().item():.4g}); nothing was saved: check the images for NaN, or lower "
                               "the learning rate")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        history.append(rec.item())
        if log is not None:
            log(step, {"recon_l1": rec.item(), "loss": loss.item()})
    model.to(memory_format=torch.contiguous_format)
    with torch.no_grad():
        model.eval()
        sample = images[:256].to(device)
        std = torch.cat([model.moments(sample[i:i + 32])[0] for i in range(0, sample.shape[0], 32)]).std()
        model.scale_factor.fill_(float(1.0 / std.clamp(min=1e-3)) if torch.isfinite(std) else 1.0)
    return model.freeze(), history


def eye_weights(eye_masks: torch.Tensor, eye_weight: float, dilate: int = 2) -> torch.Tensor:
    """Per-pixel reconstruction weights ``1 + eye_weight * eyes`` [N, 1, H, W] from eye masks [N, 1, H, W] in
    [0, 1], the masks dilated by ``dilate`` pixels (max-pool) so the lids and the eye's outline count too."""
    from train.losses.metrics import dilate_mask

    return 1.0 + eye_weight * dilate_mask(eye_masks, dilate)


def save_autoencoder(path: str | Path, model: KLAutoencoder, info: dict | None = None) -> None:
    """Write a :class:`KLAutoencoder` as safetensors with its config and scale factor in the JSON metadata."""
    meta = {**(info or {}), "kind": "kl_autoencoder", "config": asdict(model.config),
            "scale_factor": float(model.scale_factor)}
    save_checkpoint(path, model.state_dict(), meta)


def load_autoencoder(path: str | Path, device: str | torch.device = "cpu") -> KLAutoencoder:
    """Read a :func:`save_autoencoder` file -> a frozen :class:`KLAutoencoder`."""
    state, info = load_checkpoint(path, device)
    if info.get("kind") != "kl_autoencoder" or not isinstance(info.get("config"), dict):
        raise ToolkitError(f"{path}: not a KL autoencoder checkpoint (metadata 'kind' is {info.get('kind')!r})")
    known = {f.name for f in fields(AutoencoderConfig)}
    unknown = set(info["config"]) - known
    if unknown:
        raise ToolkitError(f"{path}: unknown autoencoder config fields {sorted(unknown)}")
    model = KLAutoencoder(AutoencoderConfig(**info["config"])).to(device)
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        raise ToolkitError(f"{path}: weights do not match the stored config ({str(e).splitlines()[0][:160]})") from None
    return model.freeze()


#################################################################################
#                        Stable Diffusion VAE (optional extra)                  #
#################################################################################


class SDVAECodec(LatentCodec):
    """The frozen Stable Diffusion ``AutoencoderKL`` loaded with diffusers from a local folder (no download).

    The folder is the ``vae/`` of an SD checkpoint: ``config.json`` plus the weights. 8x down, 4 channels;
    latents are the posterior mean times the VAE's ``scaling_factor`` (0.18215 for SD 1.x).
    """

    latent_channels = 4
    downsample = 8

    def __init__(self, path: str | Path, dtype: torch.dtype = torch.float32):
        super().__init__()
        path = Path(path)
        if not path.is_dir():
            raise ToolkitError(f"{path}: no such directory; expected a local Stable Diffusion VAE folder (config.json + weights)")
        if not (path / "config.json").is_file():
            raise ToolkitError(f"{path}: missing config.json; expected a diffusers AutoencoderKL folder")
        if not any(path.glob("*.safetensors")):
            # A .bin checkpoint is a pickle, which can run code when loaded: only safetensors weights are read.
            raise ToolkitError(f"{path}: no .safetensors weights (e.g. diffusion_pytorch_model.safetensors); pickled "
                               f".bin checkpoints are not loaded -- convert them to safetensors first")
        try:
            from diffusers import AutoencoderKL
        except ImportError:
            raise ToolkitError("Stable Diffusion VAE: the optional package 'diffusers' is not installed "
                               "(pip install 'ditgaze[sd-vae]')") from None
        try:
            self.vae = AutoencoderKL.from_pretrained(str(path), torch_dtype=dtype, local_files_only=True,
                                                     use_safetensors=True)
        except Exception as e:  # diffusers raises OSError/ValueError/... for incomplete folders
            raise ToolkitError(f"{path}: could not load a diffusers AutoencoderKL ({type(e).__name__}: {str(e)[:160]})") from None
        self.scaling = float(getattr(getattr(self.vae, "config", None), "scaling_factor", None) or SD_VAE_SCALING)
        self.freeze()

    def encode(self, image: torch.Tensor) -> torch.Tensor:
        self._check_image(image)
        x = (image * 2 - 1).to(self.vae.dtype)
        return self.vae.encode(x).latent_dist.mean.float() * self.scaling

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        self._check_latent(latent)
        out = self.vae.decode((latent / self.scaling).to(self.vae.dtype)).sample
        return (out.float() + 1) * 0.5

    def decoder_modules(self) -> list[nn.Module]:
        return [m for m in (getattr(self.vae, "post_quant_conv", None), self.vae.decoder) if m is not None]


def load_codec(spec: str | Path, device: str | torch.device = "cpu") -> LatentCodec:
    """A frozen codec from a spec: ``"pixel"``, a ``.safetensors`` KL autoencoder file, or an SD VAE folder."""
    if str(spec) == "pixel":
        return PixelCodec().to(device)
    path = Path(spec)
    if path.is_dir():
        return SDVAECodec(path).to(device)
    if path.suffix == ".safetensors":
        return load_autoencoder(path, device)
    raise ToolkitError(f"codec {spec!r}: expected 'pixel', a .safetensors autoencoder file or a Stable Diffusion VAE folder")
