"""A layout's arrays in the native conventions and back (docs/data.md): gaze sign, 3D frame, index shapes, code
slices, and what a layout's frames settle (GazeNeRF's pose, scale and triangulated 3D landmarks). The layouts
themselves are data in :mod:`train.data.layouts`."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from toolkit.errors import ToolkitError
from train.data.format import OPTIONAL, REQUIRED, SUBJECT_KEYS
from train.data.layouts import (
    CODE_KEYS,
    DITGAZE,
    GAZEGAUSSIAN,
    GAZENERF,
    INDEX_KEYS,
    LANDMARK_3D_KEYS,
    MODEL_CODES,
    Layout,
    get_layout,
    split_codes,
)
from train.data.triangulation import single_camera, triangulate_frames

_NATIVE_KEYS = frozenset(REQUIRED) | frozenset(OPTIONAL) | frozenset(SUBJECT_KEYS)


def _need(rows: Mapping[str, np.ndarray], key: str, why: str) -> np.ndarray:
    if key not in rows:
        raise ToolkitError(f"missing key '{key}', needed to {why}")
    return np.asarray(rows[key])


def _flip_pitch(py: np.ndarray) -> np.ndarray:
    py = np.array(py, np.float64)
    py[..., 0] = -py[..., 0]
    return py


def _world_from_stored(p: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """GazeGaussian's read of a row's 3D points: (p - w2c_Tvec) @ w2c_Rmat^T (dataloader/eth_xgaze.py L440)."""
    return np.einsum("nkj,nij->nki", p.astype(np.float64) - t[:, None, :], R.astype(np.float64))


def _stored_from_world(q: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The inverse of :func:`_world_from_stored`: p = q @ w2c_Rmat + w2c_Tvec (R is orthonormal)."""
    return np.einsum("nki,nij->nkj", q.astype(np.float64), R.astype(np.float64)) + t[:, None, :].astype(np.float64)


def _codes_to_native(layout: Layout, codes: np.ndarray, out: dict) -> None:
    """``latent_codes`` = the layout's identity then expression slice (the model's code, at the layout's
    widths); its other slices under :data:`CODE_KEYS` (GazeNeRF's texture and illumination)."""
    parts = split_codes(layout, codes)
    out["latent_codes"] = np.concatenate([parts[name] for name in MODEL_CODES], 1)
    out.update({CODE_KEYS[name]: a for name, a in parts.items() if name not in MODEL_CODES})


def _head_frame_world(rows: Mapping[str, np.ndarray], out: dict, where: str) -> None:
    """A layout whose cameras map each row's head frame (``frame_3d`` "triangulated"): the world is that head
    frame, so ``pose`` 0 and ``scale`` 1; ``facial_landmarks_3d`` triangulated per frame, except in a
    :func:`single_camera` file, which has none (the stages that need them name the key). Made only from rows with
    the cameras (a caller converting the gaze alone gets no pose)."""
    if "w2c_Rmat" not in rows:
        return
    n = len(rows["w2c_Rmat"])
    out["pose"] = np.zeros((n, 6), np.float32)
    out["scale"] = np.ones((n, 1), np.float32)
    if "facial_landmarks" in rows and not single_camera(rows):
        why = "triangulate the 3D landmarks"
        out["facial_landmarks_3d"] = triangulate_frames(
            rows["facial_landmarks"], _need(rows, "inmat", why), rows["w2c_Rmat"], _need(rows, "w2c_Tvec", why),
            _need(rows, "frame_index", why), rows.get("cam_index"), where)


def _head_gaze_from_camera(gaze_cam: np.ndarray, head_pose: np.ndarray) -> np.ndarray:
    """The head-frame gaze of an ETH-XGaze row. The normalized camera has no roll relative to the head: its
    down axis is forward x head-x (normalization_example.py L56-62), so the head x-axis seen from it has no y
    component, and with the head z-axis from face_head_pose (L327-330) that fixes the head rotation
    (``toolkit.rotations.camera_to_head_gaze``, in float64)."""
    import torch

    from toolkit.rotations import camera_to_head_gaze

    f64 = lambda a: torch.from_numpy(np.asarray(a, np.float64))  # noqa: E731
    return camera_to_head_gaze(f64(gaze_cam), f64(head_pose)).numpy()


def _native_dtypes(out: dict) -> dict:
    for k, v in out.items():
        v = np.asarray(v)
        if k in INDEX_KEYS or k == "mesh_faces":
            out[k] = v.astype(np.int32)
        elif v.dtype.kind == "f":
            out[k] = v.astype(np.float32)
    return out


def to_native(layout: str | Layout, rows: Mapping[str, np.ndarray], where: str = "") -> dict[str, np.ndarray]:
    """The arrays a ``layout`` file stores (whole keys: all of the file's rows), in native conventions and names:
    gaze sign, 3D landmarks and vertices in world coordinates, 1-D indices, (N, 1) scale, float32 labels, codes
    as the model's identity + expression (``latent_codes``) and the other slices by name (:data:`CODE_KEYS`).
    Keys with no native meaning (GazeNeRF's c2w_*, inv_inmat, pitchyaw, pitchyaw_3d; ETH-XGaze's face_mat_norm)
    are left out. What the layout's frames settle is made (GazeNeRF: pose 0, scale 1, 3D landmarks triangulated
    per frame, so pass every row of a frame; errors name ``where``); nothing else is invented (no ``vertice``)."""
    layout = get_layout(layout)
    out = {layout.renames.get(k, k): np.asarray(v) for k, v in rows.items()}
    out = {k: v for k, v in out.items() if k in _NATIVE_KEYS}
    for k in INDEX_KEYS:
        if k in out:
            out[k] = out[k].reshape(len(out[k]))
    if "scale" in out:
        out["scale"] = out["scale"].reshape(len(out["scale"]), 1)
    gaze = layout.renames.get(layout.gaze_key, layout.gaze_key)
    if layout.pitch_sign < 0 and gaze in out:
        out[gaze] = _flip_pitch(out[gaze])
    if layout.frame_3d == "w2c-transposed" and any(k in out for k in LANDMARK_3D_KEYS):
        R = _need(rows, "w2c_Rmat", "map the 3D keys to world coordinates")
        t = _need(rows, "w2c_Tvec", "map the 3D keys to world coordinates")
        for k in LANDMARK_3D_KEYS:
            if k in out:
                out[k] = _world_from_stored(out[k], R, t)
    if layout.frame_3d == "triangulated":
        _head_frame_world(rows, out, where)
    if layout.codes and "latent_codes" in out:
        _codes_to_native(layout, out["latent_codes"], out)
    if layout.gaze_frame == "normalized camera" and "pitchyaw_cam" in out:
        head_pose = _need(rows, "face_head_pose", "derive the head-frame gaze")
        out["pitchyaw_head"] = _head_gaze_from_camera(out["pitchyaw_cam"], head_pose)
    return _native_dtypes(out)


def from_native(layout: str | Layout, rows: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Native arrays in a ``layout``'s conventions, for export; :func:`to_native` gives them back. For
    gazegaussian the file gets GazeNeRF's derived camera keys too (c2w_*, inv_inmat, as
    surface_fitting/nl3dmm/fitting_nl3dmm.py L320-328 makes them), which mark it as that layout's."""
    layout = get_layout(layout)
    if layout is DITGAZE:
        return to_native(DITGAZE, rows)
    if layout is not GAZEGAUSSIAN:
        raise ToolkitError(f"data.layout={layout.name}: export is not supported (its "
                           f"{'NL3DMM codes' if layout is GAZENERF else 'normalization matrices'} cannot be made "
                           "from native files); export to gazegaussian or ditgaze")
    out = {k: np.asarray(v) for k, v in rows.items() if k in layout.keys}
    for k in INDEX_KEYS:
        if k in out:
            out[k] = out[k].reshape(-1, 1)
    if "scale" in out:
        out["scale"] = out["scale"].reshape(-1, 1)
    if "pitchyaw_head" in out:
        out["pitchyaw_head"] = _flip_pitch(out["pitchyaw_head"])
    R = _need(rows, "w2c_Rmat", "export the cameras").astype(np.float64)
    t = _need(rows, "w2c_Tvec", "export the cameras").astype(np.float64)
    for k in LANDMARK_3D_KEYS:
        if k in out:
            out[k] = _stored_from_world(out[k], R, t)
    out["c2w_Rmat"] = R.transpose(0, 2, 1)
    out["c2w_Tvec"] = -np.einsum("nji,nj->ni", R, t)
    if "inmat" in out:
        out["inv_inmat"] = np.linalg.inv(out["inmat"].astype(np.float64))
    return _native_dtypes(out)


def mesh_to_native(layout: str | Layout, vertice: np.ndarray, w2c_R: np.ndarray, w2c_t: np.ndarray) -> np.ndarray:
    """One row's ``vertice`` [V, 3] of a ``layout`` file in world coordinates (float32), with that row's camera:
    the mesh is read a row at a time, the other keys whole (:func:`to_native`)."""
    v = np.asarray(vertice)
    if get_layout(layout).frame_3d == "w2c-transposed":
        v = _world_from_stored(v[None], np.asarray(w2c_R)[None], np.asarray(w2c_t)[None])[0]
    return v.astype(np.float32)


def native_row(layout: str | Layout, row: Mapping[str, np.ndarray], index: int) -> dict[str, np.ndarray]:
    """One row (arrays without the row axis) of a ``layout`` file in native conventions (:func:`to_native`);
    ``frame_index``, when the layout does not store it, is the row ``index`` (each row its own frame). A layout
    whose rows need their frame's other rows (GazeNeRF: 3D landmarks triangulated across a frame's cameras) is
    refused: convert the file's arrays whole with :func:`to_native`."""
    layout = get_layout(layout)
    if layout is DITGAZE:
        return dict(row)
    if layout.frame_3d == "triangulated":
        raise ToolkitError(f"data.layout={layout.name}: a row's 3D landmarks are triangulated from its frame's "
                           "other rows; convert the file's arrays whole (train.data.layout_conversion.to_native)")
    out = {k: v[0] for k, v in to_native(layout, {k: np.asarray(v)[None] for k, v in row.items()}).items()}
    out.setdefault("frame_index", np.int32(index))
    return out
