import math

import pytest
import torch

from toolkit import ToolkitError
from toolkit.rotations import (
    angular_error_deg,
    axis_angle_to_quat,
    matrix_to_quat,
    normalize_quat,
    pitchyaw_to_vector,
    quat_multiply,
    quat_slerp,
    quat_to_matrix,
    so3_exp,
    so3_log,
    vector_to_pitchyaw,
)


def _random_quats(n, dtype=torch.float64):
    q = torch.randn(n, 4, dtype=dtype)
    return q / q.norm(dim=-1, keepdim=True)


def test_quat_matrix_round_trip():
    q = _random_quats(500)
    R = quat_to_matrix(q)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=q.dtype).expand(500, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(500, dtype=q.dtype), atol=1e-12)
    q2 = matrix_to_quat(R)
    q = torch.where(q[:, :1] < 0, -q, q)
    assert torch.allclose(q2, q, atol=1e-10)


def test_matrix_to_quat_near_pi_rotations():
    # 180° rotations have w = 0: the branch choice must keep full precision.
    axes = torch.nn.functional.normalize(torch.randn(100, 3, dtype=torch.float64), dim=-1)
    R = so3_exp(axes * math.pi)
    assert torch.allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-10)


def test_quat_convention_wxyz_and_hamilton():
    # 90° about z: (cos 45°, 0, 0, sin 45°) maps x to y.
    q = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    assert torch.allclose(quat_to_matrix(q) @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]), atol=1e-6)
    a, b = _random_quats(20), _random_quats(20)
    assert torch.allclose(quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b), atol=1e-12)


def test_so3_exp_log_round_trip_including_tiny_and_pi():
    w = torch.randn(300, 3, dtype=torch.float64)
    w = w / w.norm(dim=-1, keepdim=True) * torch.rand(300, 1, dtype=torch.float64) * (math.pi - 1e-6)
    w[:5] *= 1e-9
    assert torch.allclose(so3_log(so3_exp(w)), w, atol=1e-9)
    assert torch.allclose(quat_to_matrix(axis_angle_to_quat(w)), so3_exp(w), atol=1e-12)


def test_zero_and_tiny_quaternions_are_finite():
    q = torch.tensor([[0.0, 0, 0, 0], [1e-12, 0, 1e-12, 0], [0, 0, 0, 1e-30]], requires_grad=True)
    R = quat_to_matrix(q)
    assert torch.isfinite(R).all()
    assert torch.allclose(R[0], torch.eye(3))
    R.sum().backward()
    assert torch.isfinite(q.grad).all()
    assert torch.allclose(normalize_quat(q.detach())[1].norm(), torch.tensor(1.0))


def test_exp_log_gradients_finite_at_zero():
    w = torch.zeros(4, 3, requires_grad=True)
    so3_exp(w).sum().backward()
    assert torch.isfinite(w.grad).all()
    R = torch.eye(3).expand(2, 3, 3).clone().requires_grad_(True)
    so3_log(R).sum().backward()
    assert torch.isfinite(R.grad).all()


def test_slerp_endpoints_and_midpoint():
    a, b = _random_quats(10), _random_quats(10)
    same = lambda x, y: torch.allclose(quat_to_matrix(x), quat_to_matrix(y), atol=1e-9)  # noqa: E731
    assert same(quat_slerp(a, b, 0.0), a) and same(quat_slerp(a, b, 1.0), b)
    mid = quat_slerp(a, b, 0.5)
    ang = lambda x, y: so3_log(quat_to_matrix(x).transpose(-1, -2) @ quat_to_matrix(y)).norm(dim=-1)  # noqa: E731
    assert torch.allclose(ang(a, mid), ang(mid, b), atol=1e-7)
    assert torch.isfinite(quat_slerp(a, a, 0.3)).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_slerp_of_equal_quaternions_has_finite_gradients(dtype):
    q = _random_quats(6).to(dtype).requires_grad_(True)
    for q1 in (q, -q, q.detach()):  # the same rotation, its double cover, and a constant copy
        out = quat_slerp(q, q1, 0.3)
        (g,) = torch.autograd.grad(out.sum(), q)
        assert torch.isfinite(out).all() and torch.isfinite(g).all()
        assert torch.allclose(quat_to_matrix(out), quat_to_matrix(q.detach()), atol=1e-5)


def test_gaze_convention_eth_xgaze():
    # Frontal gaze towards the camera: (0, 0, -1) in OpenCV axes -> pitch 0, yaw 0.
    assert torch.allclose(vector_to_pitchyaw(torch.tensor([0.0, 0, -1])), torch.zeros(2))
    # Looking up (towards -y in OpenCV axes) is positive pitch.
    assert vector_to_pitchyaw(torch.tensor([0.0, -1, -1]))[0] == pytest.approx(math.pi / 4)
    # Looking towards -x is positive yaw: yaw = atan2(-g_x, -g_z).
    assert vector_to_pitchyaw(torch.tensor([-1.0, 0, -1]))[1] == pytest.approx(math.pi / 4)
    # The formula of the ETH-XGaze code: vector_to_pitchyaw(-g) with pitch = asin(v_y), yaw = atan2(v_x, v_z).
    g = torch.nn.functional.normalize(torch.randn(100, 3, dtype=torch.float64), dim=-1)
    v = -g
    ref = torch.stack([torch.asin(v[:, 1]), torch.atan2(v[:, 0], v[:, 2])], -1)
    assert torch.allclose(vector_to_pitchyaw(g), ref, atol=1e-6)


def test_gaze_round_trip_and_poles():
    py = torch.stack([torch.rand(1000, dtype=torch.float64) * 3.1 - 1.55, torch.rand(1000, dtype=torch.float64) * 6.2 - 3.1], -1)
    assert torch.allclose(vector_to_pitchyaw(pitchyaw_to_vector(py)), py, atol=1e-6)
    v = pitchyaw_to_vector(py)
    assert torch.allclose(pitchyaw_to_vector(vector_to_pitchyaw(v)), v, atol=1e-6)
    poles = torch.tensor([[0.0, 1, 0], [0.0, -1, 0]], requires_grad=True)
    out = vector_to_pitchyaw(poles)
    assert torch.isfinite(out).all()
    assert out[0, 0].item() == pytest.approx(-math.pi / 2, abs=1e-3)  # looking down (+y)
    assert out[1, 0].item() == pytest.approx(math.pi / 2, abs=1e-3)
    out.sum().backward()
    assert torch.isfinite(poles.grad).all()


def test_zero_gaze_vector_is_clear_error():
    with pytest.raises(ToolkitError, match="zero length"):
        vector_to_pitchyaw(torch.zeros(3))


def test_angular_error():
    a = torch.tensor([[0.1, 0.2]], dtype=torch.float64)
    assert angular_error_deg(a, a).item() == pytest.approx(0.0, abs=1e-6)
    b = torch.tensor([[0.1, 0.2 + math.radians(3)]], dtype=torch.float64)
    assert angular_error_deg(torch.tensor([[0.0, 0.0]]), torch.tensor([[0.0, math.radians(3)]])).item() == pytest.approx(3.0, abs=1e-4)
    assert angular_error_deg(a, b).item() < 3.0 + 1e-6
    x = torch.tensor([[0.3, -0.2]], requires_grad=True)
    angular_error_deg(x, x.detach()).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_normalized_head_rotation_has_no_roll_and_points_the_face():
    from toolkit.rotations import normalized_head_rotation, pitchyaw_to_vector

    torch.manual_seed(0)
    hp = (torch.rand(64, 2, dtype=torch.float64) * 2 - 1) * torch.tensor([1.4, 3.1], dtype=torch.float64)
    R = normalized_head_rotation(hp)
    eye = torch.eye(3, dtype=torch.float64).expand(64, 3, 3)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(64, dtype=torch.float64))
    forward = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    torch.testing.assert_close(R @ forward, pitchyaw_to_vector(hp))
    assert float(R[:, 1, 0].abs().max()) < 1e-12  # head x axis has no camera-y component: no roll
    front = hp[:, 1].abs() < math.pi / 2
    assert bool((R[front, 0, 0] > 0).all())  # a face towards the camera keeps the camera's x sense
    torch.testing.assert_close(normalized_head_rotation(torch.zeros(2, dtype=torch.float64)), eye[0])
    # Degenerate: the face points along the camera's y axis; finite values and gradients.
    pole = torch.tensor([[math.pi / 2, 0.3], [-math.pi / 2, -1.0]], requires_grad=True)
    Rp = normalized_head_rotation(pole)
    Rp.sum().backward()
    assert torch.isfinite(Rp).all() and torch.isfinite(pole.grad).all()
