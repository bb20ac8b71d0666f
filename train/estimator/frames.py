"""The mean of two gaze directions (pitch, yaw radians, ETH-XGaze convention); the head frame and the
normalized camera's are converted by ``toolkit.rotations.head_to_camera_gaze`` / ``camera_to_head_gaze``."""

from __future__ import annotations

import torch

from toolkit.rotations import pitchyaw_to_vector, vector_to_pitchyaw


def mean_direction(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[B, 2] (pitch, yaw) x 2 -> [B, 2]: the direction halfway between (``a`` where they are opposite)."""
    va, vb = pitchyaw_to_vector(a), pitchyaw_to_vector(b)
    s = va + vb
    # |a + b| = 2 cos(angle / 2): the guard keeps the normalization's gradient (~1 / |a + b|) bounded too.
    return vector_to_pitchyaw(torch.where(s.norm(dim=-1, keepdim=True) > 1e-3, s, va))
