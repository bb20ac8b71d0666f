"""The gaze estimator's training augmentation: photometric jitter, random blur, shifts, and the eye-patch
design's augmentation done on the patches it reads."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from train.estimator.config import GazeEstimatorTrainConfig
from train.estimator.network import GazeEstimator

BLUR_BOX_MARGIN = 8
"""Pixels added around :func:`train.estimator.crops.eye_patch_box` before the landmark jitter (``landmark_noise``,
0.3 px by default) moves the eye windows: a move of more than ~5 px, which such jitter never draws, would read
unblurred pixels."""


def jitter_photometric(images: torch.Tensor, cfg: GazeEstimatorTrainConfig, g: torch.Generator) -> torch.Tensor:
    """Per-sample brightness and contrast jitter plus Gaussian noise, [B, C, H, W] -> same (not clamped)."""
    B, dev = images.shape[0], images.device
    b = (torch.rand(B, 1, 1, 1, generator=g) * 2 - 1).to(dev) * cfg.brightness
    c = 1 + (torch.rand(B, 1, 1, 1, generator=g) * 2 - 1).to(dev) * cfg.contrast
    mean = images.mean(dim=(1, 2, 3), keepdim=True)
    x = (images - mean) * c + mean + b
    return x + torch.randn(x.shape, generator=g).to(dev) * cfg.noise


def random_blur(images: torch.Tensor, prob: float, max_sigma: float, g: torch.Generator,
                box: tuple[int, int, int, int] | None = None) -> torch.Tensor:
    """Blur each image [B, C, H, W] with probability ``prob`` by a separable Gaussian whose standard deviation is
    uniform in [0, ``max_sigma``] pixels (edge-replicated borders); the others pass unchanged. With ``box``
    ``(y0, y1, x0, x1)`` only the pixels inside it change, to exactly what blurring the whole image gives there
    (eye-patch training reads :func:`train.estimator.crops.eye_patch_box` alone: ~1/4 of the pixels).

    Why: a render is never as sharp as the anti-aliased synthetic ground truth (a latent codec's round trip, a
    coarser splat). An estimator trained on sharp images alone reads a softer image of the *same* eyes as a
    different gaze, and the gaze metric and loss then measure sharpness instead of gaze."""
    B, C, H, W = images.shape
    if prob <= 0 or max_sigma <= 0:
        return images
    dev = images.device
    sigma = torch.rand(B, generator=g) * max_sigma * (torch.rand(B, generator=g) < prob)
    # Only the drawn images are convolved (the estimator's step spent ~25% of its time blurring every image,
    # half of them with a unit impulse); a zero sigma draws no blur, however small the chance.
    sel = (sigma > 0).nonzero().squeeze(1)
    n = sel.numel()
    if n == 0:
        return images
    r = max(1, math.ceil(3 * max_sigma))
    xs = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (xs / sigma[sel].clamp_min(1e-3).unsqueeze(-1)) ** 2)
    k = (k / k.sum(-1, keepdim=True)).repeat_interleave(C, 0).to(dev, images.dtype)  # [n*C, 2r+1]
    sel = sel.to(dev)
    y0, y1, x0, x1 = box if box is not None else (0, H, 0, W)
    if not (0 <= y0 < y1 <= H and 0 <= x0 < x1 <= W):
        raise ToolkitError(f"random_blur: box {box} is not a non-empty (y0, y1, x0, x1) inside {H} x {W}")
    # The box with r pixels of context, cut at the image's edges; what the cut removed is the edge replicated,
    # as the whole image's padding would give it.
    cy0, cy1, cx0, cx1 = max(0, y0 - r), min(H, y1 + r), max(0, x0 - r), min(W, x1 + r)
    x = images[sel, :, cy0:cy1, cx0:cx1].reshape(1, n * C, cy1 - cy0, cx1 - cx0)
    x = F.pad(x, (r - (x0 - cx0), r - (cx1 - x1), r - (y0 - cy0), r - (cy1 - y1)), mode="replicate")
    x = F.conv2d(x, k.view(n * C, 1, 1, -1), groups=n * C)
    x = F.conv2d(x, k.view(n * C, 1, -1, 1), groups=n * C)
    out = images.clone()
    out[sel, :, y0:y1, x0:x1] = x.reshape(n, C, y1 - y0, x1 - x0)
    return out


def augment_eye_inputs(images: torch.Tensor, landmarks: torch.Tensor, model: "GazeEstimator",
                       cfg: GazeEstimatorTrainConfig, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The eye-patch estimator's augmentation, done on what it reads: ``model.eye_inputs`` of the images at
    landmarks jittered by ``landmark_noise`` pixels, photometric jitter on the patches, and a per-sample
    integer shift of up to ``max_shift`` on the layout.

    The geometry is that of :func:`augment_batch` on the whole image (an integer shift of image and landmarks
    together leaves the patches unchanged and moves only the layout), at a tenth of the pixels; the shift is
    drawn per sample, and contrast and noise act in patch space (patch mean, noise per patch sample)."""
    B, _, H, W = images.shape
    lm = landmarks + torch.randn(landmarks.shape, generator=g).to(landmarks.device) * cfg.landmark_noise
    patches, layout = model.eye_inputs(images, lm)
    ms = int(round(cfg.max_shift * min(H, W)))
    if ms > 0:
        shift = torch.randint(-ms, ms + 1, (B, 1, 2), generator=g).to(layout)
        layout = layout + (shift * layout.new_tensor([2 / W, 2 / H])).repeat(1, 68, 1).flatten(1)
    return jitter_photometric(patches, cfg, g).clamp(0, 1), layout


def augment_batch(images: torch.Tensor, cfg: GazeEstimatorTrainConfig, g: torch.Generator,
                  landmarks: torch.Tensor | None = None):
    """Light photometric jitter, Gaussian noise and a small integer shift (edge-replicated), [B, 3, H, W].

    With ``landmarks`` [B, 68, 2] returns ``(images, landmarks)``, the landmarks moved with the shift and
    jittered by ``landmark_noise`` pixels (a detector's noise on real data)."""
    B, _, H, W = images.shape
    x = jitter_photometric(images, cfg, g)
    ms = int(round(cfg.max_shift * min(H, W)))
    if ms > 0:
        dx, dy = (int(v) for v in torch.randint(-ms, ms + 1, (2,), generator=g))
        x = F.pad(x, (ms, ms, ms, ms), mode="replicate")[:, :, ms + dy:ms + dy + H, ms + dx:ms + dx + W]
    else:
        dx = dy = 0
    if landmarks is None:
        return x.clamp(0, 1)
    # Content moved by (-dx, -dy): the crop starts dx, dy pixels further along.
    lm = landmarks - landmarks.new_tensor([dx, dy])
    lm = lm + torch.randn(lm.shape, generator=g).to(lm.device) * cfg.landmark_noise
    return x.clamp(0, 1), lm

