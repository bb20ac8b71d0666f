"""Float32 islands for the losses under autocast."""

from __future__ import annotations

import torch


def fp32(x: torch.Tensor) -> torch.Tensor:
    return x.float() if x.dtype != torch.float32 else x


def no_autocast(device: torch.device):
    """A context in which autocast is off on ``device``: the losses compute in float32 (SSIM and cosines lose
    too much in bf16)."""
    return torch.autocast(device_type=device.type, enabled=False)
