"""Pinhole cameras in OpenCV axes.

Conventions (stated once, used by render/, geometry/ and train/):
- Camera axes are **OpenCV**: x right, y down, z forward (points in front have z > 0).
- ``viewmat`` is world-to-camera [4, 4]: ``x_cam = R @ x_world + t``.
- ``K`` [3, 3] is in pixels; pixel (i, j) (row, column) has its centre at image coordinates
  (u, v) = (j + 0.5, i + 0.5), so a principal point of (W/2, H/2) is the image centre.
- The OpenGL pair from :func:`opengl_projection` / :func:`opengl_view` maps the same point to the same
  pixel (y flipped to GL's bottom-up framebuffer rows by the projection, not by the caller).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from toolkit.errors import ToolkitError


@dataclass
class Camera:
    """One pinhole camera: K [3, 3] pixels, viewmat [4, 4] world-to-camera, image size in pixels."""

    K: torch.Tensor
    viewmat: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        self.K = torch.as_tensor(self.K, dtype=torch.float32)
        self.viewmat = torch.as_tensor(self.viewmat, dtype=torch.float32)
        if self.K.shape != (3, 3):
            raise ToolkitError(f"Camera.K: expected shape (3, 3), got {tuple(self.K.shape)}")
        if self.viewmat.shape != (4, 4):
            raise ToolkitError(f"Camera.viewmat: expected shape (4, 4), got {tuple(self.viewmat.shape)}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ToolkitError(f"Camera: width and height must be >= 1, got {self.width}x{self.height}")
        if not (torch.isfinite(self.K).all() and torch.isfinite(self.viewmat).all()):
            raise ToolkitError("Camera: K and viewmat must be finite")
        self.width, self.height = int(self.width), int(self.height)

    @property
    def camtoworld(self) -> torch.Tensor:
        """[4, 4] camera-to-world (the inverse of ``viewmat``)."""
        return torch.linalg.inv(self.viewmat)

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[..., 3] world points -> ([..., 2] pixel coordinates (u, v), [..., ] camera depth z)."""
        return project_points(points, self.viewmat, self.K)

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for an image of another size (intrinsics scaled per axis)."""
        return Camera(resize_intrinsics(self.K, self.width, self.height, width, height), self.viewmat, width, height)

    def to(self, device: torch.device | str) -> "Camera":
        return Camera(self.K.to(device), self.viewmat.to(device), self.width, self.height)


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> torch.Tensor:
    """[3, 3] pinhole intrinsics in pixels."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)


def intrinsics_from_fov(fov_y_deg: float, width: int, height: int) -> torch.Tensor:
    """[3, 3] intrinsics with square pixels, vertical field of view in degrees, centred principal point."""
    if not 0 < fov_y_deg < 180:
        raise ToolkitError(f"fov_y_deg must be in (0, 180), got {fov_y_deg}")
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return intrinsics(f, f, width / 2, height / 2)


def resize_intrinsics(K: torch.Tensor, width: int, height: int, new_width: int, new_height: int) -> torch.Tensor:
    """Scale [..., 3, 3] intrinsics from a (width, height) image to (new_width, new_height).

    Pixel-centre convention (u = j + 0.5) makes this a pure scale of fx, cx (and fy, cy): no half-pixel shift.
    """
    sx, sy = new_width / width, new_height / height
    K = K.clone()
    K[..., 0, :] = K[..., 0, :] * sx
    K[..., 1, :] = K[..., 1, :] * sy
    return K


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor | None = None) -> torch.Tensor:
    """World-to-camera [4, 4] for a camera at ``eye`` looking at ``target`` (OpenCV axes).

    ``up`` is the world direction that should appear *up* in the image. The default (0, -1, 0) suits the
    project's OpenCV-like head/world frame (y down). Raises when eye == target or the view direction is
    parallel to ``up``.
    """
    eye = torch.as_tensor(eye, dtype=torch.float32)
    target = torch.as_tensor(target, dtype=torch.float32)
    up = torch.tensor([0.0, -1.0, 0.0]) if up is None else torch.as_tensor(up, dtype=torch.float32)
    forward = target - eye
    if forward.norm() < 1e-9:
        raise ToolkitError("look_at: eye and target coincide; the view direction is undefined")
    z = forward / forward.norm()
    # Right-handed OpenCV basis: y (image down) = -up projected, x = y × z.
    x = torch.linalg.cross(-up, z)
    if x.norm() < 1e-6:
        raise ToolkitError("look_at: view direction is parallel to 'up'; pass another up vector")
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z], 0)
    V = torch.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V


def project_points(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[..., 3] world points -> ([..., 2] pixels (u, v), [...] depth). No clipping; depth may be <= 0."""
    p = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = p[..., 2]
    zs = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    u = K[0, 0] * p[..., 0] / zs + K[0, 1] * p[..., 1] / zs + K[0, 2]
    v = K[1, 1] * p[..., 1] / zs + K[1, 2]
    return torch.stack([u, v], -1), z


def orbit_rig(
    n_yaw: int,
    n_pitch: int,
    *,
    radius: float,
    yaw_range_deg: float,
    pitch_range_deg: float,
    target: tuple[float, float, float] = (0.0, 0.0, 0.0),
    fov_y_deg: float = 20.0,
    width: int = 128,
    height: int = 128,
) -> list[Camera]:
    """Cameras on a sphere arc around ``target`` facing it; the subject faces world -z (towards the rig).

    World is the OpenCV-like head frame (y down). Yaw spans ±yaw_range_deg about the vertical axis
    (positive = towards +x), pitch ±pitch_range_deg (positive = camera above the head, at -y).
    Ordered pitch-major: index = i_pitch * n_yaw + i_yaw.
    """
    cams = []
    K = intrinsics_from_fov(fov_y_deg, width, height)
    tgt = torch.tensor(target, dtype=torch.float32)
    for p in torch.linspace(-pitch_range_deg, pitch_range_deg, n_pitch) if n_pitch > 1 else torch.zeros(1):
        for y in torch.linspace(-yaw_range_deg, yaw_range_deg, n_yaw) if n_yaw > 1 else torch.zeros(1):
            pr, yr = math.radians(float(p)), math.radians(float(y))
            # Subject looks along world -z; cameras sit at negative z, "above" is -y.
            eye = tgt + radius * torch.tensor(
                [math.sin(yr) * math.cos(pr), -math.sin(pr), -math.cos(yr) * math.cos(pr)]
            )
            cams.append(Camera(K.clone(), look_at(eye, tgt), width, height))
    return cams


def eth_xgaze_rig(
    *, radius: float = 1.0, width: int = 128, height: int = 128, fov_y_deg: float = 14.0,
    target: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> list[Camera]:
    """An 18-camera arc like ETH-XGaze's capture rig: 6 yaws in ±60° × 3 pitches in ±30°."""
    return orbit_rig(6, 3, radius=radius, yaw_range_deg=60.0, pitch_range_deg=30.0, target=target,
                     fov_y_deg=fov_y_deg, width=width, height=height)


def opengl_projection(K: torch.Tensor, width: int, height: int, near: float, far: float) -> torch.Tensor:
    """[4, 4] OpenGL clip-from-eye matrix matching OpenCV intrinsics ``K`` for a ``width`` × ``height`` image.

    Use with :func:`opengl_view` (eye space = OpenCV camera space with y and z negated). NDC y is mapped
    to ``2 v / H - 1``, so GL window row r (counted bottom-up, the first row ``glReadPixels`` returns)
    is image row r: a read-back needs no flip. The price is mirrored winding: a triangle that is
    counter-clockwise in the image is clockwise in GL's window space.
    """
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    skew = float(K[0, 1])
    P = torch.zeros(4, 4)
    # Eye space: x_e = x_c, y_e = -y_c, z_e = -z_c (OpenGL looks down -z).
    # u = fx x_c/z_c + s y_c/z_c + cx ; NDC x = 2u/W - 1 ; w_clip = z_c = -z_e.
    P[0, 0] = 2 * fx / width
    P[0, 1] = -2 * skew / width
    P[0, 2] = -(2 * cx / width - 1)
    # Framebuffer row r (bottom-up in GL) = image row r: NDC y = 2v/H - 1 (no flip to GL's up).
    P[1, 1] = -2 * fy / height
    P[1, 2] = -(2 * cy / height - 1)
    P[2, 2] = -(far + near) / (far - near)
    P[2, 3] = -2 * far * near / (far - near)
    P[3, 2] = -1.0
    return P


def opengl_view(viewmat: torch.Tensor) -> torch.Tensor:
    """[4, 4] OpenGL eye-from-world: the OpenCV world-to-camera with camera y and z negated."""
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=viewmat.dtype, device=viewmat.device))
    return flip @ viewmat
