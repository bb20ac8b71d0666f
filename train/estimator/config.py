"""The gaze estimator's settings: its network shape (:class:`GazeEstimatorConfig`, the eye-patch design
:func:`eye_config`) and its trainer's (:class:`GazeEstimatorTrainConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from toolkit.errors import ToolkitError


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
    """read two eye patches cut at the eye landmarks (iBUG 36-41 and 42-47, see
    :func:`train.estimator.crops.eye_patches`) plus the 68-landmark layout instead of the whole face. Every
    call then needs the image's landmarks. At 128² an eye is ~12 px wide: a whole-face CNN does not learn to
    find and read it, a patch at the eye does."""
    eye_patch: tuple[int, int] = (24, 36)
    """(height, width) of each resampled eye patch; the patch spans 1.2 x 2 eye widths (corner to corner)."""
    mirror_average: bool = False
    """every ``forward`` call (inference, validation, and the gaze loss, gradients through both branches) also
    reads the left-right mirrored image (:func:`train.estimator.crops.mirror_faces`) and averages the two
    directions: the network's left-right biases cancel, at twice the cost (held-out error of the eye design
    4.0° -> 3.7°). The estimator's own training steps read one image each. :func:`eye_config` turns it on."""
    head_frame: bool = True
    """True (default): predict gaze in the head frame plus the head pose, and compose the camera-frame gaze
    exactly (``toolkit.rotations.normalized_head_rotation``). False: regress the camera-frame gaze directly,
    which avoids adding the head-pose estimate's error where the view is extreme: better with long training
    (3000 steps: held-out 3.84° -> 3.40°), worse in the demo's 1000-step stage (docs/results.md, 2026-11-22)."""


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
    """probability of mirroring a training sample left-right (:func:`train.estimator.crops.mirror_faces`: labels
    follow exactly); part of the augmentation, so ``augment=False`` turns it off too.
    Held-out error of the eye design, 240 subjects x 32 frames, 3000 steps: 4.3° without, 4.0° with."""
    blur_prob: float = 0.0
    """probability of blurring a training image (:func:`train.estimator.augment.random_blur`) before the eyes are
    cut out, so the estimator reads the same gaze from a softer render of the same eyes; part of the
    augmentation."""
    blur_sigma: float = 1.2
    """largest Gaussian blur standard deviation, pixels of the full image (drawn uniformly in [0, blur_sigma])."""
    warmup_steps: int = 0
    """steps of a linear learning-rate warm-up (from ``lr / warmup_steps`` to ``lr``) before the cosine decay,
    >= 0; 0: none, the first step at the full rate. Without it AdamW's first steps at 2e-3 throw a freshly
    initialized estimator off (its loss rises from 1.0 to ~1.8), and some seeds never recover (docs/results.md,
    2026-11-27)."""
    seed: int = 0
    log_every: int = 250

    def validate(self) -> None:
        """ToolkitError naming the first field no training can run with."""
        if self.loss_space not in ("vectors", "angles"):
            raise ToolkitError(f"GazeEstimatorTrainConfig.loss_space: expected 'vectors' or 'angles', got {self.loss_space!r}")
        for name in ("mirror", "blur_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ToolkitError(f"GazeEstimatorTrainConfig.{name}: expected a probability in [0, 1], "
                                   f"got {getattr(self, name)}")
        if not self.blur_sigma >= 0:
            raise ToolkitError(f"GazeEstimatorTrainConfig.blur_sigma: expected a width >= 0 (pixels), got {self.blur_sigma}")
        if not self.warmup_steps >= 0:
            raise ToolkitError(f"GazeEstimatorTrainConfig.warmup_steps: expected a step count >= 0, got {self.warmup_steps}")
        if self.steps < 1 or self.batch_size < 1:
            raise ToolkitError(f"GazeEstimatorTrainConfig: steps and batch_size must be >= 1, got {self.steps}, "
                               f"{self.batch_size}")


