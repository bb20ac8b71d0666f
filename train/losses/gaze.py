"""The gaze loss of DiT-Gaze, and the head-to-camera gaze conversion it needs.

:class:`GazeLoss` — a frozen gaze estimator ψ; angular error (degrees) between ψ(render) and ψ(target image), or
between ψ(render) and a given gaze (weak supervision with the sampled intermediate gaze). Computed in float32
even under autocast.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from toolkit.errors import ToolkitError
from toolkit.rotations import angular_error_deg
from train.losses.precision import fp32, no_autocast


class GazeLoss(nn.Module):
    """Angular error in degrees between a frozen estimator's gaze on the render and on the target.

    ``forward(render [B, 3, H, W], target_image=None, target_gaze=None [B, 2] pitch/yaw) -> [] mean degrees``;
    exactly one target must be given. The estimator (``estimator(images) -> [B, >=2]`` with gaze pitch/yaw
    first, e.g. :class:`train.estimator.network.GazeEstimator`) is frozen: eval mode, no parameter gradients;
    gradients flow through the render only.
    """

    def __init__(self, estimator: nn.Module):
        super().__init__()
        self.estimator = estimator.eval()
        for p in self.estimator.parameters():
            p.requires_grad_(False)

    def train(self, mode: bool = True) -> "GazeLoss":
        super().train(mode)
        self.estimator.eval()
        return self

    def forward(self, render: torch.Tensor, target_image: torch.Tensor | None = None,
                target_gaze: torch.Tensor | None = None, reduction: str = "mean",
                landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """``landmarks`` [B, 68, 2] (pixels of the target, which the render shares) are passed on to
        estimators that read eye patches."""
        if (target_image is None) == (target_gaze is None):
            raise ToolkitError("GazeLoss: give exactly one of target_image or target_gaze")
        est = self.estimator if landmarks is None else (lambda x: self.estimator(x, fp32(landmarks)))
        with no_autocast(render.device):
            pred = est(fp32(render))[:, :2]
            if target_image is not None:
                with torch.no_grad():
                    target = est(fp32(target_image))[:, :2]
            else:
                target = fp32(target_gaze).to(pred.device)
                if target.shape != pred.shape:
                    raise ToolkitError(f"GazeLoss: target_gaze must be [B={pred.shape[0]}, 2], got {list(target.shape)}")
            err = angular_error_deg(pred, target.detach())
        if reduction == "none":
            return err
        return err.mean()


def head_to_camera_rotation(viewmat: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """[B, 3, 3] rotation from the head frame to the camera frame (w2c ∘ pose), for world-to-camera
    ``viewmat`` [B, 4, 4] and head ``pose`` [B, 6] (axis-angle rotation first): the ``R`` of :func:`gaze_to_camera`."""
    from toolkit.rotations import so3_exp

    return viewmat[:, :3, :3] @ so3_exp(pose[:, :3])


def gaze_to_camera(pitchyaw: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Head-frame gaze [B, 2] -> camera-frame gaze [B, 2] for head-to-camera rotations R [B, 3, 3].

    The sampled intermediate gaze φ lives in the head frame, while an estimator trained on camera-frame labels
    (``pitchyaw_cam``) predicts camera-frame gaze: convert φ with this before ``GazeLoss(target_gaze=...)``.
    """
    from toolkit.rotations import pitchyaw_to_vector, vector_to_pitchyaw

    return vector_to_pitchyaw(torch.einsum("bij,bj->bi", R, pitchyaw_to_vector(pitchyaw)))
