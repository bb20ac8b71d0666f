import math

import pytest
import torch

from toolkit import ToolkitError
from toolkit.cameras import (
    Camera,
    eth_xgaze_rig,
    intrinsics,
    intrinsics_from_fov,
    look_at,
    opengl_projection,
    opengl_view,
    project_points,
    resize_intrinsics,
)


def test_look_at_projects_target_to_principal_point():
    V = look_at(torch.tensor([0.3, -0.2, -1.0]), torch.tensor([0.0, 0.0, 0.0]))
    K = intrinsics(500, 500, 64, 48)
    uv, z = project_points(torch.tensor([[0.0, 0.0, 0.0]]), V, K)
    assert torch.allclose(uv, torch.tensor([[64.0, 48.0]]), atol=1e-4)
    assert z.item() == pytest.approx(math.sqrt(0.09 + 0.04 + 1.0), rel=1e-6)
    R = V[:3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-6)
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-6)


def test_hand_computed_projection():
    # Camera at origin looking along +z (identity view): u = fx x/z + cx, v = fy y/z + cy.
    V = torch.eye(4)
    K = intrinsics(100, 120, 32, 24)
    uv, z = project_points(torch.tensor([[0.1, -0.2, 2.0]]), V, K)
    assert torch.allclose(uv, torch.tensor([[100 * 0.05 + 32, 120 * -0.1 + 24]]))
    # World up (-y, the default) appears up in the image: a point above the target has smaller v.
    V2 = look_at(torch.tensor([0.0, 0.0, -1.0]), torch.zeros(3))
    uv2, _ = project_points(torch.tensor([[0.0, -0.1, 0.0], [0.1, 0.0, 0.0]]), V2, K)
    assert uv2[0, 1] < 24 and uv2[1, 0] > 32  # above -> up; +x -> image right for a frontal camera


def test_resize_intrinsics_keeps_pixel_centres():
    K = intrinsics_from_fov(30, 64, 64)
    K2 = resize_intrinsics(K, 64, 64, 256, 128)
    V = look_at(torch.tensor([0.0, 0.0, -1.0]), torch.zeros(3))
    p = torch.tensor([[0.05, 0.03, 0.0]])
    uv, _ = project_points(p, V, K)
    uv2, _ = project_points(p, V, K2)
    assert torch.allclose(uv2, uv * torch.tensor([4.0, 2.0]), atol=1e-4)
    cam = Camera(K, V, 64, 64).resized(256, 128)
    assert cam.width == 256 and torch.allclose(cam.K, K2)


def test_opengl_pair_matches_opencv_projection():
    K = intrinsics(300, 280, 70, 50)
    V = look_at(torch.tensor([0.2, -0.1, -1.5]), torch.zeros(3))
    W, H = 128, 96
    P, Vgl = opengl_projection(K, W, H, 0.1, 10.0), opengl_view(V)
    pts = torch.randn(50, 3) * 0.2
    uv, z = project_points(pts, V, K)
    clip = torch.cat([pts, torch.ones(50, 1)], 1) @ (P @ Vgl).T
    ndc = clip[:, :3] / clip[:, 3:]
    win = torch.stack([(ndc[:, 0] + 1) * W / 2, (ndc[:, 1] + 1) * H / 2], -1)
    assert torch.allclose(win, uv, atol=1e-3)
    assert ((ndc[:, 2] > -1) & (ndc[:, 2] < 1)).all()


def test_eth_xgaze_rig_faces_subject():
    cams = eth_xgaze_rig(radius=1.0, width=64, height=64)
    assert len(cams) == 18
    for c in cams:
        uv, z = c.project(torch.zeros(1, 3))
        assert torch.allclose(uv, torch.tensor([[32.0, 32.0]]), atol=1e-3) and z.item() > 0
    centres = torch.stack([c.center for c in cams])
    assert (centres[:, 2] < 0).all()  # the rig is in front of the face (face looks towards -z)
    yaws = torch.rad2deg(torch.atan2(centres[:, 0], -centres[:, 2]))
    assert yaws.max().item() == pytest.approx(60, abs=1e-3) and yaws.min().item() == pytest.approx(-60, abs=1e-3)


@pytest.mark.parametrize(
    "kwargs,msg",
    [
        (dict(K=torch.eye(2), viewmat=torch.eye(4), width=4, height=4), "K"),
        (dict(K=torch.eye(3), viewmat=torch.eye(3), width=4, height=4), "viewmat"),
        (dict(K=torch.eye(3), viewmat=torch.eye(4), width=0, height=4), "width"),
        (dict(K=torch.full((3, 3), float("nan")), viewmat=torch.eye(4), width=4, height=4), "finite"),
    ],
)
def test_camera_validation(kwargs, msg):
    with pytest.raises(ToolkitError, match=msg):
        Camera(**kwargs)


def test_look_at_degenerate():
    with pytest.raises(ToolkitError, match="coincide"):
        look_at(torch.zeros(3), torch.zeros(3))
    with pytest.raises(ToolkitError, match="parallel"):
        look_at(torch.tensor([0.0, 1.0, 0.0]), torch.zeros(3))
