"""Stress tests of train.estimator: the head-frame composition and mirror averaging of GazeEstimator with
readings exactly on the poles (±90°), the halfway direction of opposite gazes (frames.mean_direction's guard),
training steps on labels at ±89° in both loss spaces, blur of near-zero and huge widths, drawn faces at ±89°,
the peer's differentiable resampling with landmarks far outside tiny images, and the peer ResNet-50 on constant
images. Outputs and gradients (images, angles, weights) stay finite."""

from __future__ import annotations

import math

import pytest
import torch
import torch._dynamo  # noqa: F401  (the first torch optimizer imports it, ~1 s once per process: pay it here)

from train.estimator.augment import jitter_photometric, random_blur
from train.estimator.config import GazeEstimatorConfig, GazeEstimatorTrainConfig, eye_config
from train.estimator.drawn_faces import draw_faces
from train.estimator.frames import mean_direction
from train.estimator.network import GazeEstimator
from train.estimator.peer import gazenerf_preprocess
from train.estimator.resnet50 import XGazeGazeNetwork
from train.estimator.training import train_gaze_estimator

R89, R90 = math.radians(89.0), math.pi / 2
TINY = dict(input_size=32, channels=(8, 16), hidden=16)


def _all_finite(*ts) -> bool:
    return all(t is None or bool(torch.isfinite(t).all()) for t in ts)


def test_mean_direction_of_opposite_polar_and_equal_gazes():
    a = torch.tensor([[0.0, 0.0], [R90, 0.0], [R89, R89], [0.3, -0.2], [R90, R90], [0.1, 0.2], [-R89, 0.0]],
                     requires_grad=True)
    b = torch.tensor([[0.0, math.pi], [-R90, 0.0], [-R89, -R89], [0.3, -0.2], [R90, -R90], [-0.1, 0.2 - math.pi + 1e-3],
                      [-R89, math.pi]], requires_grad=True)
    m = mean_direction(a, b)
    assert _all_finite(m) and float(m.detach()[:, 0].abs().max()) <= R90 + 1e-6
    m.sum().backward()
    assert _all_finite(a.grad, b.grad)


@pytest.mark.parametrize("design", ["face", "eyes"])
@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_head_frame_mirror_averaged_readings_on_the_poles(design, fill):
    """The network's last layer set to read (gaze, head) = (±90°, ±90°): the exact composition into the camera
    frame and the average with the mirrored reading stay finite, as do the gradients to images and weights.
    The eye design gets degenerate landmarks (all 68 on one pixel)."""
    torch.manual_seed(0)
    cfg = eye_config(32) if design == "eyes" else GazeEstimatorConfig(**TINY, mirror_average=True, head_frame=True)
    est = GazeEstimator(cfg)
    with torch.no_grad():
        est.head[-1].weight.mul_(1e-6)
        est.head[-1].bias.copy_(torch.tensor([R90, R90, R90, -R90]))
    x = torch.full((2, 3, 32, 32), fill, requires_grad=True)
    lm = torch.full((2, 68, 2), 16.0) if design == "eyes" else None
    y = est(x, lm)
    assert y.shape == (2, 4) and _all_finite(y)
    y.sum().backward()
    assert _all_finite(x.grad) and all(_all_finite(p.grad) for p in est.parameters())


@pytest.mark.parametrize("loss_space", ["vectors", "angles"])
def test_training_steps_on_labels_at_89_degrees(loss_space):
    """Gaze and head labels at ±89° (the vectors loss converts them, the head-frame term inverts the head
    rotation near its pole), every augmentation on, blur included: finite losses and weights."""
    g = torch.Generator().manual_seed(3)
    images = torch.rand(8, 3, 32, 32, generator=g)
    images[:2] = 0.0  # constant images: zero variance for the photometric jitter
    labels = torch.tensor([[R89, R89, R89, -R89], [-R89, -R89, -R89, R89]] * 4)
    losses = []
    tc = GazeEstimatorTrainConfig(steps=3, batch_size=4, loss_space=loss_space, warmup_steps=1, blur_prob=1.0)
    model, _ = train_gaze_estimator(images, labels, GazeEstimatorConfig(**TINY, mirror_average=True), tc,
                                    on_step=lambda step, loss: losses.append(loss))
    assert len(losses) == 3 and all(math.isfinite(v) for v in losses)
    assert all(_all_finite(p) for p in model.parameters())


@pytest.mark.parametrize("max_sigma", [1e-9, 1e-3, 1.0, 50.0])
def test_random_blur_and_jitter_at_extreme_widths(max_sigma):
    """Blur widths whose kernel is a single tap (the 1e-3 floor) up to a kernel far wider than the 8x8 image
    (edge replication on every side), on constant and random images, the whole image and a box."""
    g = torch.Generator().manual_seed(4)
    x = torch.cat([torch.full((1, 3, 8, 8), 0.5), torch.rand(1, 3, 8, 8, generator=g)]).requires_grad_(True)
    for box in (None, (2, 5, 1, 7)):
        y = random_blur(x, 1.0, max_sigma, g, box)
        assert _all_finite(y) and float(y.detach().min()) >= 0 and float(y.detach().max()) <= 1
        (y * torch.rand(y.shape, generator=g)).sum().backward()
        assert _all_finite(x.grad)
        x.grad = None
    j = jitter_photometric(x, GazeEstimatorTrainConfig(brightness=1.0, contrast=1.0, noise=1.0), g)
    j.sum().backward()
    assert _all_finite(j, x.grad)


def test_drawn_faces_at_89_degree_gazes_and_head_poses():
    gaze = torch.tensor([[R89, R89], [-R89, -R89], [R89, -R89], [0.0, 0.0]], requires_grad=True)
    head = torch.tensor([[R89, -R89], [-R89, R89], [0.0, R89], [-R89, 0.0]], requires_grad=True)
    img = draw_faces(16, torch.tensor([0, 1, 2, 3]), gaze, head, n_subjects=4)
    assert img.shape == (4, 3, 16, 16) and _all_finite(img)
    img.sum().backward()
    assert _all_finite(gaze.grad, head.grad)


@pytest.mark.parametrize("span", [1e-3, 0.26, 1e3])
def test_peer_resampling_with_landmarks_far_outside_tiny_images(span):
    """The peer's crop (without its uint8 quantization: differentiable) of 2x2 and 3x5 images, centred on
    landmarks at the image corner or a million pixels away, for crops from tiny to huge: finite, with finite
    gradients to the images."""
    for hw in ((2, 2), (3, 5)):
        x = torch.rand(2, 3, *hw, generator=torch.Generator().manual_seed(5)).requires_grad_(True)
        lm = torch.stack([torch.zeros(68, 2), torch.full((68, 2), 1e6) * torch.tensor([1.0, -1.0])])
        out = gazenerf_preprocess(x, lm, face_span_m=span, quantize=False)
        assert out.shape == (2, 3, 224, 224) and _all_finite(out)
        out.sum().backward()
        assert _all_finite(x.grad)


@pytest.mark.parametrize("fill", [0.0, 1.0, 1e4])
def test_peer_resnet50_on_constant_images(fill):
    """Eval mode, as the peer network is always used (frozen): constant inputs make every batch-norm input
    constant too; the readings and the gradient with respect to the input stay finite."""
    torch.manual_seed(0)
    net = XGazeGazeNetwork(4).eval()
    x = torch.full((1, 3, 32, 32), fill, requires_grad=True)
    y = net(x)
    assert y.shape == (1, 4) and _all_finite(y)
    y.sum().backward()
    assert _all_finite(x.grad)
