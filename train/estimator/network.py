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
import time
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
    eyes: bool = False
    """read two eye patches cut at the eye landmarks (iBUG 36-41 and 42-47, see :func:`eye_patches`) plus the
    68-landmark layout instead of the whole face. Every call then needs the image's landmarks. At 128²
    an eye is ~12 px wide: a whole-face CNN does not learn to find and read it, a patch at the eye does."""
    eye_patch: tuple[int, int] = (24, 36)
    """(height, width) of each resampled eye patch; the patch spans 1.2 x 2 eye widths (corner to corner)."""
    mirror_average: bool = False
    """every ``forward`` call (inference, validation, and the gaze loss, gradients through both branches) also
    reads the left-right mirrored image (:func:`mirror_faces`) and averages the two directions: the network's
    left-right biases cancel, at twice the cost (held-out error of the eye design 4.0° -> 3.7°). The
    estimator's own training steps read one image each. :func:`eye_config` turns it on."""
    head_frame: bool = True
    """True (default): predict gaze in the head frame plus the head pose, and compose the camera-frame gaze
    exactly (``toolkit.rotations.normalized_head_rotation``). False: regress the camera-frame gaze directly,
    which avoids adding the head-pose estimate's error where the view is extreme: better after 3000 steps on
    7680 images (eye design, 128²: held-out 3.84° -> 3.40°, worst image 68° -> 24°), worse in the demo's
    estimator stage (1000 steps: 6.6° / 6.7° -> 7.8° / 7.0°), so not the default (docs/model.md)."""


EYE_BAND = (0.3, 0.62, 0.24, 0.76)
"""Rows/columns of the project's normalized face crops (train/data, docs/data.md) that hold both eyes in
every view of the synthetic rig (measured from the eye landmarks 36-47 over all cameras, poses and gazes)."""


EYE_CHANNELS = (32, 64, 96)
"""stride-2 stages of the eye-patch design (a 24 x 36 patch pair: three halvings leave 3 x 5)."""


def eye_config(image_size: int) -> GazeEstimatorConfig:
    """The eye-patch design for face crops of ``image_size`` pixels.

    The patch keeps ~1.5 samples per image pixel across the eye (24 x 36 at 128², doubling with each doubling
    of the image), and each doubling adds a stride-2 stage (128 channels) so the last map stays 3 x 5.
    A fixed 24 x 36 patch would undersample larger images: the iris position, the very thing being read,
    would be no more precise at 512² than at 128².
    """
    if image_size < 16:
        raise ToolkitError(f"eye_config: image size must be >= 16 pixels, got {image_size}")
    doublings = max(0, round(math.log2(image_size / 128)))
    k = 2 ** doublings
    return GazeEstimatorConfig(eyes=True, eye_patch=(24 * k, 36 * k), channels=EYE_CHANNELS + (128,) * doublings,
                               mirror_average=True)

LEFT_EYE, RIGHT_EYE = slice(36, 42), slice(42, 48)  # iBUG-68 indices; "left" = image-left (GazeGaussian)

IBUG_MIRROR = (tuple(range(16, -1, -1)) + tuple(range(26, 16, -1)) + (27, 28, 29, 30) + (35, 34, 33, 32, 31)
               + (45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40)
               + (54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55) + (64, 63, 62, 61, 60, 67, 66, 65))
"""iBUG-68 index of each landmark's left-right counterpart (jaw, brows, nose base, eyes and lips swap sides)."""


MIRROR_SIGNS = (1.0, -1.0, 1.0, -1.0)
"""What a left-right mirror does to (gaze pitch, yaw, head pitch, yaw): both yaws change sign."""


def mirror_faces(images: torch.Tensor, labels: torch.Tensor | None = None, landmarks: torch.Tensor | None = None,
                 which: torch.Tensor | None = None):
    """Mirror normalized face crops left-right, with their labels and landmarks.

    Args:
        images: [B, C, H, W]; labels: [B, 4] (gaze pitch, yaw, head pitch, yaw), camera frame, or None;
        landmarks: [B, 68, 2] pixels or None; which: [B] bool, the samples to mirror (default all).
    Returns:
        (images, labels, landmarks) with the chosen samples mirrored (None stays None). The normalized
        camera's principal point is the image centre, so the mirror is x -> W - x in the camera frame: both
        yaws change sign, pitches stay, and the head-frame gaze mirrors the same way
        (``normalized_head_rotation`` of the mirrored pose is M R M, M = diag(-1, 1, 1)). Landmarks swap
        with their counterparts (``IBUG_MIRROR``).
    """
    B, _, H, W = images.shape
    which = torch.ones(B, dtype=torch.bool, device=images.device) if which is None else which.to(images.device)
    if bool(which.all()):
        images = images.flip(-1)
    elif bool(which.any()):  # flip the chosen ones alone: a masked select of two whole batches costs 4x more
        images = images.clone()
        images[which] = images[which].flip(-1)
    if labels is not None:
        labels = torch.where(which[:, None], labels * labels.new_tensor(MIRROR_SIGNS), labels)
    if landmarks is not None:
        m = landmarks[:, list(IBUG_MIRROR)] * landmarks.new_tensor([-1.0, 1.0]) + landmarks.new_tensor([W, 0.0])
        landmarks = torch.where(which[:, None, None], m, landmarks)
    return images, labels, landmarks


def eye_patches(images: torch.Tensor, landmarks: torch.Tensor, size: tuple[int, int] = (24, 36)) -> torch.Tensor:
    """Cut both eyes out of face images, differentiably (bilinear ``grid_sample``).

    Args:
        images: [B, C, H, W]. landmarks: [B, 68, 2] iBUG-68 (x, y) pixel coordinates of the same images
            (pixel centres at integer + 0.5 convention-free: x = 0 is the left edge of column 0).
        size: (h, w) of each patch.
    Returns:
        [B, 2 C, h, w]: the image-left eye's channels, then the image-right eye's. Each window is centred on
        the mean of the eye's six landmarks, spans 2 x 1.2 eye widths (corner to corner, at least 2 px) and is
        turned with the line through the corners, so the patch is invariant to in-plane roll and scale.
    """
    B, C, H, W = images.shape
    if landmarks.shape != (B, 68, 2):
        raise ToolkitError(f"eye_patches: landmarks must be [B={B}, 68, 2] pixels, got {list(landmarks.shape)}")
    h, w = size
    out = []
    for centre, cos, sin, half_w, half_h in _eye_windows(landmarks):
        # affine_grid maps output coords in [-1, 1] to input coords in [-1, 1] (align_corners=False).
        theta = torch.stack([
            torch.stack([cos * half_w * 2 / W, -sin * half_h * 2 / W, centre[:, 0] * 2 / W - 1], -1),
            torch.stack([sin * half_w * 2 / H, cos * half_h * 2 / H, centre[:, 1] * 2 / H - 1], -1)], 1)
        grid = F.affine_grid(theta.to(images.dtype), [B, C, h, w], align_corners=False)
        out.append(F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=False))
    return torch.cat(out, 1)


def _eye_windows(landmarks: torch.Tensor):
    """Per eye (image-left, then image-right) of [B, 68, 2] landmarks: (centre [B, 2], cos [B], sin [B],
    half width [B], half height [B]) of the turned window :func:`eye_patches` samples, in pixels."""
    for sl in (LEFT_EYE, RIGHT_EYE):
        pts = landmarks[:, sl].float()
        centre = pts.mean(1)
        axis = pts[:, 3] - pts[:, 0]  # outer/inner corners: 36 -> 39, 42 -> 45
        width = axis.norm(dim=-1).clamp_min(2.0)
        cos, sin = (axis / width.unsqueeze(-1)).unbind(-1)
        yield centre, cos, sin, width, 0.6 * width


def eye_patch_box(landmarks: torch.Tensor, H: int, W: int, margin: int = 0) -> tuple[int, int, int, int]:
    """The pixel box ``(y0, y1, x0, x1)`` (ends excluded, inside the H x W image) holding every pixel that
    :func:`eye_patches` reads for any sample of the batch [B, 68, 2], both eyes, widened by ``margin`` pixels
    (a bilinear read at pixel position p touches floor(p) and floor(p) + 1; the border mode clamps to the image)."""
    xs, ys = [], []
    for centre, cos, sin, half_w, half_h in _eye_windows(landmarks):
        for u, v in ((-1, -1), (-1, 1), (1, -1), (1, 1)):  # the window's corners; pixel centres sit at + 0.5
            xs.append(centre[:, 0] + cos * half_w * u - sin * half_h * v - 0.5)
            ys.append(centre[:, 1] + sin * half_w * u + cos * half_h * v - 0.5)
    x, y = torch.cat(xs), torch.cat(ys)
    if not (torch.isfinite(x).all() and torch.isfinite(y).all()):
        return 0, H, 0, W
    x0, x1 = math.floor(float(x.min())) - margin, math.floor(float(x.max())) + 2 + margin
    y0, y1 = math.floor(float(y.min())) - margin, math.floor(float(y.max())) + 2 + margin
    y0, y1, x0, x1 = max(0, min(y0, H)), max(0, min(y1, H)), max(0, min(x0, W)), max(0, min(x1, W))
    return (0, H, 0, W) if y1 <= y0 or x1 <= x0 else (y0, y1, x0, x1)


def mean_direction(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[B, 2] (pitch, yaw) x 2 -> [B, 2]: the direction halfway between (``a`` where they are opposite)."""
    va, vb = pitchyaw_to_vector(a), pitchyaw_to_vector(b)
    s = va + vb
    # |a + b| = 2 cos(angle / 2): the guard keeps the normalization's gradient (~1 / |a + b|) bounded too.
    return vector_to_pitchyaw(torch.where(s.norm(dim=-1, keepdim=True) > 1e-3, s, va))


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
        broken = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
        if broken:
            raise ToolkitError(f"{path}: tensor {broken[0]!r} holds NaN or inf (a diverged training?)")
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
    landmark_noise: float = 0.3
    """standard deviation (pixels) of the jitter added to the landmarks of eye-patch estimators."""
    mirror: float = 0.5
    """probability of mirroring a training sample left-right (:func:`mirror_faces`: labels follow exactly);
    part of the augmentation, so ``augment=False`` turns it off too.
    Held-out error of the eye design, 240 subjects x 32 frames, 3000 steps: 4.3° without, 4.0° with."""
    blur_prob: float = 0.0
    """probability of blurring a training image (:func:`random_blur`) before the eyes are cut out, so the
    estimator reads the same gaze from a softer render of the same eyes; part of the augmentation."""
    blur_sigma: float = 1.2
    """largest Gaussian blur standard deviation, pixels of the full image (drawn uniformly in [0, blur_sigma])."""
    seed: int = 0
    log_every: int = 250


BLUR_BOX_MARGIN = 8
"""Pixels added around :func:`eye_patch_box` before the landmark jitter (``landmark_noise``, 0.3 px by default)
moves the eye windows: a move of more than ~5 px, which such jitter never draws, would read unblurred pixels."""


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
    (eye-patch training reads :func:`eye_patch_box` alone: ~1/4 of the pixels).

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


def _check_landmarks(landmarks: torch.Tensor | None, n: int, model_needs: bool, name: str) -> None:
    if model_needs and landmarks is None:
        raise ToolkitError(f"{name}: this estimator reads eye patches; landmarks [N, 68, 2] are required")
    if landmarks is not None:
        if tuple(landmarks.shape) != (n, 68, 2):
            raise ToolkitError(f"{name} landmarks: expected [N={n}, 68, 2] pixels, got {list(landmarks.shape)}")
        if not bool(torch.isfinite(landmarks).all()):
            raise ToolkitError(f"{name} landmarks: contain NaN or inf")


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
                         landmarks: torch.Tensor | None = None, val: tuple | None = None,
                         device: str | torch.device = "cpu", init: GazeEstimator | None = None,
                         callback: Callable[[int, dict], None] | None = None,
                         on_step: Callable[[int, float], None] | None = None) -> tuple[GazeEstimator, list[dict]]:
    """Train a :class:`GazeEstimator` on in-memory data.

    Args:
        images: [N, 3, H, W] uint8 or float in [0, 1]; labels: [N, 4] radians (camera-frame gaze pitch, yaw,
            head pitch, yaw in the normalized camera).
        landmarks: [N, 68, 2] pixels, required by eye-patch estimators (``config.eyes``).
        val: optional held-out (images, labels[, landmarks]) evaluated every ``log_every`` steps.
        init: start from this estimator's weights (fine-tuning; the learning-rate schedule starts afresh); its
            configuration must equal ``config``.
        callback: called as ``callback(step, record)`` after each history record, the record with one more key,
            ``val_s``: the wall seconds its held-out evaluation took (0 without ``val``), so a caller can time
            training alone. Timings stay out of the history, which is deterministic for a seed.
        on_step: called as ``on_step(step, loss)`` after every step (a progress bar's hook).
    Returns:
        (model in eval mode, history: list of {"step", "loss", ["val_gaze_deg", "val_head_deg"]}).
    """
    tc = train_config or GazeEstimatorTrainConfig()
    needs = bool(config is not None and config.eyes)
    _check_data(images, labels, "train")
    _check_landmarks(landmarks, images.shape[0], needs, "train")
    if val is not None:
        _check_data(val[0], val[1], "val")
        _check_landmarks(val[2] if len(val) > 2 else None, val[0].shape[0], needs, "val")
    if tc.loss_space not in ("vectors", "angles"):
        raise ToolkitError(f"GazeEstimatorTrainConfig.loss_space: expected 'vectors' or 'angles', got {tc.loss_space!r}")
    if not 0.0 <= tc.mirror <= 1.0:
        raise ToolkitError(f"GazeEstimatorTrainConfig.mirror: expected a probability in [0, 1], got {tc.mirror}")
    if not (0.0 <= tc.blur_prob <= 1.0 and tc.blur_sigma >= 0):
        raise ToolkitError(f"GazeEstimatorTrainConfig: expected blur_prob in [0, 1] and blur_sigma >= 0, got "
                           f"{tc.blur_prob}, {tc.blur_sigma}")
    if tc.steps < 1 or tc.batch_size < 1:
        raise ToolkitError(f"GazeEstimatorTrainConfig: steps and batch_size must be >= 1, got {tc.steps}, {tc.batch_size}")
    torch.manual_seed(tc.seed)
    g = torch.Generator().manual_seed(tc.seed)
    model = GazeEstimator(config).to(device)
    if init is not None:
        if init.config != model.config:
            raise ToolkitError(f"train_gaze_estimator: init has configuration {init.config}, expected {model.config}")
        model.load_state_dict(init.state_dict())
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
        x = _to_float(images[idx].to(device, non_blocking=True))  # uint8 travels: 4x fewer bytes than float
        y = labels[idx].float().to(device)
        lm = landmarks[idx].float().to(device) if landmarks is not None else None
        if tc.augment and tc.mirror > 0:
            x, y, lm = mirror_faces(x, y, lm, torch.rand(len(idx), generator=g) < tc.mirror)
        if tc.augment and tc.blur_prob > 0:
            # Eye-patch designs read the eyes alone: blur their box, widened for the landmark jitter drawn next.
            box = (eye_patch_box(lm, x.shape[2], x.shape[3], margin=BLUR_BOX_MARGIN) if model.config.eyes
                   else None)
            x = random_blur(x, tc.blur_prob, tc.blur_sigma, g, box)
        if model.config.eyes:
            eye_in = augment_eye_inputs(x, lm, model, tc, g) if tc.augment else model.eye_inputs(x, lm)
            parts = model.from_eye_inputs(*eye_in)
        else:
            parts = model.forward_parts(augment_batch(x, tc, g) if tc.augment else x)
        pred = model.compose(parts)
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
        if not torch.isfinite(loss):  # never a silent NaN estimator: every later reading would be NaN
            raise ToolkitError(f"train_gaze_estimator: non-finite loss at step {step} ({float(loss.detach())}); the estimator "
                               "keeps no checkpoint, nothing was saved: check the training images and labels for "
                               "NaN, or lower the learning rate")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if on_step is not None:
            on_step(step, float(loss.detach()))
        if step % tc.log_every == 0 or step == tc.steps:
            rec, val_s = {"step": step, "loss": float(loss.detach())}, 0.0
            if val is not None:
                t0 = time.perf_counter()
                rec.update(evaluate_gaze_estimator(model, *val, device=device))
                val_s = time.perf_counter() - t0
                model.train()
            history.append(rec)
            log.info("gaze estimator step %d: %s", step, rec)
            if callback is not None:
                callback(step, dict(rec, val_s=val_s))
    model.eval()
    return model, history


@torch.no_grad()
def evaluate_gaze_estimator(model: GazeEstimator, images: torch.Tensor, labels: torch.Tensor,
                            landmarks: torch.Tensor | None = None, *, batch_size: int = 256,
                            device: str | torch.device = "cpu") -> dict[str, float]:
    """Mean angular errors in degrees on (images [N, 3, H, W], labels [N, 4], landmarks [N, 68, 2] for
    eye-patch estimators): {"val_gaze_deg", "val_head_deg"}."""
    _check_data(images, labels, "eval")
    _check_landmarks(landmarks, images.shape[0], model.config.eyes, "eval")
    was = model.training
    model.eval()
    g_err, h_err = [], []
    for i in range(0, images.shape[0], batch_size):
        x = _to_float(images[i:i + batch_size].to(device))
        y = labels[i:i + batch_size].float().to(device)
        lm = landmarks[i:i + batch_size].float().to(device) if landmarks is not None else None
        p = model(x, lm)
        g_err.append(angular_error_deg(p[:, :2], y[:, :2]).cpu())
        h_err.append(angular_error_deg(p[:, 2:], y[:, 2:]).cpu())
    model.train(was)
    return {"val_gaze_deg": float(torch.cat(g_err).mean()), "val_head_deg": float(torch.cat(h_err).mean())}
