"""Head poses and cameras of the synthetic data: the pose vector as a rotation and translation, random head
poses, and the ETH-XGaze-style normalized camera aimed at the face.

``pose`` [6] = axis-angle (3, radians) + translation (3, metres) maps the head frame to the world:
``x_world = scale · R(pose[:3]) · x_head + pose[3:]``; cameras are world-to-camera OpenCV.
"""

from __future__ import annotations

import numpy as np
import torch

from toolkit.cameras import Camera
from toolkit.rotations import so3_exp, so3_log


def pose_matrix(pose) -> tuple[np.ndarray, np.ndarray]:
    """[6] axis-angle + translation -> (R [3, 3], t [3]) with x_world = scale · R x_head + t."""
    pose = np.array(pose, np.float64)  # a writable copy (torch.from_numpy rejects read-only views)
    R = so3_exp(torch.from_numpy(pose[:3].copy())).numpy()
    return R, pose[3:6]


def sample_head_pose(rng: np.random.Generator, n: int) -> np.ndarray:
    """[n, 6] random head poses: yaw ±25°, pitch ±15°, roll ±8°, translation ±15 mm."""
    pyr = rng.uniform(-1, 1, (n, 3)) * np.radians([15.0, 25.0, 8.0])
    out = np.zeros((n, 6), np.float32)
    for i, (p, y, r) in enumerate(pyr):
        R = (so3_exp(torch.tensor([0.0, y, 0.0])) @ so3_exp(torch.tensor([p, 0.0, 0.0]))
             @ so3_exp(torch.tensor([0.0, 0.0, r])))
        out[i, :3] = so3_log(R).numpy()
    out[:, 3:] = rng.uniform(-0.015, 0.015, (n, 3))
    return out


def normalized_camera(rig_camera: Camera, face_center_world: np.ndarray, head_R_world: np.ndarray, res: int,
                      *, distance: float = 0.6, crop: float = 0.26) -> Camera:
    """ETH-XGaze-style normalized camera: from the rig camera's centre, aimed at the face centre.

    The camera looks at ``face_center_world`` from ``distance`` metres along the rig camera's ray,
    with no roll relative to the head (its x axis is perpendicular to the head's x axis' complement,
    as in the ETH-XGaze normalization: down = forward × head_x), and a focal length such that a
    ``crop`` metres wide square at the face centre fills the ``res`` × ``res`` image.
    """
    C = rig_camera.center.numpy().astype(np.float64)
    fwd = face_center_world - C
    fwd /= max(np.linalg.norm(fwd), 1e-12)
    down = np.cross(fwd, head_R_world[:, 0])
    down /= max(np.linalg.norm(down), 1e-12)
    right = np.cross(down, fwd)
    R = np.stack([right, down, fwd])
    center = face_center_world - distance * fwd
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ center
    f = res * distance / crop
    K = np.array([[f, 0, res / 2], [0, f, res / 2], [0, 0, 1]])
    return Camera(torch.from_numpy(K).float(), torch.from_numpy(V).float(), res, res)
