"""Rotations and gaze angles, batched and differentiable.

Conventions (stated once, used everywhere):
- Quaternions are **wxyz** (scalar first), as in the graphdeco 3DGS PLY ``rot_0..3`` and gsplat.
  Functions normalize on use; a zero quaternion maps to the identity rotation (never NaN).
- Rotation matrices act on column vectors: ``x' = R @ x``.
- Axis-angle vectors are ``angle * unit_axis`` (so3 tangent vectors).
- Gaze pitch/yaw follow the ETH-XGaze / MPIIGaze normalization code: for a unit gaze direction ``g`` in
  OpenCV axes (x right, y down, z forward from the camera, so a frontal gaze is ``(0, 0, -1)``)::

      pitch = asin(-g_y)          (positive = looking up)
      yaw   = atan2(-g_x, -g_z)   (positive = looking towards the camera's -x, the subject's left)
      g     = (-cos(pitch) sin(yaw), -sin(pitch), -cos(pitch) cos(yaw))

  This is ``vector_to_pitchyaw(-g)`` of the ETH-XGaze repository, so labels from real preprocessed
  files are read with the meaning they were written with.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError

EPS = 1e-12
# Below this angle so3 exp/log switch to Taylor series: sin(x)/x loses all precision near 0 in float32.
SMALL_ANGLE = 1e-4


def normalize_quat(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] wxyz -> unit quaternion; an all-zero quaternion becomes the identity (1, 0, 0, 0)."""
    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    # Scale first so tiny but non-zero quats (norm 1e-12) normalize correctly instead of underflowing.
    unit = q / norm.clamp_min(torch.finfo(q.dtype).tiny)
    return torch.where(norm > 0, unit, identity)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] wxyz (any norm) -> [..., 3, 3] rotation matrix."""
    w, x, y, z = normalize_quat(q).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation matrix -> [..., 4] unit wxyz quaternion with w >= 0.

    Uses the branch with the largest diagonal term (Shepperd's method) so no square root of a
    near-zero number is ever divided by.
    """
    m = R
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 * q_i^2 for each component; pick the largest to divide by.
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    r = torch.sqrt(sq.clamp_min(EPS))
    cands = torch.stack(
        [
            torch.stack([r[..., 0] ** 2, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], r[..., 1] ** 2, m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1], r[..., 2] ** 2, m[..., 2, 1] + m[..., 1, 2]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2], r[..., 3] ** 2], -1),
        ],
        dim=-2,
    ) / (2 * r[..., :, None])
    best = sq.argmax(dim=-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    q = normalize_quat(q)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of [..., 4] wxyz quaternions: rotation ``a`` after ``b``."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def _hat(v: torch.Tensor) -> torch.Tensor:
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(v.shape[:-1] + (3, 3))


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """[..., 3] axis-angle -> [..., 3, 3] rotation (Rodrigues), with a Taylor branch near zero."""
    theta2 = (omega * omega).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2.clamp_min(EPS))
    small = theta < SMALL_ANGLE
    safe_theta = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(safe_theta) / safe_theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(safe_theta)) / (safe_theta * safe_theta))
    K = _hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation -> [..., 3] axis-angle with angle in [0, pi].

    Goes through the quaternion (2·atan2(|v|, w)), which stays accurate at 0 and at pi where the
    trace-based arccos formula loses all precision.
    """
    q = matrix_to_quat(R)
    w, v = q[..., :1], q[..., 1:]
    vn = torch.sqrt((v * v).sum(-1, keepdim=True).clamp_min(EPS * EPS))
    angle = 2 * torch.atan2(vn, w)
    small = vn < SMALL_ANGLE
    # angle / |v| -> 2 / w as |v| -> 0.
    scale = torch.where(small, 2 / w.clamp_min(EPS), angle / torch.where(small, torch.ones_like(vn), vn))
    return v * scale


def axis_angle_to_quat(omega: torch.Tensor) -> torch.Tensor:
    """[..., 3] axis-angle -> [..., 4] unit wxyz quaternion."""
    theta2 = (omega * omega).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2.clamp_min(EPS))
    small = theta < SMALL_ANGLE
    half = 0.5 * theta
    k = torch.where(small, 0.5 - theta2 / 48, torch.sin(half) / torch.where(small, torch.ones_like(theta), theta))
    return torch.cat([torch.cos(half), omega * k], -1)


def quat_slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Spherical interpolation of [..., 4] wxyz quaternions along the shorter arc; t broadcastable to [...]."""
    q0, q1 = normalize_quat(q0), normalize_quat(q1)
    t = torch.as_tensor(t, dtype=q0.dtype, device=q0.device)
    if t.dim() == q0.dim() - 1:
        t = t[..., None]
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    # Below 1, not at it: acos'(1) is infinite, and 0 * inf would make the gradient of equal quaternions NaN.
    dot = dot.abs().clamp(max=1.0 - 1e-7)
    theta = torch.acos(dot)
    s = torch.sin(theta)
    near = s < 1e-6
    s_safe = torch.where(near, torch.ones_like(s), s)
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * theta) / s_safe)
    w1 = torch.where(near, t, torch.sin(t * theta) / s_safe)
    return normalize_quat(w0 * q0 + w1 * q1)


def pitchyaw_to_vector(pitchyaw: torch.Tensor) -> torch.Tensor:
    """[..., 2] (pitch, yaw) radians -> [..., 3] unit gaze direction (ETH-XGaze convention, module doc)."""
    pitch, yaw = pitchyaw.unbind(-1)
    cp = torch.cos(pitch)
    return torch.stack([-cp * torch.sin(yaw), -torch.sin(pitch), -cp * torch.cos(yaw)], -1)


def vector_to_pitchyaw(g: torch.Tensor, *, eps: float = 1e-9) -> torch.Tensor:
    """[..., 3] gaze direction (any non-zero length) -> [..., 2] (pitch, yaw) radians.

    Raises ``ToolkitError`` for (near-)zero vectors rather than returning an arbitrary angle.
    At the poles (g = ±y) yaw is atan2(0, 0) = 0 and pitch is ±pi/2; gradients stay finite.
    """
    n = g.norm(dim=-1, keepdim=True)
    if bool((n <= eps).any()):
        raise ToolkitError(f"gaze vector has (near-)zero length (<= {eps}); a direction is required")
    u = g / n
    # Clamp away from ±1: d/dx asin(x) is infinite at the poles.
    pitch = torch.asin((-u[..., 1]).clamp(-1 + 1e-7, 1 - 1e-7))
    gx, gz = -u[..., 0], -u[..., 2]
    # atan2's gradient is 0/0 at (0, 0); nudge the denominator-side so it stays finite at the poles.
    at_pole = (gx.abs() < 1e-12) & (gz.abs() < 1e-12)
    gz = torch.where(at_pole, torch.full_like(gz, 1e-12), gz)
    yaw = torch.atan2(gx, gz)
    return torch.stack([pitch, yaw], -1)


def normalized_head_rotation(head_pitchyaw: torch.Tensor) -> torch.Tensor:
    """[..., 2] head pose (pitch, yaw) in an ETH-XGaze normalized camera -> [..., 3, 3] head-to-camera rotation.

    Normalization leaves the head no roll: the camera's y axis is perpendicular to the head's x axis, so the
    pose is fixed by where the face points, ``f = pitchyaw_to_vector(head_pitchyaw) = R @ (0, 0, -1)``.
    Camera-frame gaze is then ``R @`` head-frame gaze. Where the face points along the camera's y axis
    (pitch ±90°) the head x axis is undefined and falls back to the camera's x axis; the result stays finite.
    """
    z = -pitchyaw_to_vector(head_pitchyaw)
    x = torch.stack([z[..., 2], torch.zeros_like(z[..., 0]), -z[..., 0]], -1)  # e_y × z
    n = x.norm(dim=-1, keepdim=True)
    fallback = torch.zeros_like(x)
    fallback[..., 0] = 1.0
    x = torch.where(n > 1e-6, x / n.clamp_min(1e-6), fallback)
    y = torch.linalg.cross(z, x, dim=-1)
    return torch.stack([x, y, z], -1)


def head_to_camera_gaze(gaze_head: torch.Tensor, head_pose: torch.Tensor) -> torch.Tensor:
    """[B, 2] head-frame gaze, [B, 2] head pose (normalized camera) -> [B, 2] camera-frame gaze (pitch, yaw)."""
    g = (normalized_head_rotation(head_pose) @ pitchyaw_to_vector(gaze_head).unsqueeze(-1)).squeeze(-1)
    return vector_to_pitchyaw(g)


def camera_to_head_gaze(gaze_cam: torch.Tensor, head_pose: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`head_to_camera_gaze`: [B, 2] camera-frame gaze -> [B, 2] head-frame gaze."""
    R = normalized_head_rotation(head_pose)
    return vector_to_pitchyaw((R.transpose(-1, -2) @ pitchyaw_to_vector(gaze_cam).unsqueeze(-1)).squeeze(-1))


def angular_error_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle in degrees between [..., 3] vectors, or between [..., 2] pitch/yaw pairs (converted first)."""
    if a.shape[-1] == 2:
        a = pitchyaw_to_vector(a)
    if b.shape[-1] == 2:
        b = pitchyaw_to_vector(b)
    a = F.normalize(a, dim=-1, eps=EPS)
    b = F.normalize(b, dim=-1, eps=EPS)
    # atan2(|a x b|, a.b) is exact for tiny angles, where acos(dot) rounds to 0 and has infinite gradient.
    cross = torch.linalg.cross(a, b, dim=-1).norm(dim=-1)
    return torch.rad2deg(torch.atan2(cross, (a * b).sum(-1)))
