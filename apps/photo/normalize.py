"""ETH-XGaze-style data normalization of a face in a photo: the normalized camera, the warp, the crop.

As ETH-XGaze's ``normalizeData_face`` (xucong-zhang/ETH-XGaze, normalization_example.py L36-L66): the camera is
turned to look at the face centre (mean of iBUG 36, 39, 42, 45, 48, 54; L36-L39) with no roll relative to the head
(down = forward × head x, right = down × forward; L56-L62), and the image is warped by the homography
W = K_n · S · R_n · K⁻¹ with S = diag(1, 1, d_n / d) (L44-L64), which scales the face to how it would look from
the normalized distance d_n. The rotation is the project's own rule, ``train.data.poses.normalized_camera``, so a
photo's crop is framed as the generator's images are.

The stored camera is the project's normalized camera: it looks at the face centre from d_n along the same ray,
with the focal length that fills ``size`` pixels with ``crop`` metres at the face. The warp images the face as
that camera would up to perspective across the face's depth (the photo was taken from d, not d_n); exact when
d = d_n.

Pixel convention: u = 0 is the left edge of column 0 (docs/data.md) for every point and for ``W``; OpenCV's
integer-centre pixels only inside :func:`warp_image`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from toolkit.cameras import Camera


@dataclass
class Normalization:
    """One face's normalization. ``R`` [3, 3] photo camera → normalized camera rotation, ``center`` [3] the
    normalized camera's centre in the photo camera frame, ``K`` [3, 3] its intrinsics for the ``size`` × ``size``
    crop, ``warp`` [3, 3] photo pixels → crop pixels, ``distance`` the face centre's distance from the photo's
    camera (metres), ``face_center`` [3] in the photo camera frame. All float64."""

    R: np.ndarray
    center: np.ndarray
    K: np.ndarray
    warp: np.ndarray
    distance: float
    face_center: np.ndarray
    size: int

    def w2c(self, head_R: np.ndarray, head_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The normalized camera in the world x_world = s · x_head (world = the scaled head frame, pose 0):
        x_photo = R_h x_world + t_h, so w2c = (R_n R_h, R_n (t_h − C_n))."""
        return self.R @ head_R, self.R @ (head_t - self.center)


def normalize(head_R: np.ndarray, face_center_cam: np.ndarray, K_photo: np.ndarray, size: int, distance: float,
              crop: float) -> Normalization:
    """The normalization of a face whose head x axis is ``head_R[:, 0]`` and whose centre is
    ``face_center_cam`` [3] (photo camera frame), seen by a photo camera ``K_photo`` [3, 3]; ``distance``,
    ``crop`` in metres, ``size`` in pixels."""
    from train.data.poses import normalized_camera

    origin = Camera(torch.eye(3), torch.eye(4), 1, 1)  # the photo's camera: the world is its frame
    fc = np.asarray(face_center_cam, np.float64)
    cam = normalized_camera(origin, fc, np.asarray(head_R, np.float64), size, distance=distance, crop=crop)
    V = cam.viewmat.numpy().astype(np.float64)  # float32 inside: ~1e-7 relative, 1e-4 px at 512 pixels
    R, K_n = V[:3, :3], cam.K.numpy().astype(np.float64)
    d = float(np.linalg.norm(fc))
    S = np.diag([1.0, 1.0, distance / d])
    W = K_n @ S @ R @ np.linalg.inv(np.asarray(K_photo, np.float64))
    return Normalization(R, -R.T @ V[:3, 3], K_n, W / W[2, 2], d, fc, int(size))


def warp_points(points: np.ndarray, W: np.ndarray) -> np.ndarray:
    """[..., 2] pixels -> [..., 2] pixels through the homography ``W`` [3, 3] (same convention both sides)."""
    p = np.asarray(points, np.float64)
    h = p @ W[:, :2].T + W[:, 2]
    return h[..., :2] / h[..., 2:3]


def _shift(dx: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dx], [0, 0, 1.0]])


def to_opencv(W: np.ndarray) -> np.ndarray:
    """A homography between u = 0 left-edge pixels -> the same map between OpenCV's integer-centre pixels."""
    return _shift(-0.5) @ W @ _shift(0.5)


def warp_image(image: np.ndarray, W: np.ndarray, size: int, *, border_value=0) -> np.ndarray:
    """[H, W(, C)] image -> [size, size(, C)] crop through ``W`` (photo pixels → crop pixels), bilinear; where the
    crop shrinks the photo by more than 1.5 the photo region under the crop is first area-averaged to about the
    crop's scale, so the warp does not alias (a 12-megapixel photo's face is several crop pixels a pixel).
    Outside the photo is ``border_value``."""
    import cv2

    H, Wd = image.shape[:2]
    inv = np.linalg.inv(W)
    corners = warp_points(np.array([[0, 0], [size, 0], [size, size], [0, size]], np.float64), inv)
    x0, y0 = np.clip(np.floor(corners.min(0)) - 2, 0, [Wd, H]).astype(int)
    x1, y1 = np.clip(np.ceil(corners.max(0)) + 2, 0, [Wd, H]).astype(int)
    if x1 - x0 < 1 or y1 - y0 < 1:
        return np.full((size, size) + image.shape[2:], border_value, image.dtype)
    roi = image[y0:y1, x0:x1]
    # photo pixels per crop pixel at the crop's centre: sqrt of the Jacobian determinant of W⁻¹ there
    c = np.array([size / 2, size / 2, 1.0])
    h = inv @ c
    J = (inv[:2, :2] * h[2] - np.outer(h[:2], inv[2, :2])) / h[2] ** 2
    k = float(np.sqrt(abs(np.linalg.det(J))))
    T = _shift(0.0)
    T[:2, 2] = [-x0, -y0]  # photo -> roi
    if k > 1.5:
        n = int(k)
        sw, sh = max(1, -(-roi.shape[1] // n)), max(1, -(-roi.shape[0] // n))
        sx, sy = roi.shape[1] / sw, roi.shape[0] / sh
        roi = cv2.resize(roi, (sw, sh), interpolation=cv2.INTER_AREA)  # edges map to edges: u_small = u_roi / s
        T = np.diag([1 / sx, 1 / sy, 1.0]) @ T
    M = to_opencv(W @ np.linalg.inv(T))
    return cv2.warpPerspective(np.ascontiguousarray(roi), M, (size, size), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=border_value)
