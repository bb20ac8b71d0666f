"""Stress tests of toolkit.eyes: eye rotations at gaze angles of ±89°, ±90° and 180° (where the rotation's
quaternion changes branch), zero and tiny quaternions turned with the eye, and sphere fits of tiny eyeballs far
from the origin and huge ones. Outputs and the gradients with respect to the gaze angles stay finite."""

from __future__ import annotations

import math

import pytest
import torch

from toolkit.eyes import eyeball_info, fit_sphere, gaze_rotation, redirect_eyes, rotate_about
from toolkit.procedural import demo_head_scene
from toolkit.rotations import pitchyaw_to_vector

EXTREME_GAZES_DEG = [(89, 0), (-89, 0), (0, 89), (0, -89), (89, 89), (-89, -89), (90, 0), (0, 90), (90, 90),
                     (0, 180), (180, 0), (-90, -180), (0, 0)]


@pytest.mark.parametrize("pitch,yaw", EXTREME_GAZES_DEG)
def test_rotate_about_at_extreme_gazes_has_finite_gradients(pitch, yaw):
    """Gaussians (one with a zero quaternion, one with a 1e-20 one) turned about an eyeball centre by the gaze
    rotation: finite means, quaternions and gradients with respect to the angles, and the frontal axis lands on
    the gaze direction."""
    g = torch.Generator().manual_seed(1)
    py = torch.tensor([math.radians(pitch), math.radians(yaw)], requires_grad=True)
    R = gaze_rotation(py)
    means = torch.randn(6, 3, generator=g)
    quats = torch.randn(6, 4, generator=g)
    quats[0] = 0.0
    quats[1] = quats[1] * 1e-20
    centre = torch.tensor([0.03, -0.005, -0.068])
    new_means, new_quats = rotate_about(means, quats, R, centre)
    assert torch.isfinite(new_means).all() and torch.isfinite(new_quats).all()
    front = R @ torch.tensor([0.0, 0.0, -1.0])
    assert torch.allclose(front, pitchyaw_to_vector(py), atol=1e-6)
    w = torch.randn(6, 4, generator=g)
    (new_means.sum() + (new_quats * w).sum() + front.sum()).backward()
    assert torch.isfinite(py.grad).all()


@pytest.mark.parametrize("deg", [89.0, -89.0])
def test_redirect_eyes_of_the_demo_head_at_89_degrees(deg):
    scene = demo_head_scene(300)
    r = math.radians(deg)
    for py in ((r, 0.0), (0.0, r), (r, r)):
        out = redirect_eyes(scene, py)
        assert torch.isfinite(out.means).all() and torch.isfinite(out.quats).all()
        assert out.validate() is out
        # Eye Gaussians stay on their spheres: a rigid turn about each centre.
        for name, eye in eyeball_info(scene).items():
            m = scene.part == (1 if name == "left" else 2)
            before = (scene.means[m] - eye["center"]).norm(dim=-1)
            after = (out.means[m] - eye["center"]).norm(dim=-1)
            assert torch.allclose(before, after, atol=1e-6)


@pytest.mark.parametrize("radius,centre", [(1e-3, 1e2), (1e-6, 0.0), (1e4, -1e2)])
def test_fit_sphere_of_tiny_far_and_huge_eyeballs(radius, centre):
    """A 1 mm sphere 100 m from the origin (its points a few float32 steps apart there), a 1 µm one and a 10 km
    one: float32 points give a finite centre and radius (the fit centres the points in float64 first)."""
    g = torch.Generator().manual_seed(2)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    c0 = torch.tensor([centre, -centre, 0.5 * centre], dtype=torch.float64)
    pts = (c0 + radius * d).float()
    c, r = fit_sphere(pts)
    assert torch.isfinite(c).all() and torch.isfinite(r)
    assert float(r) == pytest.approx(radius, rel=0.05)
