"""The project's own VGG16 feature extractor (no torchvision), for the perceptual loss.

The layer indices match torchvision's ``vgg16().features`` exactly, so a local torchvision-layout state
dict (``features.0.weight``, ``features.0.bias``, ..., ``features.28.bias``; ``classifier.*`` ignored) loads
into it unchanged. Pretrained weights cannot be downloaded here: the user passes a file
(``.pth``/``.pt`` read with ``weights_only=True``, or ``.safetensors``).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.io import check_readable_file, load_foreign_torch_checkpoint, load_tensors, nonfinite_tensors

# torchvision's configuration "D": channel counts, "M" = 2x2 max-pool.
VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")
# Indices in ``features`` of relu1_2, relu2_2, relu3_3, relu4_3 (Johnson et al.'s perceptual layers).
PERCEPTUAL_LAYERS = (3, 8, 15, 22)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _make_features(cfg=VGG16_CFG) -> nn.Sequential:
    layers: list[nn.Module] = []
    c_in = 3
    for v in cfg:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c_in, v, 3, padding=1), nn.ReLU(inplace=False)]
            c_in = v
    return nn.Sequential(*layers)


class VGG16Features(nn.Module):
    """VGG16 conv trunk; ``forward(x [B, 3, H, W] RGB in [0, 1])`` -> list of activations at ``layers``.

    Only the trunk up to the deepest requested layer runs. Inputs are ImageNet-normalized inside.
    """

    def __init__(self, layers: tuple[int, ...] = PERCEPTUAL_LAYERS):
        super().__init__()
        self.features = _make_features()
        self.layers = tuple(sorted(layers))
        if not self.layers or self.layers[-1] >= len(self.features) or self.layers[0] < 0:
            raise ToolkitError(f"VGG16Features.layers: indices must be in [0, {len(self.features) - 1}], got {layers}")
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.layers:
                out.append(x)
            if i >= self.layers[-1]:
                break
        return out

    def load_torchvision_state_dict(self, state: dict[str, torch.Tensor], source: str = "state dict") -> None:
        """Copy ``features.*`` tensors of a torchvision-layout VGG16 state dict; names the first mismatch."""
        if "state_dict" in state and isinstance(state["state_dict"], dict):
            state = state["state_dict"]
        own = self.features.state_dict()
        picked = {}
        for k, v in own.items():
            name = f"features.{k}"
            src = state.get(name, state.get(f"module.{name}"))
            if src is None:
                raise ToolkitError(f"{source}: missing tensor {name!r}; expected a torchvision-layout VGG16 state dict")
            if not isinstance(src, torch.Tensor) or tuple(src.shape) != tuple(v.shape):
                shape = list(src.shape) if isinstance(src, torch.Tensor) else type(src).__name__
                raise ToolkitError(f"{source}: tensor {name!r} has shape {shape}, expected {list(v.shape)} (VGG16)")
            picked[k] = src
        # Scanned before the float32 cast, which would turn a float64 value past its range into inf.
        if broken := nonfinite_tensors(picked):
            raise ToolkitError(f"{source}: tensor 'features.{broken[0]}' contains NaN or inf")
        self.features.load_state_dict({k: v.to(torch.float32) for k, v in picked.items()})


def load_vgg16(path: str | os.PathLike) -> VGG16Features:
    """A frozen (eval, no grad) :class:`VGG16Features` with weights from a local torchvision VGG16 file."""
    path = check_readable_file(path, "VGG16 weights file")
    if Path(path).suffix.lower() == ".safetensors":
        state, _ = load_tensors(path)
    else:
        state = load_foreign_torch_checkpoint(path)
    if not isinstance(state, dict):
        raise ToolkitError(f"{path}: expected a state dict (name -> tensor), got {type(state).__name__}")
    net = VGG16Features()
    net.load_torchvision_state_dict(state, source=str(path))
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net


def perceptual_distance(vgg: VGG16Features, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean L1 distance between VGG activations of [B, 3, H, W] images a and b, averaged over layers -> []."""
    fa, fb = vgg(a), vgg(b)
    return torch.stack([F.l1_loss(x.float(), y.float()) for x, y in zip(fa, fb)]).mean()
