"""mediapipe's 478-point face mesh as the project's landmarks: iBUG-68, iris centres and sizes, eyelid contours.

Mesh indices follow mediapipe's canonical face mesh (``face_mesh_connections``; points 468-477 exist with
``refine_landmarks=True``). Its "right" eye is the subject's right, the **image-left** eye of a frontal view:
the project's left eye (iBUG 36-41, docs/data.md).
"""

from __future__ import annotations

import numpy as np

from toolkit.errors import ToolkitError

# iBUG-68 index -> mesh index. Derived by sampling mediapipe's own contour loops (face_mesh_connections:
# FACE_OVAL, RIGHT/LEFT_EYE, RIGHT/LEFT_EYEBROW, LIPS, NOSE) by arc length at iBUG's spacing on a frontal face
# (skimage's astronaut): eyes from their corners (the loops' x extremes) at 1/3 and 2/3 of each lid, outer lips
# at sixths of each lip from the corners 61/291, inner lips at quarters from 78/308, the nose bridge at thirds
# from 168 (between the eyes) to the most protruding point 4, the nose base across the nostrils (98 ... 327),
# the brows along the upper brow line. The picks were then made left-right symmetric through the mesh's
# mirror pairs (each differed from its mirror by at most one contour vertex) and agree with the commonly used
# tables to within one contour vertex. The jaw (0-16) is approximate: 17 points at equal arc length along the
# face oval from the height of the outer eye corners round the chin (152); iBUG's jaw follows the jaw bone,
# mediapipe's oval the visible outline, which differ by a few pixels at the jaw angle. Head-pose fitting
# fits all 68 all the same: the jaw pins pitch down (apps.photo.head_pose.PNP_LANDMARKS).
MESH_TO_IBUG68 = np.array([
    127, 234, 132, 58, 172, 136, 149, 148, 152, 377, 378, 365, 397, 288, 361, 454, 356,  # 0-16 jaw (approximate)
    70, 63, 105, 66, 107,  # 17-21 image-left brow, outer -> inner
    336, 296, 334, 293, 300,  # 22-26 image-right brow, inner -> outer
    168, 197, 5, 4,  # 27-30 nose bridge -> tip
    98, 97, 2, 326, 327,  # 31-35 nose base
    33, 159, 158, 133, 153, 144,  # 36-41 image-left eye: outer corner, upper lid, inner corner, lower lid
    362, 385, 386, 263, 373, 380,  # 42-47 image-right eye: inner corner, upper lid, outer corner, lower lid
    61, 40, 37, 0, 267, 270, 291, 321, 314, 17, 84, 91,  # 48-59 outer lips from the image-left corner
    78, 81, 13, 311, 308, 402, 14, 178,  # 60-67 inner lips
], dtype=np.int64)

IRIS_CENTERS = np.array([468, 473])
"""Mesh indices of the iris centres, image-left eye first."""
IRIS_RINGS = np.array([[469, 470, 471, 472], [474, 475, 476, 477]])
"""Mesh indices of the four iris boundary points (right, top, left, bottom of each iris), image-left eye first."""

EYELID_LOOPS = np.array([
    [33, 7, 163, 144, 145, 153, 154, 155, 133, 173, 157, 158, 159, 160, 161, 246],
    [362, 382, 381, 380, 374, 373, 390, 249, 263, 466, 388, 387, 386, 385, 384, 398],
])
"""The eyelid margins as closed loops of 16 mesh points (face_mesh_connections RIGHT_EYE, LEFT_EYE, ordered),
image-left eye first: the visible eyeball is inside."""

FACE_OVAL = np.array([10, 109, 67, 103, 54, 21, 162, 127, 234, 93, 132, 58, 172, 136, 150, 149, 176, 148, 152, 377,
                      400, 378, 379, 365, 397, 288, 361, 323, 454, 356, 389, 251, 284, 332, 297, 338])
"""The face outline as a closed loop of 36 mesh points from the top of the forehead (face_mesh_connections
FACE_OVAL, ordered)."""

N_MESH = 478


def _check_mesh(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[0] != N_MESH or points.shape[1] < 2:
        raise ToolkitError(f"expected the {N_MESH} points of mediapipe's refined face mesh, got {list(points.shape)}")
    return points[:, :2]


def ibug68(points: np.ndarray) -> np.ndarray:
    """[478, 2+] mesh points (pixels) -> [68, 2] iBUG-68 landmarks (pixels)."""
    return _check_mesh(points)[MESH_TO_IBUG68]


def iris(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[478, 2+] mesh points -> (centres [2, 2] pixels, diameters [2] pixels), image-left eye first. A diameter
    is the mean of the horizontal and vertical extents of the iris ring (the lids hide its top and bottom
    less often than they move it)."""
    p = _check_mesh(points)
    ring = p[IRIS_RINGS]  # [2, 4, 2]: right, top, left, bottom
    diam = 0.5 * (np.linalg.norm(ring[:, 0] - ring[:, 2], axis=-1) + np.linalg.norm(ring[:, 1] - ring[:, 3], axis=-1))
    return p[IRIS_CENTERS], diam


def eyelids(points: np.ndarray) -> np.ndarray:
    """[478, 2+] mesh points -> [2, 16, 2] eyelid loops (pixels), image-left eye first."""
    return _check_mesh(points)[EYELID_LOOPS]


def face_outline(points: np.ndarray) -> np.ndarray:
    """[478, 2+] mesh points -> [36, 2] face oval (pixels), from the top of the forehead."""
    return _check_mesh(points)[FACE_OVAL]


def ibug_eyelids(landmarks68: np.ndarray) -> np.ndarray:
    """[68, 2] -> [2, 6, 2] the coarse eyelid polygons iBUG 36-41 and 42-47 (when no mesh is at hand)."""
    lm = np.asarray(landmarks68, np.float64)
    return np.stack([lm[36:42], lm[42:48]])


def ibug_outline(landmarks68: np.ndarray) -> np.ndarray:
    """[68, 2] -> [27, 2] a face outline from the landmarks alone: the jaw then the brows, right to left."""
    lm = np.asarray(landmarks68, np.float64)
    return np.concatenate([lm[0:17], lm[26:16:-1]])
