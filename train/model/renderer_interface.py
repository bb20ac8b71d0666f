"""The neural renderer interface every renderer implements (the DiT renderer and the baseline).

A renderer turns the splatted feature map of the two-stream Gaussian model into the output image:

* ``render(feats [B, F, h, w], shape_code [B, C], *, gaze=None, pose=None, steps=None, seed=0)``
  -> image ``[B, 3, h * upscale, w * upscale]`` in [0, 1] (clamped) -- inference;
* ``training_forward(feats, shape_code, target [B, 3, H, W], *, gaze=None, pose=None, generator=None, t=None)``
  -> :class:`RenderOutput` with the differentiable image the image/gaze losses compare (unclamped, [0, 1]
  scale) and the renderer's own auxiliary loss (the diffusion loss for the DiT, 0 for the baseline).
  ``t`` [B] fixes the diffusion timesteps (None: sampled); renderers without diffusion ignore it.

The implementations: :class:`train.model.renderer.DiTRenderer` and
:class:`train.model.baseline_renderer.BaselineRenderer`; :func:`train.model.renderer.make_renderer` builds
either by name. This module imports neither, so both can import it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import torch

from toolkit.errors import ToolkitError


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
                         generator: torch.Generator | None = None, t: torch.Tensor | None = None) -> RenderOutput: ...


def check_render_inputs(feats: torch.Tensor, shape_code: torch.Tensor, feature_channels: int, shape_dim: int) -> None:
    """ToolkitError unless ``feats [B, F, h, w]`` and ``shape_code [B, S]`` have the expected sizes."""
    if feats.dim() != 4 or feats.shape[1] != feature_channels or feats.shape[2] < 1 or feats.shape[3] < 1:
        raise ToolkitError(f"renderer feats: expected [B, {feature_channels}, h >= 1, w >= 1], got {list(feats.shape)}")
    if shape_code.dim() != 2 or shape_code.shape != (feats.shape[0], shape_dim):
        raise ToolkitError(f"renderer shape_code: expected [{feats.shape[0]}, {shape_dim}], got {list(shape_code.shape)}")


def check_finite_inputs(**tensors: torch.Tensor | None) -> None:
    """ToolkitError naming the first of ``tensors`` (name=tensor; None skipped) that holds NaN or inf values;
    one device sync for all of them."""
    given = {k: v for k, v in tensors.items() if v is not None and v.is_floating_point()}
    if not given:
        return
    device = next(iter(given.values())).device
    flags = torch.stack([torch.isfinite(v).all().to(device) for v in given.values()])
    if bool(flags.all()):
        return
    bad = next(k for k, ok in zip(given, flags.tolist()) if not ok)
    raise ToolkitError(f"renderer {bad}: expected finite values, found NaN or inf")
