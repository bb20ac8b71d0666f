"""The 3D head a photo is fitted with, and the normalization a run was trained in (``--like RUN_DIR``).

Without a run: the procedural default head (``train.data.synthetic.build_subject`` of the average identity,
``SubjectParams()``): its 68 iBUG landmarks, eyeballs and neutral mesh in the head frame (metres; x image-right,
y down, the face towards -z: docs/data.md), with the generator's normalization (0.6 m, 0.26 m). With a run: the
landmarks (``scene.metadata["landmarks"]``), eyeballs (``metadata["eyes"]``) and neutral mesh of its geometry
stage, the distance and crop of its subject files' ``normalization`` attribute and its ``data.res``, so a photo
lands in the frame the model was trained in.
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass

import numpy as np

from toolkit.errors import ToolkitError

FACE_CENTER_LANDMARKS = (36, 39, 42, 45, 48, 54)
"""The normalization's face centre: the mean of the eye corners and the mouth corners (ETH-XGaze's face model
rows, docs/data.md)."""


@dataclass
class FaceModel:
    """A head in its head frame (metres): ``landmarks`` [68, 3] iBUG, ``eye_centers`` [2, 3] and ``eye_radii``
    [2] (image-left eye first), ``mesh`` [V, 3] float32 neutral vertices with ``mesh_faces`` [F, 3] int32;
    ``source`` says where it came from."""

    landmarks: np.ndarray
    eye_centers: np.ndarray
    eye_radii: np.ndarray
    mesh: np.ndarray
    mesh_faces: np.ndarray
    source: str

    @property
    def face_center(self) -> np.ndarray:
        """[3] the normalization's face centre in the head frame (:data:`FACE_CENTER_LANDMARKS`)."""
        return self.landmarks[list(FACE_CENTER_LANDMARKS)].mean(0)


@dataclass
class Target:
    """Where a photo's faces land: the head model, the normalized camera's ``distance`` and ``crop`` (metres),
    the crop's ``size`` (pixels) and the code width of the rows' zero ``latent_codes``."""

    model: FaceModel
    distance: float
    crop: float
    size: int
    code_dim: int = 144


@functools.lru_cache(maxsize=1)
def default_face_model() -> FaceModel:
    """The procedural average head (built once per process, ~1 s)."""
    from train.data.subject_params import SubjectParams
    from train.data.synthetic import build_subject

    s = build_subject(SubjectParams())
    return FaceModel(s.landmarks().astype(np.float64), s.eye_centers.astype(np.float64),
                     np.full(2, s.eye_radius), s.neutral_vertices().astype(np.float32),
                     s.head_faces.astype(np.int32), "the procedural average head (train.data.synthetic)")


def subject_face_model(subject, source: str = "a procedural subject") -> FaceModel:
    """A ``train.data.synthetic.Subject``'s own head (tests and benchmarks: the exact model of a render)."""
    return FaceModel(subject.landmarks().astype(np.float64), subject.eye_centers.astype(np.float64),
                     np.full(2, subject.eye_radius), subject.neutral_vertices().astype(np.float32),
                     subject.head_faces.astype(np.int32), source)


def default_target(size: int = 512) -> Target:
    from train.data.generate import NORM_CROP, NORM_DISTANCE

    return Target(default_face_model(), NORM_DISTANCE, NORM_CROP, size)


def _run_normalization(files) -> tuple[float, float]:
    """(distance, crop) from the first subject file's ``normalization`` attribute, else the generator's."""
    import h5py

    from train.data.generate import NORM_CROP, NORM_DISTANCE

    for f in files[:1]:
        try:
            with h5py.File(f, "r") as h:
                text = h.attrs.get("normalization")
            d = json.loads(text) if isinstance(text, (str, bytes)) else {}
            dist, crop = float(d.get("distance", NORM_DISTANCE)), float(d.get("crop", NORM_CROP))
        except (OSError, ValueError, TypeError, AttributeError) as e:
            raise ToolkitError(f"{f}: attribute 'normalization' cannot be read as JSON {{distance, crop}} "
                               f"({e.__class__.__name__})") from None
        if not (0 < dist < 100 and 0 < crop < 100):
            raise ToolkitError(f"{f}: attribute 'normalization' gives distance {dist} m and crop {crop} m; expected "
                               "positive metres")
        return dist, crop
    return NORM_DISTANCE, NORM_CROP


def run_target(run_dir: str | os.PathLike, size: int | None = None) -> Target:
    """The :class:`Target` of a trained run: its geometry's head and eyes, its data's normalization and
    ``data.res`` (``size`` overrides the resolution)."""
    from geometry.mesh_files import load_mesh
    from toolkit.eyes import check_eyes_metadata
    from toolkit.scene import GaussianScene
    from train.model.gaussian_config import UNITS_PER_METRE
    from train.trained_run import TrainedRun

    run = TrainedRun.open(run_dir)
    scene_path = run.context.path("geometry", "scene")
    meta = GaussianScene.load(scene_path).metadata
    per_m = UNITS_PER_METRE.get(meta.get("units", "m"))
    if per_m is None or meta.get("landmarks") is None:
        raise ToolkitError(f"{scene_path}: expected landmarks in metres, m/cm/mm, in its metadata (re-run stage "
                           "geometry)")
    landmarks = np.asarray(meta["landmarks"], np.float64) / per_m
    if landmarks.shape != (68, 3) or not np.isfinite(landmarks).all():
        raise ToolkitError(f"{scene_path}: metadata landmarks: expected 68 finite 3D points")
    eyes = check_eyes_metadata(meta.get("eyes"), f"{scene_path} metadata eyes")
    if set(eyes) != {"left", "right"}:
        raise ToolkitError(f"{scene_path}: metadata eyes: expected both eyeballs (left and right)")
    centers = np.array([eyes["left"][0], eyes["right"][0]], np.float64) / per_m
    radii = np.array([eyes["left"][1], eyes["right"][1]], np.float64) / per_m
    verts, faces = load_mesh(run.context.path("geometry", "mesh"))
    model = FaceModel(landmarks, centers, radii, verts.numpy().astype(np.float32), faces.numpy().astype(np.int32),
                      f"the geometry of run {run_dir}")
    distance, crop = _run_normalization(run.subject_files())
    return Target(model, distance, crop, int(size or run.config.data.res), sum(run.code_widths()))
