"""LPIPS perceptual distance, VGG variant (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features
as a Perceptual Metric"), in plain torch, for the evaluation metrics.

This module owns the LPIPS computation and the reading of its two weight files; the VGG16 trunk and the
torchvision-layout loader are :mod:`train.losses.vgg`'s.

Convention: images are [B, 3, H, W] RGB, nominally in [0, 1], with H, W >= 16 (relu5_3 sits after four
2x2 poolings). Values outside [0, 1] are accepted, not clamped, but the distance is then meaningless; they
must be finite. LPIPS's own input scaling is applied inside: x -> 2x - 1 in [-1, 1], then
(x - shift) / scale with shift = (-0.030, -0.088, -0.188), scale = (0.458, 0.448, 0.450) (not the ImageNet
mean/std of :class:`train.losses.vgg.VGG16Features`).

d(a, b) = sum over l of mean over (h, w) of sum over c of w_l[c] * (n(f_l(a)) - n(f_l(b)))[c, h, w]^2, with
f_l the VGG16 activations at relu1_2, relu2_2, relu3_3, relu4_3, relu5_3, n the unit normalization over
channels (x / (||x|| + 1e-10)) and w_l >= 0 the learned 1x1 "lin" weights.

Pretrained weights cannot be downloaded here: the user passes a torchvision VGG16 state dict and the
``lpips`` package's ``weights/v0.1/vgg.pth`` (both ``.pth``/``.pt`` read with ``weights_only=True``, or
``.safetensors``).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn as nn

from toolkit.errors import ToolkitError
from toolkit.io import check_readable_file, load_state_dict_file
from train.losses.vgg import VGG16Features

# torchvision ``features`` indices of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 and their channel counts.
LPIPS_LAYERS = (3, 8, 15, 22, 29)
LPIPS_CHANNELS = (64, 128, 256, 512, 512)
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)
NORM_EPS = 1e-10  # the reference implementation's, added to the channel norm
MIN_SIZE = 16  # four poolings leave relu5_3 at least 1x1


class LPIPS(nn.Module):
    """Frozen LPIPS-VGG; ``forward(a, b)`` on [B, 3, H, W] images in [0, 1] -> [B] distances (0 for a == b).

    Built directly it holds untrained VGG weights and lin weights of one (the paper's unlearned baseline);
    use :meth:`from_files` for the real metric. Parameters never require grad, but gradients reach the inputs,
    so it also serves as a loss; they stay finite for identical inputs and all-zero activations.
    Computes in the module's dtype (float32 unless converted).
    """

    def __init__(self):
        super().__init__()
        self.vgg = VGG16Features(layers=LPIPS_LAYERS)
        self.lin = nn.ParameterList([nn.Parameter(torch.ones(1, c, 1, 1)) for c in LPIPS_CHANNELS])
        # Kept in float64 and cast per call, so a float64 copy of the module uses the exact constants.
        for name, value in (("shift", LPIPS_SHIFT), ("scale", LPIPS_SCALE)):
            value = torch.tensor(value, dtype=torch.float64).view(1, 3, 1, 1)
            self.register_buffer(name, value, persistent=False)
        self.eval()
        self.requires_grad_(False)

    @classmethod
    def from_files(cls, vgg_path: str | os.PathLike, lin_path: str | os.PathLike) -> LPIPS:
        """LPIPS with a torchvision-layout VGG16 state dict (``features.N.weight/bias``; ``classifier.*``
        ignored) and the LPIPS VGG lin file (``lin0.model.1.weight`` ... ``lin4.model.1.weight``, or
        ``lin0.weight`` ...; shapes [1, C, 1, 1], non-negative)."""
        model = cls()
        vgg_path = check_readable_file(vgg_path, "VGG16 weights file")
        model.vgg.load_torchvision_state_dict(load_state_dict_file(vgg_path), source=str(vgg_path))
        lin_path = check_readable_file(lin_path, "LPIPS linear-layer weights file")
        lin_state = load_state_dict_file(lin_path)
        with torch.no_grad():
            for k, param in enumerate(model.lin):
                param.copy_(_lin_weight(lin_state, k, lin_path))
        return model

    def normalized_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """[B, 3, H, W] in [0, 1] -> the five channel-normalized activations [B, C_l, H_l, W_l]."""
        x = (2 * x - 1 - self.shift.to(x.dtype)) / self.scale.to(x.dtype)
        out = []
        for i, layer in enumerate(self.vgg.features[: LPIPS_LAYERS[-1] + 1]):
            x = layer(x)
            if i in LPIPS_LAYERS:
                # vector_norm's gradient at a zero vector is 0, where a plain sqrt's is NaN (masked today only
                # by the ReLU each tap follows).
                out.append(x / (torch.linalg.vector_norm(x, dim=1, keepdim=True) + NORM_EPS))
        return out

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Images a, b [B, 3, H, W] (finite, H, W >= 16) -> [B] LPIPS distances in the module's dtype."""
        _check_images(a, b)
        dtype = self.lin[0].dtype
        fa, fb = self.normalized_features(a.to(dtype)), self.normalized_features(b.to(dtype))
        per_level = [(((x - y) ** 2) * w).sum(1).mean((1, 2)) for x, y, w in zip(fa, fb, self.lin)]
        return torch.stack(per_level).sum(0)


def load_lpips(vgg_path: str | os.PathLike, lin_path: str | os.PathLike) -> LPIPS:
    """:meth:`LPIPS.from_files`: a frozen LPIPS-VGG from a local VGG16 file and the LPIPS lin file."""
    return LPIPS.from_files(vgg_path, lin_path)


def _lin_weight(state: dict, k: int, path: Path) -> torch.Tensor:
    """Level ``k``'s lin weight from the official layout (``lin{k}.model.1.weight``: Dropout then Conv2d) or
    the flat one (``lin{k}.weight``), checked: shape [1, C, 1, 1], finite, non-negative."""
    names = (f"lin{k}.model.1.weight", f"lin{k}.weight")
    name = next((n for n in names if n in state), None)
    if name is None:
        raise ToolkitError(f"{path}: missing tensor {names[0]!r} (or {names[1]!r}); expected the LPIPS VGG "
                           f"linear-layer weights (the lpips package's weights/v0.1/vgg.pth)")
    w = state[name]
    expected = [1, LPIPS_CHANNELS[k], 1, 1]
    if not isinstance(w, torch.Tensor) or list(w.shape) != expected:
        got = list(w.shape) if isinstance(w, torch.Tensor) else type(w).__name__
        raise ToolkitError(f"{path}: tensor {name!r} has shape {got}, expected {expected} "
                           f"(LPIPS-VGG lin layer)")
    if not w.is_floating_point() or not bool(torch.isfinite(w).all()):
        raise ToolkitError(f"{path}: tensor {name!r} must be finite floating-point values")
    if bool((w < 0).any()):
        raise ToolkitError(f"{path}: tensor {name!r} has negative weights (min {float(w.min()):.3g}); "
                           f"LPIPS lin weights are non-negative")
    return w.to(torch.float32)


def _check_images(a: torch.Tensor, b: torch.Tensor) -> None:
    for name, x in (("a", a), ("b", b)):
        if not isinstance(x, torch.Tensor) or x.dim() != 4 or x.shape[1] != 3:
            got = list(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise ToolkitError(f"lpips: input {name} must be a [B, 3, H, W] image tensor, got {got}")
        if not x.is_floating_point():
            raise ToolkitError(f"lpips: input {name} must be floating-point in [0, 1], got {x.dtype}")
    if a.shape != b.shape:
        raise ToolkitError(f"lpips: inputs must have one shape, got {list(a.shape)} and {list(b.shape)}")
    if min(a.shape[-2:]) < MIN_SIZE:
        raise ToolkitError(f"lpips: images must be at least {MIN_SIZE}x{MIN_SIZE} pixels (relu5_3 follows "
                           f"four 2x2 poolings), got {a.shape[-2]}x{a.shape[-1]}")
    for name, x in (("a", a), ("b", b)):
        if not bool(torch.isfinite(x).all()):
            raise ToolkitError(f"lpips: input {name} contains NaN or inf")
