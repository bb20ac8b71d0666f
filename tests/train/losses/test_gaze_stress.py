"""Stress tests of train.losses.gaze: the angular error at its two singular points (0°, where acos would have an
infinite slope, and 180°, opposite directions), at ±89° and ±90° gazes (the poles of the pitch/yaw chart),
through the head-to-camera conversion with head rotations of π. The loss and its gradient with respect to the
render, and the conversion's gradients with respect to gaze and head pose, stay finite."""

from __future__ import annotations

import math

import pytest
import torch

from train.losses import GazeLoss, gaze_to_camera, head_to_camera_rotation

R89, R90 = math.radians(89.0), math.pi / 2


class _FixedGaze(torch.nn.Module):
    """A frozen stand-in estimator that reads a set gaze, nudged by the image's mean so gradients reach it."""

    def __init__(self, pitchyaw):
        super().__init__()
        self.register_buffer("pitchyaw", torch.tensor(pitchyaw, dtype=torch.float32))
        self.gain = torch.nn.Parameter(torch.tensor(1e-3))

    def forward(self, images, landmarks=None):
        return self.pitchyaw + (images.mean((1, 2, 3))[:, None] - 0.5) * self.gain


PAIRS = [  # (the render's reading, the target gaze)
    ((0.0, 0.0), (0.0, 0.0)),  # zero error
    ((R89, 0.0), (R89, 0.0)),  # zero error at 89° pitch
    ((R89, R89), (-R89, -R89)),  # nearly opposite
    ((R90, 0.0), (-R90, 0.0)),  # exactly opposite poles
    ((0.0, 0.0), (0.0, math.pi)),  # exactly opposite on the equator
    ((R90, R90), (R90, -R90)),  # one pole, two yaws: the same direction
    ((-R89, R89), (R89, -R89)),
]


@pytest.mark.parametrize("pred,target", PAIRS)
def test_gaze_loss_at_zero_and_180_degrees_and_at_the_poles(pred, target):
    est = _FixedGaze([pred, target])
    loss_fn = GazeLoss(est)
    render = torch.full((2, 3, 8, 8), 0.5, requires_grad=True)
    per = loss_fn(render, target_gaze=torch.tensor([target, pred]), reduction="none")
    assert torch.isfinite(per).all() and float(per.detach().min()) >= 0 and float(per.detach().max()) <= 180 + 1e-3
    per.sum().backward()
    assert torch.isfinite(render.grad).all()
    render.grad = None
    same = loss_fn(render, target_image=torch.full((2, 3, 8, 8), 0.5))  # reading the target too: zero error
    same.backward()
    assert torch.isfinite(same) and torch.isfinite(render.grad).all()


@pytest.mark.parametrize("pitchyaw", [(R89, 0.0), (-R89, R89), (R90, 0.0), (-R90, 0.0), (0.0, math.pi), (R90, math.pi)])
def test_gaze_to_camera_at_the_poles_with_half_turn_head_poses(pitchyaw):
    """Head poses of a half turn about x, y and z (axis-angle of length π) and of zero; gazes on the poles."""
    gaze = torch.tensor([pitchyaw] * 4, requires_grad=True)
    pose = torch.zeros(4, 6)
    pose[0, 0], pose[1, 1], pose[2, 2] = math.pi, math.pi, math.pi
    pose.requires_grad_(True)
    viewmat = torch.eye(4).expand(4, 4, 4).clone()
    viewmat[:, :3, :3] = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # a camera turned about x
    R = head_to_camera_rotation(viewmat, pose)
    out = gaze_to_camera(gaze, R)
    assert torch.isfinite(R).all() and torch.isfinite(out).all()
    assert float(out.detach()[:, 0].abs().max()) <= R90 + 1e-6
    (out * torch.tensor([1.0, 0.5])).sum().backward()
    assert torch.isfinite(gaze.grad).all() and torch.isfinite(pose.grad).all()
