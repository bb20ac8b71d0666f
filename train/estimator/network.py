"""A compact CNN gaze estimator (no torchvision) and its checkpoints.

``GazeEstimator(images [B, 3, H, W] RGB in [0, 1]) -> [B, 4]``: gaze (pitch, yaw) then head (pitch, yaw), radians,
ETH-XGaze convention (``toolkit.rotations``). Any input size is resized (bilinear, antialiased — differentiable,
so the gaze loss can backpropagate through it) to ``input_size``.

Two independently trained instances (different seeds / data splits) are used: one frozen inside the gaze
loss, one held out for evaluation only, so the model is never trained on its metric.

Checkpoints are safetensors + JSON info (``toolkit.io.save_checkpoint``) with ``kind`` and the config, so a
wrong or incompatible file is a one-line ``ToolkitError``.
"""

from __future__ import annotations

import os
from dataclasses import asdict

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.io import load_checkpoint, nonfinite_tensors, save_checkpoint
from toolkit.rotations import head_to_camera_gaze
from train.estimator.config import GazeEstimatorConfig
from train.estimator.crops import MIRROR_SIGNS, eye_patches, mirror_faces
from train.estimator.frames import mean_direction

CHECKPOINT_KIND = "ditgaze.gaze_estimator"
CHECKPOINT_VERSION = 1


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
        self.input_hw = tuple(cfg.eye_patch) if cfg.eyes else \
            (max(1, round(cfg.input_size * (bottom - top) / (right - left))), cfg.input_size)
        if min(self.input_hw) < 2 ** len(cfg.channels) or not cfg.channels:
            raise ToolkitError(f"GazeEstimatorConfig: input {self.input_hw} too small for {len(cfg.channels)} stride-2 stages")
        c_in = 6 if cfg.eyes else 3
        self.stem = nn.Sequential(nn.Conv2d(c_in, cfg.channels[0], 3, 1, 1, bias=False),
                                  nn.GroupNorm(min(8, cfg.channels[0]), cfg.channels[0]), nn.ReLU())
        blocks, c = [], cfg.channels[0]
        for c_out in cfg.channels:
            blocks.append(ConvBlock(c, c_out, 2))
            c = c_out
        self.blocks = nn.Sequential(*blocks)
        h, w = self.input_hw
        for _ in cfg.channels:
            h, w = (h + 1) // 2, (w + 1) // 2
        n_feat = c * h * w
        if cfg.eyes:
            # The landmark layout carries the head pose and where the face sits; the patches carry the eyes.
            self.layout = nn.Sequential(nn.Linear(136, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, cfg.hidden), nn.ReLU())
            n_feat += cfg.hidden
        self.head = nn.Sequential(nn.Linear(n_feat, cfg.hidden), nn.ReLU(),
                                  nn.Dropout(cfg.dropout), nn.Linear(cfg.hidden, 4))

    @staticmethod
    def _check_images(images: torch.Tensor) -> None:
        if images.dim() != 4 or images.shape[1] != 3:
            raise ToolkitError(f"GazeEstimator: images must be [B, 3, H, W] RGB in [0, 1], got {list(images.shape)}")

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        self._check_images(images)
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

    def forward_parts(self, images: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 3, H, W] (+ [B, 68, 2] landmarks when ``config.eyes``) -> [B, 4]: the network's own outputs,
        (head-frame gaze, head pose) when ``config.head_frame``, else (camera-frame gaze, head pose)."""
        if not self.config.eyes:
            return self.head(self.blocks(self.stem(self.preprocess(images))).flatten(1))
        self._check_images(images)
        return self.from_eye_inputs(*self.eye_inputs(images, self._eye_landmarks(images, landmarks)))

    def _eye_landmarks(self, images: torch.Tensor, landmarks: torch.Tensor | None) -> torch.Tensor:
        """The [B, 68, 2] landmarks an eye-patch estimator needs, on the images' device and dtype, or ToolkitError."""
        B = images.shape[0]
        if landmarks is None or tuple(landmarks.shape) != (B, 68, 2):
            raise ToolkitError(f"GazeEstimator: this estimator reads eye patches and needs the images' landmarks "
                               f"[B={B}, 68, 2] pixels, got {None if landmarks is None else list(landmarks.shape)}")
        return landmarks.to(images.device, images.dtype)

    def eye_inputs(self, images: torch.Tensor, landmarks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What an eye-patch estimator reads: ([B, 6, h, w] eye patches in [0, 1], [B, 136] landmark layout
        in [-1, 1] of the image). Split out so training can augment the small patches, not the whole image."""
        landmarks = landmarks.to(images.device, images.dtype)
        H, W = images.shape[2:]
        layout = (landmarks / landmarks.new_tensor([W, H]) * 2 - 1).flatten(1)
        return eye_patches(images, landmarks, self.input_hw), layout

    def from_eye_inputs(self, patches: torch.Tensor, layout: torch.Tensor) -> torch.Tensor:
        """:meth:`eye_inputs` -> [B, 4], the outputs of :meth:`forward_parts`."""
        x = self.blocks(self.stem((patches - 0.5) / 0.25)).flatten(1)
        return self.head(torch.cat([x, self.layout(layout)], 1))

    def compose(self, parts: torch.Tensor) -> torch.Tensor:
        """:meth:`forward_parts` outputs -> [B, 4] (camera-frame gaze, head pose)."""
        if not self.config.head_frame:
            return parts
        return torch.cat([head_to_camera_gaze(parts[:, :2], parts[:, 2:]), parts[:, 2:]], 1)

    def forward(self, images: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 3, H, W] (+ [B, 68, 2] landmarks for eye-patch estimators) -> [B, 4] camera-frame gaze, head pose."""
        if not self.config.mirror_average:
            return self.compose(self.forward_parts(images, landmarks))
        self._check_images(images)
        B = images.shape[0]
        # Whole-face designs ignore landmarks; eye designs check them before the batch doubles.
        landmarks = self._eye_landmarks(images, landmarks) if self.config.eyes else None
        mirrored, _, lm_m = mirror_faces(images, None, landmarks)
        both = self.compose(self.forward_parts(torch.cat([images, mirrored]),
                                               None if landmarks is None else torch.cat([landmarks, lm_m])))
        plain, back = both[:B], both[B:] * both.new_tensor(MIRROR_SIGNS)
        return torch.cat([mean_direction(plain[:, :2], back[:, :2]), mean_direction(plain[:, 2:], back[:, 2:])], 1)

    def gaze(self, images: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 3, H, W] -> [B, 2] gaze (pitch, yaw)."""
        return self(images, landmarks)[:, :2]

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
        for key in ("channels", "crop", "eye_patch"):
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
        if broken := nonfinite_tensors(state):
            raise ToolkitError(f"{path}: tensor {broken[0]!r} holds NaN or inf (a diverged training?)")
        model.load_state_dict(state)
        model.to(device)
        if frozen:
            model.eval()
            for p in model.parameters():
                p.requires_grad_(False)
        return model

