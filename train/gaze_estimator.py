"""A compact CNN gaze estimator (no torchvision) and its trainer.

``GazeEstimator(images [B, 3, H, W] RGB in [0, 1]) -> [B, 4]``: gaze (pitch, yaw) then head (pitch, yaw), radians,
ETH-XGaze convention (``toolkit.rotations``). Any input size is resized (bilinear, antialiased — differentiable,
so the gaze loss can backpropagate through it) to ``input_size``.

Two independently trained instances (different seeds / data splits) are used: one frozen inside the gaze
loss, one held out for evaluation only, so the model is never trained on its metric.

Checkpoints are safetensors + JSON info (``toolkit.io.save_checkpoint``) with ``kind`` and the config, so a
wrong or incompatible file is a one-line ``ToolkitError``.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import asdict, dataclass
from typing import Callable

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.io import load_checkpoint, save_checkpoint
from toolkit.rotations import (
    angular_error_deg,
    normalized_head_rotation,
    pitchyaw_to_vector,
    vector_to_pitchyaw,
)

log = logging.getLogger(__name__)
CHECKPOINT_KIND = "ditgaze.gaze_estimator"
CHECKPOINT_VERSION = 1


@dataclass
class GazeEstimatorConfig:
    """Network shape."""

    input_size: int = 96
    """width the (cropped) input is resized to; the height follows the crop's aspect ratio."""
    crop: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)
    """(top, bottom, left, right) fractions of the image kept before resizing. The whole face crop by
    default; an eye band such as ``EYE_BAND`` spends every input pixel where the gaze is visible."""
    channels: tuple[int, ...] = (32, 64, 96, 128)
    """channels of the stride-2 stages (the input is downsampled 2^len(channels) times)."""
    hidden: int = 256
    dropout: float = 0.0
    head_frame: bool = True
    """predict gaze in the head frame plus the head pose, and compose the camera-frame gaze exactly
    (``toolkit.rotations.normalized_head_rotation``): the eyes' appearance in their sockets then maps to one
    output instead of being entangled with the view. False: regress camera-frame gaze directly."""


EYE_BAND = (0.3, 0.62, 0.24, 0.76)
"""Rows/columns of the project's normalized face crops (train/data, docs/data.md) that hold both eyes in
every view of the synthetic rig (measured from the eye landmarks 36-47 over all cameras, poses and gazes)."""


def head_to_camera_gaze(gaze_head: torch.Tensor, head_pose: torch.Tensor) -> torch.Tensor:
    """[B, 2] head-frame gaze, [B, 2] head pose (normalized camera) -> [B, 2] camera-frame gaze (pitch, yaw)."""
    g = (normalized_head_rotation(head_pose) @ pitchyaw_to_vector(gaze_head).unsqueeze(-1)).squeeze(-1)
    return vector_to_pitchyaw(g)


def camera_to_head_gaze(gaze_cam: torch.Tensor, head_pose: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`head_to_camera_gaze`: [B, 2] camera-frame gaze -> [B, 2] head-frame gaze."""
    R = normalized_head_rotation(head_pose)
    return vector_to_pitchyaw((R.transpose(-1, -2) @ pitchyaw_to_vector(gaze_cam).unsqueeze(-1)).squeeze(-1))


class ConvBlock(nn.Module):
    """conv3x3 (stride s) -> GroupNorm -> ReLU -> conv3x3 -> GroupNorm, plus a projected residual, -> ReLU."""

    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.norm1 = nn.GroupNorm(min(8, c_out), c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.norm2 = nn.GroupNorm(min(8, c_out), c_out)
        self.skip = nn.Conv2d(c_in, c_out, 1, stride, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = torch.relu(self.norm1(self.conv1(x)))
        return torch.relu(self.norm2(self.conv2(h)) + self.skip(x))


class GazeEstimator(nn.Module):
    """Face crop -> [gaze pitch, gaze yaw, head pitch, head yaw] (radians).

    GroupNorm rather than BatchNorm: the frozen instance then behaves the same in the gaze loss whatever
    the batch, and no running statistics can drift. The head flattens the final 4x4-ish map instead of
    global pooling: gaze lives in *where* the iris sits, which pooling would discard.
    """

    def __init__(self, config: GazeEstimatorConfig | None = None):
        super().__init__()
        self.config = cfg = config or GazeEstimatorConfig()
        top, bottom, left, right = cfg.crop
        if not (0.0 <= top < bottom <= 1.0 and 0.0 <= left < right <= 1.0):
            raise ToolkitError(f"GazeEstimatorConfig.crop: expected 0 <= top < bottom <= 1 and 0 <= left < right <= 1, "
                               f"got {cfg.crop}")
        self.input_hw = (max(1, round(cfg.input_size * (bottom - top) / (right - left))), cfg.input_size)
        if min(self.input_hw) < 2 ** len(cfg.channels) or not cfg.channels:
            raise ToolkitError(f"GazeEstimatorConfig: input {self.input_hw} too small for {len(cfg.channels)} stride-2 stages")
        self.stem = nn.Sequential(nn.Conv2d(3, cfg.channels[0], 3, 1, 1, bias=False),
                                  nn.GroupNorm(min(8, cfg.channels[0]), cfg.channels[0]), nn.ReLU())
        blocks, c = [], cfg.channels[0]
        for c_out in cfg.channels:
            blocks.append(ConvBlock(c, c_out, 2))
            c = c_out
        self.blocks = nn.Sequential(*blocks)
        h, w = self.input_hw
        for _ in cfg.channels:
            h, w = (h + 1) // 2, (w + 1) // 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * h * w, cfg.hidden), nn.ReLU(),
                                  nn.Dropout(cfg.dropout), nn.Linear(cfg.hidden, 4))

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        if images.dim() != 4 or images.shape[1] != 3:
            raise ToolkitError(f"GazeEstimator: images must be [B, 3, H, W] RGB in [0, 1], got {list(images.shape)}")
        H, W = images.shape[2:]
        top, bottom, left, right = self.config.crop
        r0, r1 = int(round(top * H)), max(int(round(top * H)) + 1, int(round(bottom * H)))
        c0, c1 = int(round(left * W)), max(int(round(left * W)) + 1, int(round(right * W)))
        images = images[:, :, r0:r1, c0:c1]
        h, w = self.input_hw
        if tuple(images.shape[2:]) != (h, w):
            images = F.interpolate(images, size=(h, w), mode="bilinear", align_corners=False,
                                   antialias=images.shape[2] > h or images.shape[3] > w)
        return (images - 0.5) / 0.25

    def forward_parts(self, images: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] -> [B, 4]: the network's own outputs, (head-frame gaze, head pose) when
        ``config.head_frame``, else (camera-frame gaze, head pose)."""
        return self.head(self.blocks(self.stem(self.preprocess(images))))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        out = self.forward_parts(images)
        if not self.config.head_frame:
            return out
        return torch.cat([head_to_camera_gaze(out[:, :2], out[:, 2:]), out[:, 2:]], 1)

    def gaze(self, images: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] -> [B, 2] gaze (pitch, yaw)."""
        return self(images)[:, :2]

    # ------------------------------------------------------------------ storage
    def save(self, path: str | os.PathLike, info: dict | None = None) -> None:
        """Write safetensors weights with {"kind", "version", "config", **info} as JSON metadata (atomic)."""
        meta = {"kind": CHECKPOINT_KIND, "version": CHECKPOINT_VERSION, "config": asdict(self.config)}
        meta.update(info or {})
        save_checkpoint(path, self.state_dict(), meta)

    @classmethod
    def load(cls, path: str | os.PathLike, device: str | torch.device = "cpu", *, frozen: bool = True) -> "GazeEstimator":
        """Read a checkpoint written by :meth:`save`; missing, foreign or incompatible files raise ToolkitError.

        ``frozen`` (default) returns it in eval mode with ``requires_grad=False`` on every parameter.
        """
        state, info = load_checkpoint(path, device)
        if info.get("kind") != CHECKPOINT_KIND:
            raise ToolkitError(f"{path}: not a gaze estimator checkpoint (kind={info.get('kind')!r}, expected {CHECKPOINT_KIND!r})")
        if not isinstance(info.get("version"), int) or info["version"] > CHECKPOINT_VERSION:
            raise ToolkitError(f"{path}: gaze estimator checkpoint version {info.get('version')!r} is not supported "
                               f"(this toolkit reads 1..{CHECKPOINT_VERSION})")
        raw = info.get("config")
        if not isinstance(raw, dict):
            raise ToolkitError(f"{path}: gaze estimator checkpoint has no 'config' in its metadata")
        known = set(GazeEstimatorConfig.__dataclass_fields__)
        unknown = sorted(set(raw) - known)
        if unknown:
            raise ToolkitError(f"{path}: unknown gaze estimator config field(s) {unknown}")
        raw = dict(raw)
        for key in ("channels", "crop"):
            if key in raw:
                raw[key] = tuple(raw[key])
        try:
            model = cls(GazeEstimatorConfig(**raw))
        except (TypeError, ValueError) as e:
            raise ToolkitError(f"{path}: bad gaze estimator config ({e})") from None
        own = model.state_dict()
        for k, v in own.items():
            if k not in state:
                raise ToolkitError(f"{path}: missing tensor {k!r} for the configured gaze estimator")
            if tuple(state[k].shape) != tuple(v.shape):
                raise ToolkitError(f"{path}: tensor {k!r} has shape {list(state[k].shape)}, expected {list(v.shape)}")
        extra = sorted(set(state) - set(own))
        if extra:
            raise ToolkitError(f"{path}: unexpected tensor(s) {extra[:3]} for a gaze estimator")
        model.load_state_dict(state)
        model.to(device)
        if frozen:
            model.eval()
            for p in model.parameters():
                p.requires_grad_(False)
        return model


# ----------------------------------------------------------------------------- training
@dataclass
class GazeEstimatorTrainConfig:
    """Trainer settings (Adam, cosine learning-rate decay, light augmentation)."""

    steps: int = 3000
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    head_weight: float = 0.5
    """weight of the head pitch/yaw L1 term relative to the gaze term."""
    loss_space: str = "vectors"
    """"vectors": L1 between unit direction vectors of prediction and label (no ±180° yaw wrap-around, every
    direction weighted by its angle); "angles": L1 on raw (pitch, yaw) radians."""
    augment: bool = True
    brightness: float = 0.15
    contrast: float = 0.15
    noise: float = 0.02
    max_shift: float = 0.03
    """largest random translation, as a fraction of the image size (labels are unchanged by a small shift)."""
    seed: int = 0
    log_every: int = 250


def augment_batch(images: torch.Tensor, cfg: GazeEstimatorTrainConfig, g: torch.Generator) -> torch.Tensor:
    """Light photometric jitter, Gaussian noise and a small integer shift (edge-replicated), [B, 3, H, W]."""
    B, _, H, W = images.shape
    dev = images.device
    b = (torch.rand(B, 1, 1, 1, generator=g) * 2 - 1).to(dev) * cfg.brightness
    c = 1 + (torch.rand(B, 1, 1, 1, generator=g) * 2 - 1).to(dev) * cfg.contrast
    mean = images.mean(dim=(1, 2, 3), keepdim=True)
    x = (images - mean) * c + mean + b
    x = x + torch.randn(x.shape, generator=g).to(dev) * cfg.noise
    ms = int(round(cfg.max_shift * min(H, W)))
    if ms > 0:
        dx, dy = (int(v) for v in torch.randint(-ms, ms + 1, (2,), generator=g))
        x = F.pad(x, (ms, ms, ms, ms), mode="replicate")[:, :, ms + dy:ms + dy + H, ms + dx:ms + dx + W]
    return x.clamp(0, 1)


def _check_data(images: torch.Tensor, labels: torch.Tensor, name: str) -> None:
    if images.dim() != 4 or images.shape[1] != 3:
        raise ToolkitError(f"{name} images: expected [N, 3, H, W], got {list(images.shape)}")
    if labels.shape != (images.shape[0], 4):
        raise ToolkitError(f"{name} labels: expected [N={images.shape[0]}, 4] (gaze pitch, yaw, head pitch, yaw), got {list(labels.shape)}")
    if not bool(torch.isfinite(labels).all()):
        raise ToolkitError(f"{name} labels: contain NaN or inf")


def _to_float(images: torch.Tensor) -> torch.Tensor:
    return images.float() / 255.0 if images.dtype == torch.uint8 else images.float()


def train_gaze_estimator(images: torch.Tensor, labels: torch.Tensor, config: GazeEstimatorConfig | None = None,
                         train_config: GazeEstimatorTrainConfig | None = None, *,
                         val: tuple[torch.Tensor, torch.Tensor] | None = None, device: str | torch.device = "cpu",
                         callback: Callable[[int, dict], None] | None = None) -> tuple[GazeEstimator, list[dict]]:
    """Train a :class:`GazeEstimator` on in-memory data.

    Args:
        images: [N, 3, H, W] uint8 or float in [0, 1]; labels: [N, 4] radians (gaze pitch, yaw, head pitch, yaw).
        val: optional held-out (images, labels) evaluated every ``log_every`` steps.
    Returns:
        (model in eval mode, history: list of {"step", "loss", ["val_gaze_deg", "val_head_deg"]}).
    """
    tc = train_config or GazeEstimatorTrainConfig()
    _check_data(images, labels, "train")
    if val is not None:
        _check_data(*val, "val")
    if tc.loss_space not in ("vectors", "angles"):
        raise ToolkitError(f"GazeEstimatorTrainConfig.loss_space: expected 'vectors' or 'angles', got {tc.loss_space!r}")
    if tc.steps < 1 or tc.batch_size < 1:
        raise ToolkitError(f"GazeEstimatorTrainConfig: steps and batch_size must be >= 1, got {tc.steps}, {tc.batch_size}")
    torch.manual_seed(tc.seed)
    g = torch.Generator().manual_seed(tc.seed)
    model = GazeEstimator(config).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s, tc.steps) / tc.steps)))
    n = images.shape[0]
    w = torch.tensor([1.0, 1.0, tc.head_weight, tc.head_weight], device=device)
    history: list[dict] = []
    perm, pos = torch.randperm(n, generator=g), 0
    model.train()
    for step in range(1, tc.steps + 1):
        if pos + tc.batch_size > n:
            perm, pos = torch.randperm(n, generator=g), 0
        idx = perm[pos:pos + tc.batch_size]
        pos += tc.batch_size
        x = _to_float(images[idx]).to(device)
        y = labels[idx].float().to(device)
        if tc.augment:
            x = augment_batch(x, tc, g)
        parts = model.forward_parts(x)
        pred = parts if not model.config.head_frame else \
            torch.cat([head_to_camera_gaze(parts[:, :2], parts[:, 2:]), parts[:, 2:]], 1)
        if tc.loss_space == "vectors":
            pv = torch.cat([pitchyaw_to_vector(pred[:, :2]), pitchyaw_to_vector(pred[:, 2:])], -1)
            yv = torch.cat([pitchyaw_to_vector(y[:, :2]), pitchyaw_to_vector(y[:, 2:])], -1)
            d = (pv - yv).abs()
            loss = d[:, :3].mean() + tc.head_weight * d[:, 3:].mean()
            if model.config.head_frame:
                # Supervise the head-frame gaze too: it is what the eyes show, whatever the view.
                d_h = pitchyaw_to_vector(parts[:, :2]) - pitchyaw_to_vector(camera_to_head_gaze(y[:, :2], y[:, 2:]))
                loss = loss + d_h.abs().mean()
        else:
            loss = ((pred - y).abs() * w).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if step % tc.log_every == 0 or step == tc.steps:
            rec = {"step": step, "loss": float(loss.detach())}
            if val is not None:
                rec.update(evaluate_gaze_estimator(model, *val, device=device))
                model.train()
            history.append(rec)
            log.info("gaze estimator step %d: %s", step, rec)
            if callback is not None:
                callback(step, rec)
    model.eval()
    return model, history


@torch.no_grad()
def evaluate_gaze_estimator(model: GazeEstimator, images: torch.Tensor, labels: torch.Tensor, *,
                            batch_size: int = 256, device: str | torch.device = "cpu") -> dict[str, float]:
    """Mean angular errors in degrees on (images [N, 3, H, W], labels [N, 4]): {"val_gaze_deg", "val_head_deg"}."""
    _check_data(images, labels, "eval")
    was = model.training
    model.eval()
    g_err, h_err = [], []
    for i in range(0, images.shape[0], batch_size):
        x = _to_float(images[i:i + batch_size]).to(device)
        y = labels[i:i + batch_size].float().to(device)
        p = model(x)
        g_err.append(angular_error_deg(p[:, :2], y[:, :2]).cpu())
        h_err.append(angular_error_deg(p[:, 2:], y[:, 2:]).cpu())
    model.train(was)
    return {"val_gaze_deg": float(torch.cat(g_err).mean()), "val_head_deg": float(torch.cat(h_err).mean())}
