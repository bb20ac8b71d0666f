"""Triangulating a frame's 3D landmarks from the 2D landmarks of its cameras: how GazeNeRF's files, which store no
3D keys but a camera per row that maps that row's head frame, get theirs (``train.data.layout_conversion``)."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from toolkit.errors import ToolkitError


def _where(where: str) -> str:
    return f"{where}: " if where else ""


def frame_rows(frame_index: np.ndarray, cam_index: np.ndarray | None = None, where: str = "") -> list[np.ndarray]:
    """The rows of each frame, to triangulate across: a run of consecutive rows with one ``frame_index`` in which
    no camera repeats. GazeNeRF writes a frame's cameras in turn (dataset_pre_processing.py L383-445) and the
    index as uint8 (L260-265): frames 256 apart share an index value but never a run. A frame seen by fewer than
    two cameras is one ToolkitError naming ``where``, the frame and the key."""
    runs = _frame_runs(frame_index, cam_index)
    for rows in runs:
        if len(rows) < 2:
            raise ToolkitError(f"{_frame_what(where, frame_index, rows)} is seen by {len(rows)} camera; triangulating "
                               "its 3D landmarks from 'facial_landmarks' needs at least 2")
    return runs


def _frame_what(where: str, frame_index: np.ndarray, rows: np.ndarray) -> str:
    return (f"{_where(where)}key 'facial_landmarks_3d': frame_index {int(np.reshape(frame_index, -1)[rows[0]])} "
            f"(rows {rows[0]}-{rows[-1]})")


def _frame_runs(frame_index: np.ndarray, cam_index: np.ndarray | None) -> list[np.ndarray]:
    frame_index = np.asarray(frame_index).reshape(-1)
    cams = None if cam_index is None else np.asarray(cam_index).reshape(-1)
    runs, start, seen = [], 0, set()
    for i in range(len(frame_index)):
        if i > start and (frame_index[i] != frame_index[start] or (cams is not None and cams[i] in seen)):
            runs.append(np.arange(start, i))
            start, seen = i, set()
        if cams is not None:
            seen.add(cams[i])
    if len(frame_index):
        runs.append(np.arange(start, len(frame_index)))
    return runs


MIN_RAY_ANGLE = 1e-3
"""Radians: a landmark whose rays from a frame's cameras all lie closer than this to parallel has no depth to
triangulate (the cameras share a centre, or look at it along one line)."""
GAUSS_NEWTON_STEPS = 3


def _triangulate(uv: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, str]:
    """Points [L, 3] seen at pixels ``uv`` [C, L, 2] by C cameras x = K (R X + t) (float64): the linear
    (DLT) solution on normalized image coordinates, then Gauss-Newton steps on the pixel reprojection error.
    Returns (points, "") or (anything, why the triangulation is degenerate)."""
    xn = np.einsum("cij,clj->cli", np.linalg.inv(K), np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], -1))
    P = np.concatenate([R, t[:, :, None]], -1)  # [C, 3, 4]
    A = np.concatenate([xn[..., :1] * P[:, None, 2] - P[:, None, 0],
                        xn[..., 1:2] * P[:, None, 2] - P[:, None, 1]], 0)  # [2C, L, 4]
    A = A.transpose(1, 0, 2)
    A = A / np.linalg.norm(A, axis=-1, keepdims=True).clip(1e-300)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1]
    if not np.isfinite(Xh).all() or (np.abs(Xh[:, 3]) < 1e-12 * np.abs(Xh[:, :3]).max(1)).any():
        return Xh[:, :3], "a landmark at infinity (parallel rays)"
    X = Xh[:, :3] / Xh[:, 3:]
    centres = -np.einsum("cji,cj->ci", R, t)  # [C, 3]
    rays = X[None] - centres[:, None]  # [C, L, 3]
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True).clip(1e-300)
    cos = np.einsum("ali,bli->lab", rays, rays).clip(-1, 1)
    if (np.arccos(cos.min((1, 2))) < MIN_RAY_ANGLE).any():
        return X, f"rays closer than {MIN_RAY_ANGLE} rad to parallel (cameras without a baseline)"
    for _ in range(GAUSS_NEWTON_STEPS):
        p = np.einsum("cij,lj->cli", R, X) + t[:, None]  # camera coordinates [C, L, 3]
        q = np.einsum("cij,clj->cli", K, p)
        r = q[..., :2] / q[..., 2:] - uv  # [C, L, 2] pixels
        # d(q_xy / q_z)/dX = (K[:2] - (q_xy / q_z) K[2]) R / q_z
        J = np.einsum("clab,cbj->claj", K[:, None, :2] - (q[..., :2] / q[..., 2:])[..., None] * K[:, None, None, 2],
                      R) / q[..., 2:, None]  # [C, L, 2, 3]
        JtJ = np.einsum("claj,clak->ljk", J, J)
        Jtr = np.einsum("claj,cla->lj", J, r)
        X = X - np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
    depth = np.einsum("cij,lj->cli", R, X)[..., 2] + t[:, 2:3]
    if not np.isfinite(X).all() or (depth <= 0).any():
        return X, "a landmark behind a camera"
    return X, ""


def triangulate_frames(landmarks: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, frame_index: np.ndarray,
                       cam_index: np.ndarray | None = None, where: str = "") -> np.ndarray:
    """[N, L, 3] the 3D landmarks of every row, triangulated per frame from the 2D ``landmarks`` [N, L, 2] (pixels,
    native u: 0 is the left edge) of the frame's rows (:func:`_frame_runs`), each seen by x = K (R X + t) (``K``
    [N, 3, 3], ``R`` [N, 3, 3], ``t`` [N, 3]), in the frame those cameras map from; every row of a frame gets
    its frame's points. Linear triangulation, refined by Gauss-Newton on the pixel error, in float64. A frame seen
    by fewer than two cameras, or whose triangulation is degenerate, is one ToolkitError naming ``where``, the
    frame and the key."""
    lm, K, R, t = (np.asarray(a, np.float64) for a in (landmarks, K, R, t))
    out = np.empty(lm.shape[:2] + (3,))
    for rows in frame_rows(frame_index, cam_index, where):
        X, degenerate = _triangulate(lm[rows], K[rows], R[rows], t[rows])
        if degenerate:
            raise ToolkitError(f"{_frame_what(where, frame_index, rows)}: the triangulation from its {len(rows)} "
                               f"cameras' 'facial_landmarks' is degenerate: {degenerate}")
        out[rows] = X
    return out


def single_camera(rows: Mapping[str, np.ndarray]) -> bool:
    """Whether every frame of a file is seen by one camera: GazeNeRF's MPIIFaceGaze and ColumbiaGaze files (one
    webcam or one photo per frame: dataset_pre_processing.py L559-612, L844), whose 3D landmarks no triangulation
    can give (a file mixing one-camera and multi-camera frames is refused frame by frame instead)."""
    if "frame_index" not in rows:
        return False
    return all(len(r) == 1 for r in _frame_runs(rows["frame_index"], rows.get("cam_index")))
