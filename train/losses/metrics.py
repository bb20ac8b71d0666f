"""Image metrics of the gaze-redirection protocol (GazeNeRF / GazeGaussian Table 1).

Images are [B, 3, H, W] float in [0, 1]. Before any metric, pixels outside the head mask are set to
white in both images (the protocol's white background), so the background never counts.
Metrics that need weights nobody can download here (LPIPS, identity similarity) return ``None``
unless the caller supplies them; tables print ``None`` as ``n/a``.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError


def composite_on_white(img: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """[B, 3, H, W] image, [B, 1, H, W] or [B, H, W] mask in [0, 1] -> image with white outside the mask."""
    if mask.dim() == 3:
        mask = mask[:, None]
    mask = mask.to(img.dtype)
    return img * mask + (1 - mask)


def dilate_mask(mask: torch.Tensor, pixels: int) -> torch.Tensor:
    """[B, 1, H, W] mask in [0, 1] grown by ``pixels`` in every direction (a square max filter), as float."""
    mask = mask.float()
    return F.max_pool2d(mask, 2 * pixels + 1, stride=1, padding=pixels) if pixels > 0 else mask


def psnr(pred: torch.Tensor, target: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """[B, C, H, W] in [0, 1] -> [B] PSNR in dB (capped by eps at about 100 dB for identical images)."""
    _check_pair(pred, target)
    mse = ((pred - target) ** 2).flatten(1).mean(1)
    return 10 * torch.log10(1.0 / mse.clamp_min(eps))


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11) -> torch.Tensor:
    """[B, C, H, W] in [0, 1] -> [B] mean SSIM (Gaussian window 11, σ 1.5, as Wang et al. / kornia)."""
    import kornia

    _check_pair(pred, target)
    if min(pred.shape[-2:]) < 2:  # the window's reflect padding needs 2 pixels a side
        raise ToolkitError(f"ssim: images must be at least 2x2 pixels, got {pred.shape[-2]}x{pred.shape[-1]}")
    window = min(window, pred.shape[-1] - (1 - pred.shape[-1] % 2), pred.shape[-2] - (1 - pred.shape[-2] % 2))
    window = max(window, 3)
    return kornia.metrics.ssim(pred, target, window).flatten(1).mean(1)


def _check_pair(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.shape != b.shape or a.dim() != 4:
        raise ToolkitError(f"metric inputs must both be [B, C, H, W] of one shape, got {list(a.shape)} and {list(b.shape)}")


def summarize(values: Sequence[float | None]) -> float | None:
    """Mean of the non-None values, or None when there are none."""
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return sum(vals) / len(vals) if vals else None


def bootstrap_mean_interval(values: Sequence[float | None], level: float = 0.95, resamples: int = 2000,
                            seed: int = 0) -> tuple[float, float] | None:
    """Percentile bootstrap interval of the mean of the non-None, non-NaN ``values`` (resampled with
    replacement, ``resamples`` times, a fixed seed so a report is reproducible); None for fewer than 2 values.
    It covers the choice of samples (an evaluation's pairs) only, not the randomness of the training."""
    vals = [v for v in values if v is not None and not math.isnan(v)]
    if len(vals) < 2:
        return None
    x = torch.tensor(vals, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    means = x[torch.randint(0, len(vals), (resamples, len(vals)), generator=g)].mean(1)
    lo, hi = torch.quantile(means, torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=torch.float64)).tolist()
    return lo, hi


TABLE1_COLUMNS = [
    ("gaze_error_deg", "Gaze ↓ (°)"),
    ("head_pose_error_deg", "Head pose ↓ (°)"),
    ("ssim", "SSIM ↑"),
    ("psnr", "PSNR ↑ (dB)"),
    ("lpips", "LPIPS ↓"),
    ("fid", "FID ↓"),
    ("identity_similarity", "ID sim. ↑"),
    ("images_per_s", "img/s ↑"),
]


def table1_markdown(rows: dict[str, dict[str, Any]]) -> str:
    """{method name: {metric key: value}} -> a Markdown table in the layout of the paper's Table 1."""
    head = "| Method | " + " | ".join(label for _, label in TABLE1_COLUMNS) + " |"
    sep = "|---|" + "|".join("---:" for _ in TABLE1_COLUMNS) + "|"
    lines = [head, sep]
    for name, vals in rows.items():
        cells = []
        for key, _ in TABLE1_COLUMNS:
            v = vals.get(key)
            cells.append("n/a" if v is None else (f"{v:.3f}" if key in ("ssim", "lpips", "identity_similarity") else f"{v:.2f}"))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def downsample_to(img: torch.Tensor, size: int) -> torch.Tensor:
    """Area-downsample [B, C, H, W] to size × size (used to compare renders at a common resolution)."""
    if img.shape[-1] == size and img.shape[-2] == size:
        return img
    return F.interpolate(img, size=(size, size), mode="area")
