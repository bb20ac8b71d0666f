"""The neural renderer interface and the latent DiT renderer behind it.

A renderer turns the splatted feature map of the two-stream Gaussian model into the output image:

* ``render(feats [B, F, h, w], shape_code [B, 144], *, gaze=None, pose=None, steps=None, seed=0)``
  -> image ``[B, 3, h * upscale, w * upscale]`` in [0, 1] (clamped) -- inference;
* ``training_forward(feats, shape_code, target [B, 3, H, W], *, gaze=None, pose=None, generator=None)``
  -> :class:`RenderOutput` with the differentiable image the image/gaze losses compare (unclamped, [0, 1]
  scale) and the renderer's own auxiliary loss (the diffusion loss for the DiT, 0 for the baseline).

:class:`DiTRenderer`: encode the target with the frozen codec, noise it at a random timestep, run the DiT
with the features and codes, take the x0 estimate, decode it (training); at inference run DDIM from seeded
noise with K steps (K = 1 is the deterministic one-step path) and decode. The baseline (GazeGaussian's
renderer) is :class:`train.baseline_renderer.BaselineRenderer`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import torch
import torch.nn as nn

from toolkit.errors import ToolkitError
from train.codec import LatentCodec
from train.diffusion import DiffusionConfig, GaussianDiffusion
from train.dit import DiT


@dataclass
class RenderOutput:
    """What a renderer's training pass gives the losses."""

    image: torch.Tensor
    """``[B, 3, H, W]`` on the [0, 1] scale, unclamped, differentiable."""
    aux_loss: torch.Tensor
    """Scalar loss the renderer adds by itself (DiT: diffusion MSE; baseline: 0)."""
    extras: dict[str, torch.Tensor] = field(default_factory=dict)
    """Inspection values (DiT: ``t``, ``latent_pred``, ``latent_target``)."""


@runtime_checkable
class Renderer(Protocol):
    """Splatted features + codes -> image. ``upscale`` = output size / feature-map size."""

    upscale: int

    def render(self, feats: torch.Tensor, shape_code: torch.Tensor, *, gaze: torch.Tensor | None = None,
               pose: torch.Tensor | None = None, steps: int | None = None, seed: int = 0) -> torch.Tensor: ...

    def training_forward(self, feats: torch.Tensor, shape_code: torch.Tensor, target: torch.Tensor, *,
                         gaze: torch.Tensor | None = None, pose: torch.Tensor | None = None,
                         generator: torch.Generator | None = None) -> RenderOutput: ...


def check_render_inputs(feats: torch.Tensor, shape_code: torch.Tensor, feature_channels: int, shape_dim: int) -> None:
    """ToolkitError unless ``feats [B, F, h, w]`` and ``shape_code [B, S]`` have the expected sizes."""
    if feats.dim() != 4 or feats.shape[1] != feature_channels:
        raise ToolkitError(f"renderer feats: expected [B, {feature_channels}, h, w], got {list(feats.shape)}")
    if shape_code.dim() != 2 or shape_code.shape != (feats.shape[0], shape_dim):
        raise ToolkitError(f"renderer shape_code: expected [{feats.shape[0]}, {shape_dim}], got {list(shape_code.shape)}")


class DiTRenderer(nn.Module):
    """The DiT-Gaze renderer: features -> (DiT + DDIM in the codec's latent space) -> decoded image.

    ``upscale`` is output size / feature size (4 in GazeGaussian); the latent grid is then
    ``h * upscale / codec.downsample``. ``default_steps`` is the DDIM step count of ``render``.
    The codec is frozen here: only the DiT trains, gradients reach it through ``codec.decode``.
    """

    def __init__(self, dit: DiT, codec: LatentCodec, diffusion: GaussianDiffusion | None = None, *,
                 upscale: int = 4, default_steps: int = 1):
        super().__init__()
        if dit.config.latent_channels != codec.latent_channels:
            raise ToolkitError(f"DiTRenderer: DiT latent_channels={dit.config.latent_channels} but the codec "
                               f"has {codec.latent_channels}")
        self.dit = dit
        self.codec = codec.freeze()
        self.diffusion = diffusion or GaussianDiffusion(DiffusionConfig())
        self.upscale = upscale
        self.default_steps = default_steps

    def latent_shape(self, feats: torch.Tensor) -> tuple[int, int, int, int]:
        H, W = feats.shape[2] * self.upscale, feats.shape[3] * self.upscale
        h, w = self.codec.latent_size(H, W)
        return feats.shape[0], self.codec.latent_channels, h, w

    def _model_fn(self, feats, shape_code, gaze, pose, latent_hw: tuple[int, int]):
        # The feature map is the same at every sampling step: encode it once.
        emb = self.dit.encode_features(feats, latent_hw)
        return lambda x, t: self.dit(x, t, feats, shape_code, gaze, pose, feature_embedding=emb)

    def training_forward(self, feats: torch.Tensor, shape_code: torch.Tensor, target: torch.Tensor, *,
                         gaze: torch.Tensor | None = None, pose: torch.Tensor | None = None,
                         generator: torch.Generator | None = None, t: torch.Tensor | None = None) -> RenderOutput:
        check_render_inputs(feats, shape_code, self.dit.config.feature_channels, self.dit.config.shape_dim)
        B, C, h, w = self.latent_shape(feats)
        if target.shape != (B, 3, h * self.codec.downsample, w * self.codec.downsample):
            raise ToolkitError(f"DiTRenderer target: expected [{B}, 3, {h * self.codec.downsample}, "
                               f"{w * self.codec.downsample}] (features x {self.upscale}), got {list(target.shape)}")
        with torch.no_grad():
            x0 = self.codec.encode(target).float()
        out = self.diffusion.training_step(self._model_fn(feats, shape_code, gaze, pose, (h, w)), x0, t=t,
                                          generator=generator)
        image = self.codec.decode(out["x0_pred"])
        return RenderOutput(image=image, aux_loss=out["loss"],
                            extras={"t": out["t"], "latent_pred": out["x0_pred"], "latent_target": x0})

    def render(self, feats: torch.Tensor, shape_code: torch.Tensor, *, gaze: torch.Tensor | None = None,
               pose: torch.Tensor | None = None, steps: int | None = None, seed: int = 0,
               noise: torch.Tensor | None = None, eta: float = 0.0) -> torch.Tensor:
        """DDIM with ``steps`` (default ``default_steps``) from ``noise`` or from noise drawn with ``seed``."""
        check_render_inputs(feats, shape_code, self.dit.config.feature_channels, self.dit.config.shape_dim)
        shape = self.latent_shape(feats)
        g = torch.Generator().manual_seed(seed)
        if noise is None:
            noise = torch.randn(shape, generator=g)
        elif tuple(noise.shape) != shape:
            raise ToolkitError(f"DiTRenderer noise: expected {list(shape)}, got {list(noise.shape)}")
        model_fn = self._model_fn(feats, shape_code, gaze, pose, shape[2:])
        latent = self.diffusion.ddim_sample(model_fn, noise.to(feats.device), steps or self.default_steps, eta=eta,
                                            generator=g)
        return self.codec.decode(latent).clamp(0, 1)

    def forward(self, feats: torch.Tensor, shape_code: torch.Tensor, gaze: torch.Tensor | None = None,
                pose: torch.Tensor | None = None) -> torch.Tensor:
        return self.render(feats, shape_code, gaze=gaze, pose=pose)


def make_renderer(kind: str, codec: LatentCodec | None = None, *, model: str = "DiT-Gaze-tiny",
                  output_size: int = 128, upscale: int = 4, diffusion: DiffusionConfig | None = None,
                  **model_kw) -> nn.Module:
    """``"dit"`` (needs a codec) or ``"baseline"``; ``model_kw`` go to the DiT config / baseline config."""
    if kind == "dit":
        from train.dit import make_dit

        if codec is None:
            raise ToolkitError("make_renderer('dit'): a latent codec is required (see train.codec.load_codec)")
        grid = output_size // codec.downsample
        dit = make_dit(model, input_size=grid, latent_channels=codec.latent_channels, **model_kw)
        return DiTRenderer(dit, codec, GaussianDiffusion(diffusion), upscale=upscale)
    if kind == "baseline":
        from train.baseline_renderer import BaselineConfig, BaselineRenderer

        return BaselineRenderer(BaselineConfig(upscale=upscale, **model_kw))
    raise ToolkitError(f"renderer kind: expected 'dit' or 'baseline', got {kind!r}")
