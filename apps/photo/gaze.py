"""The gaze of a face in a photo, estimated from its irises, or given in the photo camera's frame.

Each iris centre's camera ray is intersected with the model's eyeball sphere (radius s · r) posed by the head
pose and placed against that eye's corners (:func:`iris_gaze`); the gaze of that eye is the unit vector from the
eyeball centre to the hit point (the pupil centre lies on the sphere in the generator's eye). The two eyes' vectors are
averaged in the head frame (both eyes turn by one rotation in the project's model: docs/data.md). A ray that
misses the sphere (landmark noise on a face turned away) takes the sphere point nearest to it.

Conventions (toolkit.rotations): pitch = asin(−g_y), yaw = atan2(−g_x, −g_z), radians.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from toolkit.rotations import vector_to_pitchyaw

MAX_GAZE = math.radians(80.0)
"""A larger estimate is refused as implausible (both the project's files and the model expect a gaze towards the
front)."""


def pitchyaw(g: np.ndarray) -> np.ndarray:
    """[..., 3] directions -> [..., 2] (pitch, yaw) radians, float64."""
    return vector_to_pitchyaw(torch.from_numpy(np.asarray(g, np.float64))).numpy()


def pitchyaw_vector(py: np.ndarray) -> np.ndarray:
    """[..., 2] (pitch, yaw) -> [..., 3] unit directions."""
    p, y = np.asarray(py, np.float64)[..., 0], np.asarray(py, np.float64)[..., 1]
    return np.stack([-np.cos(p) * np.sin(y), -np.sin(p), -np.cos(p) * np.cos(y)], -1)


def ray_sphere(direction: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """The first point where the ray from the origin along ``direction`` [3] meets the sphere, else the sphere
    point nearest to the ray."""
    d = direction / np.linalg.norm(direction)
    along = float(d @ center)
    closest = along * d
    gap = float(np.linalg.norm(center - closest))
    if gap >= radius:
        return center + radius * (closest - center) / max(gap, 1e-12)
    return (along - math.sqrt(radius * radius - gap * gap)) * d


EYE_CORNERS = ((36, 39), (42, 45))
"""iBUG corners of the image-left and image-right eye: each eyeball is placed relative to its own corners."""


def iris_gaze(iris_px: np.ndarray, landmarks68: np.ndarray, K: np.ndarray, pose, model) -> np.ndarray:
    """Head-frame gaze [2] (pitch, yaw) of a face from its iris centres ``iris_px`` [2, 2] and landmarks
    ``landmarks68`` [68, 2] (photo pixels, image-left eye first), the photo's ``K`` [3, 3], its ``pose``
    (``apps.photo.head_pose.HeadPose``) and head ``model`` (``apps.photo.face_model.FaceModel``).

    Each eyeball sits where the model puts it relative to the midpoint of that eye's corners, the midpoint taken
    from the photo (its ray, at the posed model's depth) rather than from the posed model: a millimetre of
    eyeball misplacement is ~5° of gaze, and the whole-face fit misplaces the eyes by more than its corners do
    (on synthetic renders: 12.4° mean error against 18.0° with the posed model's eyeballs)."""
    Kinv = np.linalg.inv(np.asarray(K, np.float64))
    lm = np.asarray(landmarks68, np.float64)
    vecs = []
    for k, (a, b) in enumerate(EYE_CORNERS):
        mid_model = pose.to_camera(0.5 * (model.landmarks[a] + model.landmarks[b]))
        ray = Kinv @ np.r_[0.5 * (lm[a] + lm[b]), 1.0]
        c = ray / ray[2] * mid_model[2] + pose.to_camera(model.eye_centers[k]) - mid_model
        hit = ray_sphere(Kinv @ np.r_[iris_px[k], 1.0], c, pose.scale * float(model.eye_radii[k]))
        vecs.append(pose.R.T @ ((hit - c) / np.linalg.norm(hit - c)))
    g = np.mean(vecs, 0)
    return pitchyaw(g / np.linalg.norm(g))


def camera_gaze_to_head(pitchyaw_photo: np.ndarray, head_R: np.ndarray) -> np.ndarray:
    """A gaze given in the photo camera's frame (a labels CSV) -> the head frame (pitch, yaw)."""
    return pitchyaw(np.asarray(head_R, np.float64).T @ pitchyaw_vector(pitchyaw_photo))
