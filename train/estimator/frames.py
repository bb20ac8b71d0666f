"""Gaze directions between frames: the head frame and the normalized camera's (pitch, yaw radians, ETH-XGaze
convention, ``toolkit.rotations``), and the mean of two directions."""

from __future__ import annotations

import torch

from toolkit.rotations import normalized_head_rotation, pitchyaw_to_vector, vector_to_pitchyaw


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
