"""The per-region image loss of DiT-Gaze.

Per region (``head``, ``face``, ``eyes``; masks from the data), both images are put on a white background outside
the region, then ``λ_L1·L1 + λ_SSIM·(1 − SSIM) + λ_P·perceptual``. L1 and SSIM are averaged over the region's
pixels only, so a small region (the eyes) is not drowned by its background. The perceptual term uses the
project's own VGG16 (``train.losses.vgg``) with a local torchvision-layout state dict; with no weights file the
term is disabled and logged once. Computed in float32 even under autocast.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from train.losses.metrics import composite_on_white
from train.losses.precision import fp32, no_autocast

log = logging.getLogger(__name__)
REGIONS = ("head", "face", "eyes")
_EPS = 1e-6
_perceptual_off_logged = False


@dataclass
class ImageLossConfig:
    """Weights of the per-region image loss."""

    lambda_l1: float = 1.0
    """weight of the masked L1 term."""
    lambda_ssim: float = 0.2
    """weight of (1 − SSIM) (SSIM from kornia, ``ssim_window`` Gaussian window)."""
    lambda_perceptual: float = 0.1
    """weight of the VGG16 perceptual term (ignored when ``vgg_path`` is None)."""
    ssim_window: int = 11
    vgg_path: str | None = None
    """local torchvision-layout VGG16 state dict (.pth/.pt/.safetensors); None disables the perceptual term."""
    region_weights: dict[str, float] = field(default_factory=lambda: {"head": 1.0, "face": 1.0, "eyes": 1.0})


class ImageLoss(nn.Module):
    """Region image loss. ``forward(pred, target, masks, weights=None) -> (total [], logs {name: float})``.

    Args of forward:
        pred: [B, 3, h, w] RGB in [0, 1], or a dict region -> [B, 3, h, w] (e.g. the face-only render for
            ``face``); h, w may be smaller than the target's (a 1/4-resolution RGB head): target and mask are
            then area-downsampled to the prediction's size.
        target: [B, 3, H, W] RGB in [0, 1] with a white background.
        masks: dict region -> [B, 1, H, W] (or [B, H, W]) in [0, 1]; a region with weight 0 is skipped.
        weights: optional per-region weights overriding ``config.region_weights``.
    """

    def __init__(self, config: ImageLossConfig | None = None):
        super().__init__()
        self.config = cfg = config or ImageLossConfig()
        if cfg.ssim_window < 3 or cfg.ssim_window % 2 == 0:
            raise ToolkitError(f"ImageLossConfig.ssim_window: expected an odd integer >= 3, got {cfg.ssim_window}")
        self.vgg = None
        if cfg.vgg_path is not None and cfg.lambda_perceptual > 0:
            from train.losses.vgg import load_vgg16

            self.vgg = load_vgg16(cfg.vgg_path)
        elif cfg.lambda_perceptual > 0:
            global _perceptual_off_logged
            if not _perceptual_off_logged:
                log.warning("perceptual loss disabled: no VGG16 weights given (ImageLossConfig.vgg_path); "
                            "pass a local torchvision-layout VGG16 state dict to enable it")
                _perceptual_off_logged = True

    @property
    def perceptual_enabled(self) -> bool:
        return self.vgg is not None

    def train(self, mode: bool = True) -> "ImageLoss":
        super().train(mode)
        if self.vgg is not None:
            self.vgg.eval()  # frozen: never switch to training behaviour
        return self

    def region_loss(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """One region: {"l1", "ssim" (= 1 − SSIM), "perceptual", "total"} scalars (float32)."""
        cfg = self.config
        with no_autocast(pred.device):
            pred, target, mask = fp32(pred), fp32(target), fp32(mask)
            if mask.dim() == 3:
                mask = mask[:, None]
            if pred.dim() != 4 or pred.shape[1] != 3:
                raise ToolkitError(f"ImageLoss: pred must be [B, 3, H, W], got {list(pred.shape)}")
            if target.dim() != 4 or target.shape[:2] != pred.shape[:2]:
                raise ToolkitError(f"ImageLoss: target must be [B={pred.shape[0]}, 3, H, W], got {list(target.shape)}")
            if mask.dim() != 4 or mask.shape[0] != pred.shape[0] or mask.shape[1] != 1 or mask.shape[2:] != target.shape[2:]:
                raise ToolkitError(f"ImageLoss: mask must be [B, 1, {target.shape[2]}, {target.shape[3]}], got {list(mask.shape)}")
            if pred.shape[2:] != target.shape[2:]:
                target = F.interpolate(target, size=pred.shape[2:], mode="area")
                mask = F.interpolate(mask, size=pred.shape[2:], mode="area")
            mask = mask.clamp(0, 1)
            a, b = composite_on_white(pred, mask), composite_on_white(target, mask)
            area = mask.sum(dim=(1, 2, 3))  # [B]
            l1 = ((a - b).abs() * mask).sum(dim=(1, 2, 3)) / (3 * area + _EPS)
            out = {"l1": l1.mean()}
            zero = pred.new_zeros(())
            if cfg.lambda_ssim > 0:
                win = min(cfg.ssim_window, _largest_odd(min(pred.shape[2:])))
                if win >= 3:
                    smap = _ssim_map(a, b, win).mean(1, keepdim=True)  # [B, 1, H, W]
                    ssim = (smap * mask).sum(dim=(1, 2, 3)) / (area + _EPS)
                    # Empty regions contribute 0 rather than 1 − 0.
                    out["ssim"] = torch.where(area > _EPS, 1 - ssim, torch.zeros_like(ssim)).mean()
                else:
                    out["ssim"] = zero
            else:
                out["ssim"] = zero
            if self.vgg is not None and cfg.lambda_perceptual > 0:
                from train.losses.vgg import perceptual_distance

                out["perceptual"] = perceptual_distance(self.vgg, a, b)
            else:
                out["perceptual"] = zero
            out["total"] = cfg.lambda_l1 * out["l1"] + cfg.lambda_ssim * out["ssim"] + cfg.lambda_perceptual * out["perceptual"]
        return out

    def forward(self, pred, target: torch.Tensor, masks: dict[str, torch.Tensor],
                weights: dict[str, float] | None = None) -> tuple[torch.Tensor, dict[str, float]]:
        w = dict(self.config.region_weights)
        w.update(weights or {})
        unknown = set(w) - set(REGIONS)
        if unknown:
            raise ToolkitError(f"ImageLoss: unknown region(s) {sorted(unknown)}; expected {list(REGIONS)}")
        total = None
        logs: dict[str, float] = {}
        for region in REGIONS:
            if w.get(region, 0.0) == 0.0:
                continue
            if region not in masks:
                raise ToolkitError(f"ImageLoss: masks has no {region!r} entry (weight {w[region]}); got {sorted(masks)}")
            p = pred.get(region) if isinstance(pred, dict) else pred
            if p is None:
                raise ToolkitError(f"ImageLoss: pred has no {region!r} image; got {sorted(pred)}")
            parts = self.region_loss(p, target, masks[region])
            for k, v in parts.items():
                logs[f"{region}/{k}"] = float(v.detach())
            term = w[region] * parts["total"]
            total = term if total is None else total + term
        if total is None:
            total = target.new_zeros((), dtype=torch.float32)
        logs["image/total"] = float(total.detach())
        return total, logs


def _largest_odd(n: int) -> int:
    return n if n % 2 == 1 else n - 1


def _ssim_map(a: torch.Tensor, b: torch.Tensor, window: int) -> torch.Tensor:
    """[B, C, H, W] SSIM map (kornia, Gaussian window, max value 1)."""
    import kornia

    return kornia.metrics.ssim(a, b, window, max_val=1.0)
