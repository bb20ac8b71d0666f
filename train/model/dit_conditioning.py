"""The DiT-Gaze-specific embedders of the DiT (:mod:`train.model.dit`): the codes into the adaLN vector, the
splatted feature map onto the latent grid; and the soft saturation of the codes the baseline renderer shares.

Shapes: ``B`` batch, ``F`` splatted feature channels, ``h x w`` the feature map, ``E`` the encoded feature
channels, ``H x W`` the latent grid, ``D`` the DiT's hidden size.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError

CODE_LIMIT = 10.0  # soft bound on every code entry, far above the unit scale of learned codes


def saturate_codes(x: torch.Tensor, limit: float = CODE_LIMIT) -> torch.Tensor:
    """Soft bound ``limit * tanh(x / limit)``: the identity for ordinary codes, finite for huge ones."""
    return limit * torch.tanh(x / limit)


class CodeEmbedder(nn.Module):
    """Embeds the shape code (and optionally gaze and pose) into the adaLN conditioning vector."""

    def __init__(self, shape_dim: int, gaze_dim: int, pose_dim: int, hidden_size: int):
        super().__init__()
        self.gaze_dim, self.pose_dim = gaze_dim, pose_dim
        in_dim = shape_dim + 2 * gaze_dim + pose_dim  # the gaze enters as sin/cos of (pitch, yaw)
        self.mlp = nn.Sequential(nn.Linear(in_dim, hidden_size), nn.SiLU(), nn.Linear(hidden_size, hidden_size))

    def forward(self, shape_code: torch.Tensor, gaze: torch.Tensor | None, pose: torch.Tensor | None) -> torch.Tensor:
        parts = [shape_code]
        if self.gaze_dim:
            if gaze is None:
                raise ToolkitError("DiT: this configuration conditions on gaze [B, 2] but none was given")
            parts += [torch.sin(gaze), torch.cos(gaze)]
        if self.pose_dim:
            if pose is None:
                raise ToolkitError(f"DiT: this configuration conditions on pose [B, {self.pose_dim}] but none was given")
            parts.append(pose)
        x = torch.cat([p.to(shape_code.dtype) for p in parts], dim=-1)
        return self.mlp(saturate_codes(x))


class FeatureEncoder(nn.Module):
    """Encodes the splatted feature map ``[B, F, h, w]`` to ``[B, E, H, W]`` on the latent grid."""

    def __init__(self, in_channels: int, out_channels: int, hidden: int = 64):
        super().__init__()
        self.conv_in = nn.Conv2d(in_channels, hidden, 3, padding=1)
        self.conv_out = nn.Conv2d(hidden, out_channels, 3, padding=1)

    def forward(self, feats: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        x = F.silu(self.conv_in(feats))
        if tuple(x.shape[-2:]) != tuple(size):
            shrinking = x.shape[-2] >= size[0] and x.shape[-1] >= size[1]
            x = F.interpolate(x, size=size, mode="area") if shrinking else F.interpolate(
                x, size=size, mode="bilinear", align_corners=False)
        return self.conv_out(x)
