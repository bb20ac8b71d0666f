"""The latent Diffusion Transformer of DiT-Gaze: a DiT (Peebles & Xie, 2023) conditioned on splatted features.

Shapes: ``B`` batch, ``C`` latent channels (4 for the Stable Diffusion VAE and the project's KL autoencoder,
3 in pixel space), ``H x W`` the latent grid, ``F`` the splatted feature channels (32), ``h x w`` the feature
map (GazeGaussian renders it at 1/4 of the output image, i.e. 2x the 8x-down latent grid).

How the two conditioning signals enter:

* **Vector conditioning through adaLN.** ``c = TimestepEmbedder(t) + CodeEmbedder([tau, phi?, gamma?])`` where
  ``tau`` is the shape code (identity + expression, ``shape_dim``: 144 for native data), ``phi`` the gaze (pitch, yaw; embedded as
  sin/cos) and ``gamma`` the head pose (6-d) -- the last two only when the configuration enables them. Codes
  pass through a soft saturation ``L * tanh(x / L)`` (``L = CODE_LIMIT``) before the MLP so that huge codes
  cannot blow up the modulations; ordinary codes (|x| << L) are passed unchanged. Every ``DiTBlock`` and the
  ``FinalLayer`` regress (shift, scale, gate) from ``SiLU(c)``; those regressors are zero-initialized
  (adaLN-Zero), so each block is exactly the identity at initialization.
* **Spatial conditioning by channel concatenation (InstructPix2Pix).** ``FeatureEncoder`` maps the splatted
  feature map ``[B, F, h, w]`` to ``feature_embed_channels`` channels on the latent grid ``[B, E, H, W]``
  (3x3 conv at the feature resolution, resize to the latent grid -- area average when shrinking, bilinear
  when growing -- then 3x3 conv). It is concatenated with the noisy latent to ``[B, C + E, H, W]`` and
  patchified by one Conv2d. The patch-embedding weights that read the ``E`` extra channels are zero at
  initialization, so the model starts as an unconditional latent DiT and learns to use the features, exactly
  as InstructPix2Pix adds its image channels to a pretrained model. With ``base_channels > 0`` (the residual
  renderer) the base latent ``z_base`` -- the splatted RGB encoded by the frozen codec -- is concatenated as
  well, ``[B, C + E + C_base, H, W]``, with zero-initialized weights too.

Reads like DiT's ``models.py``: embedding layers, core model, sin-cos position embeddings, configurations. The
two DiT-Gaze-specific embedders (codes, feature maps) live in :mod:`train.model.dit_conditioning`.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass
from typing import Callable

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from train.model.dit_conditioning import CodeEmbedder, FeatureEncoder


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """adaLN modulation: ``x [B, N, D]`` scaled by ``1 + scale [B, D]`` and shifted by ``shift [B, D]``."""
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


@dataclass
class DiTConfig:
    """A DiT-Gaze renderer network. Defaults are the paper configuration (depth 6, 8 heads, 4-ch latent)."""

    input_size: int = 64
    """Latent grid side ``H = W`` the fixed position embedding is built for (other sizes are recomputed)."""
    patch_size: int = 2
    """Side of the square patches that become tokens; must divide the latent grid."""
    latent_channels: int = 4
    """Channels of the (noisy) latent: 4 for the SD VAE / KL autoencoder, 3 in pixel space."""
    feature_channels: int = 32
    """Channels ``F`` of the splatted feature map."""
    feature_embed_channels: int = 8
    """Channels ``E`` the feature map is encoded to before the channel concatenation."""
    feature_hidden: int = 64
    """Channels of the feature encoder's hidden layer (a 3x3 conv at the feature map's resolution, SiLU, a 3x3
    conv to ``E``): at 128² its two passes a training step were ~30% of the demo's step at 64."""
    base_channels: int = 0
    """Channels of an optional *base latent* ``[B, base_channels, H, W]`` concatenated with the input (the
    residual renderer passes the encoded splat RGB ``z_base``; 0 leaves it out). Zero-initialized like the
    feature channels."""
    hidden_size: int = 384
    depth: int = 6
    num_heads: int = 8
    mlp_ratio: float = 4.0
    shape_dim: int = 144
    """Identity + expression code size (GazeGaussian's tau): the Gaussian model's ``code_dim``, the data's."""
    gaze_dim: int = 0
    """2 to condition the adaLN vector on the gaze (pitch, yaw), 0 to leave it out."""
    pose_dim: int = 0
    """6 to condition the adaLN vector on the head pose, 0 to leave it out."""

    def validate(self) -> None:
        for name in ("input_size", "hidden_size", "patch_size", "latent_channels", "feature_channels",
                     "feature_hidden", "depth", "num_heads", "shape_dim"):
            v = getattr(self, name)
            if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < 1:
                raise ToolkitError(f"DiTConfig.{name}: expected a positive integer, got {v!r}")
        if self.hidden_size % self.num_heads:
            raise ToolkitError(f"DiTConfig.hidden_size: {self.hidden_size} is not divisible by num_heads={self.num_heads}")
        if (self.hidden_size // self.num_heads) % 2 or self.hidden_size % 4:
            raise ToolkitError(f"DiTConfig.hidden_size: {self.hidden_size} must be a multiple of 4 (2D sin-cos embedding)")
        if self.input_size % self.patch_size:
            raise ToolkitError(f"DiTConfig.input_size: {self.input_size} is not divisible by patch_size={self.patch_size}")
        if self.gaze_dim not in (0, 2):
            raise ToolkitError(f"DiTConfig.gaze_dim: expected 0 or 2 (pitch, yaw), got {self.gaze_dim}")
        if self.pose_dim not in (0, 6):
            raise ToolkitError(f"DiTConfig.pose_dim: expected 0 or 6 (axis-angle + translation), got {self.pose_dim}")
        for name in ("base_channels", "feature_embed_channels"):
            if getattr(self, name) < 0:
                raise ToolkitError(f"DiTConfig.{name}: expected >= 0, got {getattr(self, name)}")
        r = self.mlp_ratio
        if not (isinstance(r, numbers.Real) and math.isfinite(r) and r > 0 and int(self.hidden_size * r) >= 1):
            raise ToolkitError(f"DiTConfig.mlp_ratio: expected a number > 0 (an MLP width hidden_size * mlp_ratio >= 1), "
                               f"got {self.mlp_ratio!r}")


#################################################################################
#        Embedding Layers for Timesteps and Patches (codes: dit_conditioning)   #
#################################################################################


class TimestepEmbedder(nn.Module):
    """Embeds scalar (possibly fractional) timesteps: 256 sinusoidal frequencies -> MLP."""

    def __init__(self, hidden_size: int, frequency_embedding_size: int = 256):
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(frequency_embedding_size, hidden_size), nn.SiLU(), nn.Linear(hidden_size, hidden_size)
        )
        self.frequency_embedding_size = frequency_embedding_size

    @staticmethod
    def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
        """``t [B]`` -> ``[B, dim]`` cos/sin features with periods from 2*pi to ``max_period``."""
        half = dim // 2
        freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
        args = t.float()[:, None] * freqs[None]
        emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
        if dim % 2:
            emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
        return emb

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.timestep_embedding(t, self.frequency_embedding_size))


class PatchEmbed(nn.Module):
    """``[B, Cin, H, W]`` -> ``[B, (H/p)(W/p), D]`` tokens with one Conv2d of kernel = stride = p."""

    def __init__(self, patch_size: int, in_channels: int, hidden_size: int):
        super().__init__()
        self.proj = nn.Conv2d(in_channels, hidden_size, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


#################################################################################
#                                 Core DiT Model                                #
#################################################################################


class Attention(nn.Module):
    """Multi-head self-attention through ``F.scaled_dot_product_attention``."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, N, D = x.shape
        q, k, v = self.qkv(x).reshape(B, N, 3, self.num_heads, D // self.num_heads).permute(2, 0, 3, 1, 4)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(B, N, D))


class Mlp(nn.Module):
    """Token-wise two-layer MLP with tanh-GELU, as in ViT/DiT."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x), approximate="tanh"))


class DiTBlock(nn.Module):
    """A DiT block with adaLN-Zero conditioning (shift/scale/gate for attention and MLP)."""

    def __init__(self, hidden_size: int, num_heads: int, mlp_ratio: float = 4.0):
        super().__init__()
        self.norm1 = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(hidden_size, num_heads)
        self.norm2 = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=1e-6)
        self.mlp = Mlp(hidden_size, int(hidden_size * mlp_ratio))
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 6 * hidden_size))

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        shift_msa, scale_msa, gate_msa, shift_mlp, scale_mlp, gate_mlp = self.adaLN_modulation(c).chunk(6, dim=1)
        x = x + gate_msa.unsqueeze(1) * self.attn(modulate(self.norm1(x), shift_msa, scale_msa))
        x = x + gate_mlp.unsqueeze(1) * self.mlp(modulate(self.norm2(x), shift_mlp, scale_mlp))
        return x


class FinalLayer(nn.Module):
    """adaLN-modulated LayerNorm, then a linear map from each token to its ``p x p x C`` patch."""

    def __init__(self, hidden_size: int, patch_size: int, out_channels: int):
        super().__init__()
        self.norm_final = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=1e-6)
        self.linear = nn.Linear(hidden_size, patch_size * patch_size * out_channels)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 2 * hidden_size))

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        shift, scale = self.adaLN_modulation(c).chunk(2, dim=1)
        return self.linear(modulate(self.norm_final(x), shift, scale))


class DiT(nn.Module):
    """Latent DiT conditioned on a splatted feature map (channel concat) and codes (adaLN-Zero).

    ``forward(x [B, C, H, W], t [B], feats [B, F, h, w], shape_code [B, shape_dim], gaze [B, 2]?, pose [B, 6]?)``
    returns the network output ``[B, C, H, W]`` (epsilon or v, as the diffusion's ``prediction`` says).
    ``H`` and ``W`` must be multiples of the patch size; other grids than ``input_size`` work (the fixed
    position embedding is recomputed for them).
    """

    def __init__(self, config: DiTConfig | None = None, **overrides):
        super().__init__()
        config = DiTConfig(**{**asdict(config or DiTConfig()), **overrides})
        config.validate()
        self.config = config
        c = config
        self.feature_encoder = FeatureEncoder(c.feature_channels, c.feature_embed_channels, c.feature_hidden)
        self.x_embedder = PatchEmbed(c.patch_size, c.latent_channels + c.feature_embed_channels + c.base_channels,
                                     c.hidden_size)
        self.t_embedder = TimestepEmbedder(c.hidden_size)
        self.code_embedder = CodeEmbedder(c.shape_dim, c.gaze_dim, c.pose_dim, c.hidden_size)
        grid = c.input_size // c.patch_size
        # Fixed (not learned) sin-cos embedding, kept out of checkpoints because it is a pure function of the grid.
        self.register_buffer("pos_embed", get_2d_sincos_pos_embed(c.hidden_size, grid, grid), persistent=False)
        self.blocks = nn.ModuleList([DiTBlock(c.hidden_size, c.num_heads, c.mlp_ratio) for _ in range(c.depth)])
        self.final_layer = FinalLayer(c.hidden_size, c.patch_size, c.latent_channels)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        def _basic_init(module: nn.Module) -> None:
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)

        self.apply(_basic_init)

        # Patch embedding like nn.Linear (as DiT), then InstructPix2Pix: the weights that read the encoded
        # feature (and base-latent) channels start at zero, so they cannot change the output until learned.
        w = self.x_embedder.proj.weight.data
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))
        nn.init.zeros_(self.x_embedder.proj.bias)
        w[:, self.config.latent_channels:].zero_()

        nn.init.normal_(self.t_embedder.mlp[0].weight, std=0.02)
        nn.init.normal_(self.t_embedder.mlp[2].weight, std=0.02)
        nn.init.normal_(self.code_embedder.mlp[0].weight, std=0.02)
        nn.init.normal_(self.code_embedder.mlp[2].weight, std=0.02)

        # adaLN-Zero: every block's shift/scale/gate regressor is zero, so each block is the identity at init.
        for block in self.blocks:
            nn.init.zeros_(block.adaLN_modulation[-1].weight)
            nn.init.zeros_(block.adaLN_modulation[-1].bias)
        # Zero output layer: the initial prediction is 0 (the mean of epsilon and of v).
        nn.init.zeros_(self.final_layer.adaLN_modulation[-1].weight)
        nn.init.zeros_(self.final_layer.adaLN_modulation[-1].bias)
        nn.init.zeros_(self.final_layer.linear.weight)
        nn.init.zeros_(self.final_layer.linear.bias)

    def unpatchify(self, x: torch.Tensor, gh: int, gw: int) -> torch.Tensor:
        """``[B, gh*gw, p*p*C]`` tokens -> ``[B, C, gh*p, gw*p]`` latent."""
        p, C = self.config.patch_size, self.config.latent_channels
        x = x.reshape(x.shape[0], gh, gw, p, p, C)
        return torch.einsum("nhwpqc->nchpwq", x).reshape(x.shape[0], C, gh * p, gw * p)

    def conditioning(self, t: torch.Tensor, shape_code: torch.Tensor, gaze: torch.Tensor | None = None,
                     pose: torch.Tensor | None = None) -> torch.Tensor:
        """The adaLN vector ``c [B, D]`` = timestep embedding + code embedding."""
        return self.t_embedder(t) + self.code_embedder(shape_code, gaze, pose)

    def encode_features(self, feats: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """``[B, F, h, w]`` -> ``[B, E, H, W]``; samplers compute it once and pass it to every step."""
        return self.feature_encoder(feats, size)

    def forward(self, x: torch.Tensor, t: torch.Tensor, feats: torch.Tensor, shape_code: torch.Tensor,
                gaze: torch.Tensor | None = None, pose: torch.Tensor | None = None, *,
                feature_embedding: torch.Tensor | None = None, base: torch.Tensor | None = None) -> torch.Tensor:
        """``feature_embedding`` (from :meth:`encode_features`) skips the feature encoder when given;
        ``base [B, base_channels, H, W]`` is required exactly when ``config.base_channels > 0``."""
        self._check_inputs(x, t, feats, shape_code)
        B, _, H, W = x.shape
        p = self.config.patch_size
        gh, gw = H // p, W // p
        grid = self.config.input_size // p
        pos = self.pos_embed if gh == gw == grid else get_2d_sincos_pos_embed(self.config.hidden_size, gh, gw, x.device)
        if feature_embedding is None:
            feature_embedding = self.encode_features(feats, (H, W))
        elif feature_embedding.shape != (B, self.config.feature_embed_channels, H, W):
            raise ToolkitError(f"DiT feature_embedding: expected [{B}, {self.config.feature_embed_channels}, {H}, {W}], "
                               f"got {list(feature_embedding.shape)}")
        parts = [x, feature_embedding.to(x.dtype)]
        if self.config.base_channels:
            if base is None or base.shape != (B, self.config.base_channels, H, W):
                raise ToolkitError(f"DiT base: expected [{B}, {self.config.base_channels}, {H}, {W}] (config.base_channels), "
                                   f"got {None if base is None else list(base.shape)}")
            parts.append(base.to(x.dtype))
        elif base is not None:
            raise ToolkitError("DiT base: this configuration has base_channels=0 but a base latent was given")
        h = torch.cat(parts, dim=1)
        tokens = self.x_embedder(h) + pos.to(h.dtype)
        c = self.conditioning(t.expand(B) if t.dim() == 0 else t, shape_code, gaze, pose)
        for block in self.blocks:
            tokens = block(tokens, c)
        return self.unpatchify(self.final_layer(tokens, c), gh, gw)

    def _check_inputs(self, x: torch.Tensor, t: torch.Tensor, feats: torch.Tensor, shape_code: torch.Tensor) -> None:
        c = self.config
        if x.dim() != 4 or x.shape[1] != c.latent_channels:
            raise ToolkitError(f"DiT input x: expected [B, {c.latent_channels}, H, W], got {list(x.shape)}")
        if x.shape[2] % c.patch_size or x.shape[3] % c.patch_size:
            raise ToolkitError(f"DiT input x: latent grid {list(x.shape[2:])} is not a multiple of patch_size={c.patch_size}")
        if feats.dim() != 4 or feats.shape[0] != x.shape[0] or feats.shape[1] != c.feature_channels:
            raise ToolkitError(f"DiT feats: expected [{x.shape[0]}, {c.feature_channels}, h, w], got {list(feats.shape)}")
        if shape_code.shape != (x.shape[0], c.shape_dim):
            raise ToolkitError(f"DiT shape_code: expected [{x.shape[0]}, {c.shape_dim}], got {list(shape_code.shape)}")
        if t.dim() > 1 or (t.dim() == 1 and t.shape[0] != x.shape[0]):
            raise ToolkitError(f"DiT t: expected a scalar or [{x.shape[0]}], got {list(t.shape)}")


#################################################################################
#                   Sine/Cosine Positional Embedding Functions                  #
#################################################################################


def get_1d_sincos_pos_embed(embed_dim: int, pos: torch.Tensor) -> torch.Tensor:
    """``pos [M]`` -> ``[M, embed_dim]``: half sines, half cosines of geometrically spaced frequencies."""
    omega = 1.0 / 10000 ** (torch.arange(embed_dim // 2, dtype=torch.float64, device=pos.device) / (embed_dim / 2.0))
    out = pos.double()[:, None] * omega[None]
    return torch.cat([torch.sin(out), torch.cos(out)], dim=1)


def get_2d_sincos_pos_embed(embed_dim: int, grid_h: int, grid_w: int, device: torch.device | str | None = None
                            ) -> torch.Tensor:
    """Fixed 2D sin-cos embedding ``[grid_h * grid_w, embed_dim]`` (row-major tokens): half for x, half for y."""
    ys, xs = torch.meshgrid(torch.arange(grid_h, device=device), torch.arange(grid_w, device=device), indexing="ij")
    emb = torch.cat([get_1d_sincos_pos_embed(embed_dim // 2, xs.reshape(-1)),
                     get_1d_sincos_pos_embed(embed_dim // 2, ys.reshape(-1))], dim=1)
    return emb.float()


#################################################################################
#                                DiT-Gaze Configs                               #
#################################################################################


def DiT_paper(**kw) -> DiT:
    """The paper's renderer: depth 6, 8 heads, hidden 384, patch 2, 4-channel latent."""
    return DiT(**{**dict(depth=6, num_heads=8, hidden_size=384, patch_size=2), **kw})


def DiT_paper_p4(**kw) -> DiT:
    """The paper's depth and heads with 4x4 patches (4x fewer tokens, for 512^2 outputs)."""
    return DiT(**{**dict(depth=6, num_heads=8, hidden_size=384, patch_size=4), **kw})


def DiT_small(**kw) -> DiT:
    """A mid-size renderer for short CPU runs: depth 4, 4 heads, hidden 128."""
    return DiT(**{**dict(depth=4, num_heads=4, hidden_size=128, patch_size=2, feature_embed_channels=8), **kw})


def DiT_tiny(**kw) -> DiT:
    """The CPU test configuration: depth 2, 4 heads, hidden 64."""
    return DiT(**{**dict(depth=2, num_heads=4, hidden_size=64, patch_size=2, mlp_ratio=2.0,
                         feature_embed_channels=4), **kw})


def DiT_pixel(**kw) -> DiT:
    """For pixel space at 128^2: depth 2, 4 heads, hidden 128, 8x8 patches (256 tokens)."""
    return DiT(**{**dict(depth=2, num_heads=4, hidden_size=128, patch_size=8, mlp_ratio=2.0,
                         feature_embed_channels=4), **kw})


DIT_MODELS: dict[str, Callable[..., DiT]] = {
    "DiT-Gaze-paper": DiT_paper,
    "DiT-Gaze-paper/4": DiT_paper_p4,
    "DiT-Gaze-S": DiT_small,
    "DiT-Gaze-tiny": DiT_tiny,
    "DiT-Gaze-pixel": DiT_pixel,
}


def make_dit(name: str, **kw) -> DiT:
    """Build a named configuration (``DIT_MODELS``); keyword overrides go to ``DiTConfig``."""
    if name not in DIT_MODELS:
        raise ToolkitError(f"DiT model name: unknown {name!r}, expected one of {sorted(DIT_MODELS)}")
    return DIT_MODELS[name](**kw)
