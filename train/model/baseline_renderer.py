"""GazeGaussian's expression-guided neural renderer, kept as the ablation baseline of the DiT renderer.

Structure (GazeGaussian, after the progressive RGB renderer of Gaussian Head Avatar / GIRAFFE):
``log2(upscale)`` blocks, each ``PixelShuffleUpsample`` (3x3 conv to 4C, pixel shuffle x2, [1 2 1] blur) ->
1x1 conv -> LeakyReLU(0.2) -> attention pooling over the shape code; an RGB skip path adds a 1x1 "to-RGB"
of every block to the bilinearly upsampled, blurred RGB of the previous one; sigmoid at the end.

Attention pooling: each pixel's feature gives a key ``[S]`` (S = shape-code size) and a value ``[C]``; the
shape code is the single query; softmax over all pixels of ``key . code / sqrt(S)`` weights the values, and
the pooled ``[C]`` vector is added to every pixel. Unlike the reference, each block has its own key/value
projections sized to its channels (the reference shares one sized for ``min_feat`` only). Codes pass through
the same soft saturation as the DiT's.

Gaze and pose are accepted for interface parity and ignored (the GazeGaussian renderer sees only the shape
code); ``steps`` and ``seed`` are ignored too (one deterministic pass).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from train.model.dit_conditioning import saturate_codes
from train.model.renderer_interface import RenderOutput, check_finite_inputs, check_render_inputs


@dataclass
class BaselineConfig:
    """GazeGaussian's renderer sizes (its defaults: 32-channel features at 1/4 of the output)."""

    feature_channels: int = 32
    upscale: int = 4
    """Output size / feature-map size, a power of two (one upsampling block per factor of two)."""
    min_channels: int = 32
    """Channels halve per block down to this floor (as in the reference)."""
    shape_dim: int = 144
    """Identity + expression code size: the Gaussian model's ``code_dim``, the data's."""

    def validate(self) -> None:
        u = self.upscale
        if u < 1 or u & (u - 1):
            raise ToolkitError(f"BaselineConfig.upscale: expected a power of two, got {u}")
        for name in ("feature_channels", "min_channels", "shape_dim"):
            if getattr(self, name) < 1:
                raise ToolkitError(f"BaselineConfig.{name}: expected a positive integer, got {getattr(self, name)}")


def blur(x: torch.Tensor) -> torch.Tensor:
    """Depthwise [1 2 1] x [1 2 1] / 16 blur with reflect padding (anti-aliases the upsampling)."""
    k = torch.tensor([1.0, 2.0, 1.0], device=x.device, dtype=x.dtype)
    k = (k[:, None] * k[None, :] / 16).expand(x.shape[1], 1, 3, 3)
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="reflect"), k, groups=x.shape[1])


class PixelShuffleUpsample(nn.Module):
    """``[B, C, h, w]`` -> ``[B, C, 2h, 2w]``: 3x3 conv to 4C, pixel shuffle, blur."""

    def __init__(self, ch: int):
        super().__init__()
        self.conv = nn.Conv2d(ch, 4 * ch, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return blur(F.pixel_shuffle(self.conv(x), 2))


class AttentionPool(nn.Module):
    """Adds to every pixel the shape-code-queried softmax average of the pixel values."""

    def __init__(self, ch: int, code_dim: int):
        super().__init__()
        self.k_proj = nn.Linear(ch, code_dim)
        self.v_proj = nn.Linear(ch, ch)
        self.scale = 1.0 / math.sqrt(code_dim)

    def forward(self, x: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        tokens = x.flatten(2).transpose(1, 2)  # [B, hw, C]
        scores = torch.einsum("bnd,bd->bn", self.k_proj(tokens), code.to(x.dtype)) * self.scale
        pooled = torch.einsum("bn,bnc->bc", scores.softmax(dim=1), self.v_proj(tokens))
        return x + pooled[:, :, None, None]


class BaselineRenderer(nn.Module):
    """GazeGaussian's renderer: ``feats [B, F, h, w]`` + ``shape_code [B, S]`` -> ``[B, 3, h*u, w*u]`` in (0, 1)."""

    def __init__(self, config: BaselineConfig | None = None):
        super().__init__()
        self.config = c = config or BaselineConfig()
        c.validate()
        self.upscale = c.upscale
        n = int(math.log2(c.upscale))
        ch = [max(c.feature_channels // 2**i, c.min_channels) for i in range(n + 1)]
        self.up = nn.ModuleList(PixelShuffleUpsample(ch[i]) for i in range(n))
        self.feat = nn.ModuleList(nn.Conv2d(ch[i], ch[i + 1], 1) for i in range(n))
        self.pool = nn.ModuleList(AttentionPool(ch[i + 1], c.shape_dim) for i in range(n))
        self.to_rgb = nn.ModuleList(nn.Conv2d(ch[i], 3, 1) for i in range(n + 1))

    def forward(self, feats: torch.Tensor, shape_code: torch.Tensor, gaze: torch.Tensor | None = None,
                pose: torch.Tensor | None = None) -> torch.Tensor:
        """The differentiable image, sigmoid-activated (so already in (0, 1))."""
        check_render_inputs(feats, shape_code, self.config.feature_channels, self.config.shape_dim)
        code = saturate_codes(shape_code)
        rgb = self.to_rgb[0](feats)
        x = feats
        for up, feat, pool, to_rgb in zip(self.up, self.feat, self.pool, self.to_rgb[1:], strict=True):
            x = pool(F.leaky_relu(feat(up(x)), 0.2), code)
            rgb = blur(F.interpolate(rgb, scale_factor=2.0, mode="bilinear", align_corners=False)) + to_rgb(x)
        return torch.sigmoid(rgb)

    def render(self, feats: torch.Tensor, shape_code: torch.Tensor, *, gaze: torch.Tensor | None = None,
               pose: torch.Tensor | None = None, steps: int | None = None, seed: int = 0) -> torch.Tensor:
        check_finite_inputs(feats=feats, shape_code=shape_code)  # the shapes: forward's check
        return self.forward(feats, shape_code)

    def training_forward(self, feats: torch.Tensor, shape_code: torch.Tensor, target: torch.Tensor, *,
                         gaze: torch.Tensor | None = None, pose: torch.Tensor | None = None,
                         generator: torch.Generator | None = None, t: torch.Tensor | None = None) -> RenderOutput:
        image = self.forward(feats, shape_code)  # no diffusion: ``t`` has nothing to set
        if target.shape != image.shape:
            raise ToolkitError(f"BaselineRenderer target: expected {list(image.shape)}, got {list(target.shape)}")
        return RenderOutput(image=image, aux_loss=image.new_zeros(()))
