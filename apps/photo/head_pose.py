"""Head pose of a face in a photo: PnP of the 2D landmarks against the head model, then the head scale.

x_cam = s · R · x_head + t (the photo's camera frame, OpenCV axes; docs/data.md's pose with world = camera).
A single view does not separate the head's size from its distance (s · R x + t and R x + t / s project alike), so
the scale comes from a metric cue: the iris, whose visible diameter is nearly the same in every adult
(:data:`IRIS_DIAMETER`). Its depth f · D / d_px against the depth PnP gives the unit model's eyes is s; without
iris points, or with ``scale`` given, s is that value (1: the model's size).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.errors import ToolkitError

PNP_LANDMARKS = np.arange(68)
"""iBUG points PnP fits: all 68. The jaw is approximate (apps.photo.landmarks68) and the model's a half ellipse,
yet it is what pins pitch down: on 10 synthetic renders (mediapipe's landmarks, the average head model) the head
rotation was off by 4.2° on average with all 68 points, 11.3° without the jaw (brows, nose, eyes, mouth), 14.4°
with the nose, eyes and mouth alone (benchmarks/prepare.py measures the first)."""

IRIS_DIAMETER = 0.0117
"""m: the visible iris diameter of adults, 11.7 ± 0.5 mm (the metric cue of mediapipe's iris depth estimate:
Ablavatski et al. 2020, "Real-time Pupil Tracking from Monocular Video for Digital Puppetry")."""

SCALE_RANGE = (0.8, 1.25)
"""Head scales the iris may set (adult heads vary by about ±10%); an iris reading outside is clamped."""

MAX_REPROJECTION = 0.12
"""Largest accepted RMS reprojection error of the fitted landmarks, as a fraction of the face width: above it
the model does not fit the face (a profile, a wrong landmark fit)."""


@dataclass
class HeadPose:
    """``R`` [3, 3] and ``t`` [3] (float64) with x_cam = s · R · x_head + t; ``scale`` s; ``rms_px`` the RMS
    reprojection error of :data:`PNP_LANDMARKS` in pixels; ``scale_source`` "iris", "given" or "model"."""

    R: np.ndarray
    t: np.ndarray
    scale: float
    rms_px: float
    scale_source: str

    def to_camera(self, x_head: np.ndarray) -> np.ndarray:
        """[..., 3] head-frame points -> camera frame."""
        return self.scale * np.asarray(x_head, np.float64) @ self.R.T + self.t


def _project(x_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (x_cam[..., :2] / x_cam[..., 2:3]) * np.diag(K)[:2] + K[:2, 2]


def solve_pnp(landmarks2d: np.ndarray, K: np.ndarray, model_landmarks: np.ndarray,
              points: np.ndarray = PNP_LANDMARKS) -> tuple[np.ndarray, np.ndarray, float]:
    """(R [3, 3], t [3], RMS px) of the unit-scale model: ``cv2.solvePnP`` (SQPnP, a global solver) then
    Levenberg-Marquardt refinement (``cv2.solvePnPRefineLM``). ``landmarks2d`` [68, 2] in the u = 0 left-edge
    convention with ``K`` [3, 3] in the same (principal point W/2 for a centred one): no half-pixel shift."""
    import cv2

    obj = np.ascontiguousarray(model_landmarks[points], np.float64)
    img = np.ascontiguousarray(np.asarray(landmarks2d, np.float64)[points])
    if not (np.isfinite(img).all() and np.isfinite(K).all()):
        raise ToolkitError("head pose: the landmarks or the camera contain NaN or inf")
    K = np.asarray(K, np.float64)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        # SQPnP refuses image points whose normalized spread is tiny: a long focal length (a telephoto, a large
        # --focal) against a small face, nearly an orthographic view. EPnP's control points still hold there.
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        raise ToolkitError("head pose: PnP found no pose for these landmarks")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.reshape(3)
    if t[2] <= 0:
        raise ToolkitError("head pose: PnP put the head behind the camera")
    err = _project(obj @ R.T + t, K) - img
    return R, t, float(np.sqrt((err ** 2).sum(-1).mean()))


def head_scale(pose_R: np.ndarray, pose_t: np.ndarray, K: np.ndarray, eye_centers: np.ndarray,
               iris_diameters_px: np.ndarray | None) -> float | None:
    """The head scale s from the iris: each eye's depth f · :data:`IRIS_DIAMETER` / d_px over the depth of the
    unit model's eyeball centre (R e + t)_z, averaged over the eyes; None without usable iris sizes."""
    if iris_diameters_px is None:
        return None
    d = np.asarray(iris_diameters_px, np.float64)
    ok = np.isfinite(d) & (d > 1.0)
    if not ok.any():
        return None
    f = 0.5 * (K[0, 0] + K[1, 1])
    z_unit = (eye_centers @ pose_R.T + pose_t)[:, 2]
    return float(np.mean((f * IRIS_DIAMETER / d[ok]) / z_unit[ok]))


def head_pose(landmarks2d: np.ndarray, K: np.ndarray, model, *, iris_diameters_px: np.ndarray | None = None,
              scale: float | None = None) -> HeadPose:
    """The head pose of one face: PnP of ``landmarks2d`` [68, 2] against ``model`` (``apps.photo.face_model.
    FaceModel``) at unit scale, then the scale s (``scale`` when given, else from the iris, clamped to
    :data:`SCALE_RANGE`, else 1), which moves the head along the rays (t → s t): the same projection."""
    R, t, rms = solve_pnp(landmarks2d, K, model.landmarks)
    width = float(np.ptp(np.asarray(landmarks2d)[:, 0]))
    if rms > MAX_REPROJECTION * max(width, 1.0):
        raise ToolkitError(f"the head model does not fit the landmarks (RMS {rms:.1f} px on a face {width:.0f} px "
                           "wide: a profile or a wrong landmark fit?)")
    if scale is not None:
        s, source = float(scale), "given"
    else:
        s = head_scale(R, t, K, model.eye_centers, iris_diameters_px)
        source = "model" if s is None else "iris"
        s = 1.0 if s is None else float(np.clip(s, *SCALE_RANGE))
    return HeadPose(R, s * t, s, rms, source)


def face_direction_deg(R: np.ndarray, t: np.ndarray, face_center: np.ndarray, scale: float = 1.0) -> float:
    """Degrees between the face direction (head −z) and the direction from the face centre to the camera: 0 for a
    face looking into the lens, 90 for a profile."""
    fwd = -R[:, 2]
    to_cam = -(scale * R @ face_center + t)
    c = fwd @ to_cam / max(np.linalg.norm(to_cam), 1e-12)
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
