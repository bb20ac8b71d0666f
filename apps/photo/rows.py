"""One face of a photo as one row of a native subject file (docs/data.md, docs/photos.md), and the file itself.

The row's world is the head frame scaled by the head scale s (``pose`` = 0, ``scale`` = s: x_world = s · x_head),
the centre of the poses the model was trained on; the stored camera (``w2c_Rmat``, ``w2c_Tvec``, ``inmat``) is
the normalized camera in that world (apps.photo.normalize). ``GazeDataset`` folds s into the world as it reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from apps.photo import landmarks68 as lm68
from toolkit.errors import ToolkitError

MAX_TURN_DEG = 75.0
"""A face turned further from the camera (head −z against the direction to the camera) is refused: the mesh's
fit of a near-profile is unreliable and most of the face is hidden."""

MIN_FACE_PX = 64
"""Faces narrower than this in the photo (pixels) are skipped: too few pixels for the eyes."""

EXTRA_ROW_KEYS = ("warp", "face_box", "source_size", "iris_centers")
"""The rows' keys beyond the format's: what undoes the normalization (``warp`` [3, 3] photo → crop pixels,
``face_box`` [4] x0, y0, x1, y1 photo pixels, ``source_size`` [2] width, height) and the iris centres [2, 2]
in crop pixels. Readers of the format ignore keys they do not know."""


@dataclass
class FaceObservation:
    """One face in a photo, photo pixels (u = 0 the left edge): ``landmarks68`` [68, 2]; ``iris_centers`` [2, 2]
    and ``iris_diameters`` [2] (None when unknown); ``eyelids`` [2, L, 2] eyelid loops and ``outline`` [K, 2] the
    face's outline (image-left eye first)."""

    landmarks68: np.ndarray
    iris_centers: np.ndarray | None
    iris_diameters: np.ndarray | None
    eyelids: np.ndarray
    outline: np.ndarray

    @classmethod
    def from_mesh(cls, points: np.ndarray) -> "FaceObservation":
        """From mediapipe's 478 refined mesh points [478, 2+]."""
        centers, diameters = lm68.iris(points)
        return cls(lm68.ibug68(points), centers, diameters, lm68.eyelids(points), lm68.face_outline(points))

    @classmethod
    def from_landmarks(cls, landmarks68: np.ndarray, iris_centers: np.ndarray | None = None) -> "FaceObservation":
        """From iBUG-68 landmarks alone (and iris centres when known): iBUG eyelid hexagons, jaw + brow outline."""
        lm = np.asarray(landmarks68, np.float64)
        return cls(lm, None if iris_centers is None else np.asarray(iris_centers, np.float64), None,
                   lm68.ibug_eyelids(lm), lm68.ibug_outline(lm))

    def box(self) -> np.ndarray:
        """[4] (x0, y0, x1, y1): the bounding box of the landmarks and the outline."""
        p = np.concatenate([self.landmarks68, self.outline])
        return np.concatenate([p.min(0), p.max(0)])


@dataclass
class FaceRow:
    """One row: ``arrays`` every per-row key of the file (no leading N), ``source_landmarks`` [68, 2] in photo
    pixels and ``notes`` (the head pose's RMS, the scale's source) for the report and the contact sheet."""

    arrays: dict[str, np.ndarray]
    source_landmarks: np.ndarray
    notes: dict = field(default_factory=dict)


def _gaze_head(obs: FaceObservation, K: np.ndarray, pose, model, gaze_photo: np.ndarray | None) -> np.ndarray:
    from apps.photo.gaze import MAX_GAZE, camera_gaze_to_head, iris_gaze

    if gaze_photo is not None:
        g = camera_gaze_to_head(gaze_photo, pose.R)
    elif obs.iris_centers is not None:
        g = iris_gaze(obs.iris_centers, obs.landmarks68, K, pose, model)
    else:
        raise ToolkitError("no iris centres and no labelled gaze: the gaze cannot be estimated")
    if not np.isfinite(g).all() or np.abs(g).max() > MAX_GAZE:
        raise ToolkitError(f"the estimated gaze (pitch {math.degrees(g[0]):.0f}°, yaw {math.degrees(g[1]):.0f}°) is "
                           f"beyond ±{math.degrees(MAX_GAZE):.0f}° of the head: the iris fit failed")
    return g


def _face_center(obs: FaceObservation, K: np.ndarray, pose, model) -> np.ndarray:
    """[3] the face centre the normalized camera aims at (photo camera frame): at the posed model's face-centre
    depth, on the ray through the mean of the observed iBUG 36, 39, 42, 45, 48, 54 (shifted by the posed model's
    own gap between the mean of those six projections and the projection of their 3D mean, a perspective effect
    of a few pixels). The crop is then centred on the face as detected, not as the rigid model fits it (their gap
    is the fit's residual: 7.5 against 4.3 px of crop eye-centre error at 512² in benchmarks/prepare.py)."""
    from apps.photo.face_model import FACE_CENTER_LANDMARKS

    idx = list(FACE_CENTER_LANDMARKS)
    project = lambda x: (x[..., :2] / x[..., 2:3]) @ np.diag(np.diag(K)[:2]) + K[:2, 2]  # noqa: E731
    center = pose.to_camera(model.face_center)
    gap = project(center) - project(pose.to_camera(model.landmarks[idx])).mean(0)
    ray = np.linalg.inv(K) @ np.r_[obs.landmarks68[idx].mean(0) + gap, 1.0]
    return ray / ray[2] * center[2]


def _check_eyes_in_photo(obs: FaceObservation, width: int, height: int) -> None:
    """A face cut by the photo's edge through an eye is refused: the landmarker places the eye beyond the edge
    all the same (it fits a whole face), but its iris, gaze and mask would be guesses on black."""
    for side, sl in (("image-left", slice(36, 42)), ("image-right", slice(42, 48))):
        p = obs.landmarks68[sl]
        if obs.iris_centers is not None:
            p = np.concatenate([p, obs.iris_centers[:1] if side == "image-left" else obs.iris_centers[1:]])
        if (p < 0).any() or (p[:, 0] > width).any() or (p[:, 1] > height).any():
            raise ToolkitError(f"the face is cut off by the photo's edge (its {side} eye is outside the photo): use a "
                               "photo showing the whole face")


def prepare_face(bgr: np.ndarray, obs: FaceObservation, K: np.ndarray, target, *, frame_index: int = 0,
                 gaze_photo: np.ndarray | None = None, scale: float | None = None, person=None) -> FaceRow:
    """Fit, normalize and label one face: ``bgr`` [H, W, 3] uint8 the photo, ``obs`` the face, ``K`` [3, 3] the
    photo's intrinsics, ``target`` (``apps.photo.face_model.Target``) the head model and normalization;
    ``gaze_photo`` [2] a given gaze (radians, photo camera frame) instead of the iris estimate; ``scale`` a given
    head scale instead of the iris'; ``person`` a callable [S, S, 3] RGB -> [S, S] person probability
    (``FaceFinder.person``) to refine the head mask. A face that cannot be used is a ToolkitError."""
    from apps.photo import masks
    from apps.photo.gaze import pitchyaw, pitchyaw_vector
    from apps.photo.head_pose import face_direction_deg, head_pose
    from apps.photo.normalize import normalize, warp_image, warp_points

    model, size = target.model, target.size
    _check_eyes_in_photo(obs, bgr.shape[1], bgr.shape[0])
    pose = head_pose(obs.landmarks68, K, model, iris_diameters_px=obs.iris_diameters, scale=scale)
    turn = face_direction_deg(pose.R, pose.t, model.face_center, pose.scale)
    if turn > MAX_TURN_DEG:
        raise ToolkitError(f"the face is turned {turn:.0f}° from the camera (at most {MAX_TURN_DEG:.0f}°)")
    norm = normalize(pose.R, _face_center(obs, K, pose, model), K, size, target.distance, target.crop)
    crop = warp_image(bgr, norm.warp, size)
    W = norm.warp
    lm, lids, outline = (warp_points(a, W) for a in (obs.landmarks68, obs.eyelids, obs.outline))
    person_p = None if person is None else person(np.ascontiguousarray(crop[..., ::-1]))
    head = masks.head_mask(size, lm, outline, lids, person_p)
    left, right = masks.eye_masks(size, lids)
    g_head = _gaze_head(obs, K, pose, model, gaze_photo)
    R_w2c, t_w2c = norm.w2c(pose.R, pose.t)
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    iris = np.full((2, 2), np.nan) if obs.iris_centers is None else warp_points(obs.iris_centers, W)
    arrays = {
        "face_patch": crop, "head_mask": head, "left_eye_mask": left, "right_eye_mask": right,
        "facial_landmarks": f32(lm), "facial_landmarks_3d": f32(pose.scale * model.landmarks),
        "latent_codes": np.zeros(target.code_dim, np.float32), "pose": np.zeros(6, np.float32),
        "scale": f32([pose.scale]), "w2c_Rmat": f32(R_w2c), "w2c_Tvec": f32(t_w2c), "inmat": f32(norm.K),
        "pitchyaw_head": f32(g_head), "face_head_pose": f32(pitchyaw(R_w2c @ np.array([0.0, 0.0, -1.0]))),
        "cam_index": np.zeros(1, np.int32), "frame_index": np.array([frame_index], np.int32),
        "vertice": f32(pose.scale * model.mesh), "pitchyaw_cam": f32(pitchyaw(R_w2c @ pitchyaw_vector(g_head))),
        "warp": f32(W), "face_box": f32(obs.box()), "source_size": np.array(bgr.shape[1::-1], np.int32),
        "iris_centers": f32(np.nan_to_num(iris, nan=-1.0)),
    }
    notes = {"rms_px": pose.rms_px, "scale_source": pose.scale_source, "turn_deg": turn, "distance_m": norm.distance}
    return FaceRow(arrays, np.asarray(obs.landmarks68, np.float64), notes)


def photo_rows(photo, finder, target, *, frame_index: int = 0, largest_face: bool = False, focal: float | None = None,
               scale: float | None = None, gaze: np.ndarray | None = None) -> tuple[list[FaceRow], list[str]]:
    """The rows of one decoded photo (``apps.photo.images.Photo``), largest face first, and a problem line for
    each face left out. ``finder`` an ``apps.photo.faces.FaceFinder``; ``target`` the head model and
    normalization (``apps.photo.face_model``); ``focal`` pixels (default EXIF, else 1.2 × the longer side);
    ``gaze`` [2] a labelled gaze (radians, photo camera frame), which keeps the largest face only. A photo with
    no usable face is a ToolkitError saying why."""
    from apps.photo.images import photo_focal, photo_intrinsics

    faces, unfitted = finder.faces(np.ascontiguousarray(photo.bgr[..., ::-1]))
    if largest_face or gaze is not None:  # one labelled gaze a photo: its largest face
        faces = faces[:1]
    small = [f for f in faces if f.width < MIN_FACE_PX]
    faces = [f for f in faces if f.width >= MIN_FACE_PX]
    if not faces:
        if small:
            raise ToolkitError(f"the face found is {small[0].width:.0f} px wide, under {MIN_FACE_PX} px: use a larger "
                               "photo (the original, not a thumbnail) or one taken closer")
        if unfitted:
            raise ToolkitError("a face was detected but the landmarker could not fit it (a profile or an occluded "
                               "face?)")
        raise ToolkitError(f"no face found (expected a face at least {MIN_FACE_PX} px wide, whole in the photo and "
                           f"turned less than {MAX_TURN_DEG:.0f}° from the camera)")
    K = photo_intrinsics(*photo.size, photo_focal(photo, focal)[0])
    rows, problems = [], []
    for k, face in enumerate(faces):
        try:
            rows.append(prepare_face(photo.bgr, FaceObservation.from_mesh(face.points), K, target,
                                     frame_index=frame_index, gaze_photo=gaze, scale=scale, person=finder.person))
        except ToolkitError as e:
            problems.append(f"face {k + 1} of {len(faces)}: {e}")
    if not rows:
        raise ToolkitError("; ".join(problems))
    return rows, problems


def subject_arrays(model) -> dict[str, np.ndarray]:
    """The file's subject-level arrays: the head model's neutral mesh and eyeballs (head frame)."""
    return {"neutral_vertice": np.asarray(model.mesh, np.float32), "mesh_faces": np.asarray(model.mesh_faces, np.int32),
            "eyeball_centers": np.asarray(model.eye_centers, np.float32),
            "eyeball_radii": np.asarray(model.eye_radii, np.float32)}


def write_rows(path, rows: list[FaceRow], target, attrs: dict):
    """Write ``rows`` as one subject file (atomically: ``train.data.format.write_subject_h5``)."""
    from train.data.format import write_subject_h5

    if not rows:
        raise ToolkitError(f"{path}: no rows to write")
    stacked = {k: np.stack([r.arrays[k] for r in rows]) for k in rows[0].arrays}
    return write_subject_h5(path, stacked, subject=subject_arrays(target.model), attrs=attrs)
