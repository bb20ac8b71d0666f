"""Stress tests of toolkit.cameras: projection of points on the camera plane, behind it and very far, look-at
frames whose view direction nearly runs along the up axis, orbit rigs at ±89° pitch and near/far extremes of the
GL projection. Outputs and gradients stay finite; the exactly degenerate cases are clear errors, not NaN."""

from __future__ import annotations

import math

import pytest
import torch

from toolkit.cameras import (
    Camera,
    intrinsics,
    intrinsics_from_fov,
    look_at,
    opengl_projection,
    opengl_view,
    orbit_rig,
    project_points,
    resize_intrinsics,
)
from toolkit.errors import ToolkitError


def _finite(*ts: torch.Tensor) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in ts)


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_project_points_on_the_camera_plane_behind_and_far(scale):
    """z = 0 exactly, |z| below the 1e-12 guard, behind the camera and 1e6 units away, at three world scales:
    the pixel coordinates and their gradients (through points, viewmat and K) are finite."""
    V = look_at(torch.tensor([0.0, 0.0, -2.0]) * scale, torch.zeros(3))
    K = intrinsics(500.0, 500.0, 64.0, 48.0)
    K[0, 1] = 0.5  # a skew term multiplies y / z too
    tz = float(V[2, 3])
    pts = torch.tensor([
        [0.3, -0.2, -tz],  # on the camera plane: z = 0
        [0.3, -0.2, -tz + 1e-14 * scale],  # |z| below the guard
        [0.3, -0.2, -tz - 1.0 * scale],  # behind
        [0.0, 0.0, 1e6 * scale],  # far in front
        [1e-30, 0.0, 1.0 * scale],  # a denormal-sized offset
    ]) * torch.tensor([scale, scale, 1.0])
    pts.requires_grad_(True)
    Vg, Kg = V.clone().requires_grad_(True), K.clone().requires_grad_(True)
    uv, z = project_points(pts, Vg, Kg)
    assert _finite(uv, z)
    (uv.sum() + z.sum()).backward()
    assert _finite(pts.grad, Vg.grad, Kg.grad)


@pytest.mark.parametrize("deg", [89.0, 89.9, 89.999, -89.999])
def test_look_at_nearly_along_the_up_axis_is_orthonormal_with_finite_gradients(deg):
    """A camera looking almost straight down (or up) the world y axis, the default up: the frame is still a
    rotation and the gradient with respect to the eye position finite (it grows like 1 / angle, as it must)."""
    r = math.radians(deg)
    eye = torch.tensor([0.18 * math.cos(r), -math.sin(r), 0.8 * math.cos(r)], requires_grad=True)
    V = look_at(eye, torch.zeros(3))
    R = V[:3, :3].detach()
    assert _finite(V)
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-5) and float(torch.det(R)) == pytest.approx(1.0, abs=1e-5)
    (V * torch.arange(16.0).view(4, 4)).sum().backward()
    assert _finite(eye.grad)


def test_look_at_exactly_along_an_axis_is_a_clear_error_and_other_axes_are_fine():
    """Straight along the up axis has no frame (ToolkitError); straight along x or z, and along y with another
    up vector, give exact rotations."""
    with pytest.raises(ToolkitError, match="parallel"):
        look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3))
    for eye, up in (([3.0, 0, 0], None), ([0, 0, -3.0], None), ([0, 0, 3.0], None), ([0, -3.0, 0], [0, 0, 1.0])):
        V = look_at(torch.tensor(eye), torch.zeros(3), None if up is None else torch.tensor(up))
        R = V[:3, :3]
        assert _finite(V) and torch.allclose(R @ R.T, torch.eye(3), atol=1e-6)


@pytest.mark.parametrize("dist", [2e-9, 1e-4, 1e7])
def test_look_at_tiny_and_huge_distances(dist):
    """Eye and target 2e-9 (just above the coincidence guard), 1e-4 and 1e7 apart: a finite rotation that
    puts the target on the optical axis."""
    target = torch.zeros(3)  # at a 0.1 offset, float32 cannot hold a 2e-9 step at all
    eye = target + dist * torch.tensor([0.6, -0.0, -0.8])
    V = look_at(eye, target)
    assert _finite(V) and torch.allclose(V[:3, :3] @ V[:3, :3].T, torch.eye(3), atol=1e-5)
    cam_t = V[:3, :3] @ target + V[:3, 3]
    assert abs(float(cam_t[0])) <= 1e-6 * max(dist, 1.0) and float(cam_t[2]) > 0


def test_orbit_rig_at_89_degrees_of_pitch_and_full_yaw():
    """The rig's extreme rows (pitch ±89°, yaw ±180°) give finite, orthonormal cameras whose centres lie on
    the sphere; a pitch of 90° puts a camera on the up axis and is a clear error."""
    cams = orbit_rig(5, 3, radius=0.6, yaw_range_deg=180.0, pitch_range_deg=89.0, width=16, height=12)
    for c in cams:
        R = c.viewmat[:3, :3]
        assert _finite(c.viewmat, c.camtoworld, c.center)
        assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-5)
        assert float(c.center.norm()) == pytest.approx(0.6, rel=1e-5)
    with pytest.raises(ToolkitError, match="parallel"):
        orbit_rig(1, 3, radius=0.6, yaw_range_deg=0.0, pitch_range_deg=90.0)


@pytest.mark.parametrize("t", [1e-6, 1e6])
def test_camtoworld_of_tiny_and_far_cameras(t):
    V = look_at(torch.tensor([0.0, 0.0, -t]), torch.zeros(3))
    cam = Camera(intrinsics_from_fov(30, 16, 16), V, 16, 16)
    c2w = cam.camtoworld
    assert _finite(c2w, cam.center)
    assert torch.allclose(c2w[:3, 3], torch.tensor([0.0, 0.0, -t]), rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize("near,far", [(1e-6, 1e10), (0.01, 0.0100001), (1e3, 1e9)])
def test_opengl_projection_at_extreme_planes(near, far):
    """Planes 16 decades apart or nearly coincident: a finite clip matrix that still maps the near plane to
    NDC depth -1 (to float32 precision)."""
    K = intrinsics_from_fov(89.0, 1, 1)
    P = opengl_projection(K, 1, 1, near, far)
    assert _finite(P, opengl_view(torch.eye(4)))
    clip = P @ torch.tensor([0.0, 0.0, -near, 1.0], dtype=torch.float32)
    assert float(clip[2] / clip[3]) == pytest.approx(-1.0, abs=1e-2)


def test_intrinsics_from_extreme_fields_of_view_and_resizes():
    for fov in (1e-3, 179.999):
        K = intrinsics_from_fov(fov, 4096, 1)
        assert _finite(K) and float(K[0, 0]) > 0
        K1 = resize_intrinsics(K, 4096, 1, 1, 4096)
        assert _finite(K1) and float(K1[0, 0]) > 0 and float(K1[1, 1]) > 0
