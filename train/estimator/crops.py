"""Face-crop geometry the gaze estimator reads: both eyes cut out at their landmarks (:func:`eye_patches`),
the pixels those cuts touch (:func:`eye_patch_box`), and the left-right mirror of a face with its labels and
landmarks (:func:`mirror_faces`). Landmarks are iBUG-68 (x, y) pixels."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError

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

