"""The per-subject HDF5 format (GazeGaussian-preprocessed ETH-XGaze keys): schema, writing, validation.

One file per subject; N rows (images). Per-row datasets are listed in :data:`REQUIRED` (the keys of the
preprocessed ETH-XGaze files) and :data:`OPTIONAL` (written by the synthetic generator, read when
present). Subject-level datasets (:data:`SUBJECT_KEYS`) and attributes describe the generator's subject.
docs/data.md documents every key and the frames.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.errors import ToolkitError

# key -> (trailing shape after N; None = any size, "H"/"W"/"V" = shared sizes), dtype kinds allowed
REQUIRED: dict[str, tuple[tuple, str]] = {
    "face_patch": (("H", "W", 3), "u"),
    "head_mask": (("H", "W"), "u"),
    "left_eye_mask": (("H", "W"), "u"),
    "right_eye_mask": (("H", "W"), "u"),
    "facial_landmarks": ((68, 2), "f"),
    "facial_landmarks_3d": ((68, 3), "f"),
    "latent_codes": ((144,), "f"),
    "pose": ((6,), "f"),
    "scale": ((1,), "f"),
    "w2c_Rmat": ((3, 3), "f"),
    "w2c_Tvec": ((3,), "f"),
    "inmat": ((3, 3), "f"),
    "pitchyaw_head": ((2,), "f"),
    "face_head_pose": ((2,), "f"),
    "cam_index": ((), "iu"),
    "frame_index": ((), "iu"),
    "vertice": (("V", 3), "f"),
}
OPTIONAL: dict[str, tuple[tuple, str]] = {
    "pitchyaw_cam": ((2,), "f"),
    "expression_params": ((4,), "f"),
    "light_dir": ((3,), "f"),
}
SUBJECT_KEYS = ("neutral_vertice", "mesh_faces", "eyeball_centers", "eyeball_radii", "identity_params")
IMAGE_KEYS = ("face_patch", "head_mask", "left_eye_mask", "right_eye_mask")
FORMAT_VERSION = 1


def write_subject_h5(path: str | os.PathLike, rows: dict[str, np.ndarray], *, subject: dict[str, np.ndarray] | None = None,
                     attrs: dict[str, Any] | None = None, compression: str | None = "lzf") -> Path:
    """Write one subject file atomically (temp file in the same folder, then rename).

    Args:
        rows: every key of :data:`REQUIRED` (and any of :data:`OPTIONAL`) with N rows.
        subject: subject-level arrays (``neutral_vertice`` [V, 3] head frame, ``mesh_faces`` [F, 3],
            ``eyeball_centers`` [2, 3] head frame, ``eyeball_radii`` [2], ``identity_params`` [22]).
        attrs: JSON-able file attributes (strings, numbers).
    """
    from toolkit.io import atomic_h5

    missing = [k for k in REQUIRED if k not in rows]
    if missing:
        raise ToolkitError(f"write_subject_h5: missing keys {missing}")
    n = len(rows["face_patch"])
    for k, v in rows.items():
        if len(v) != n:
            raise ToolkitError(f"write_subject_h5: {k} has {len(v)} rows, face_patch has {n}")
    path = Path(path)
    with atomic_h5(path) as f:
        for k, v in rows.items():
            v = np.asarray(v)
            big = v.ndim >= 3 and v[0].size >= 1024
            f.create_dataset(k, data=v, chunks=(1,) + v.shape[1:] if big else None,
                             compression=compression if big else None)
        for k, v in (subject or {}).items():
            f.create_dataset(k, data=np.asarray(v))
        f.attrs["format_version"] = FORMAT_VERSION
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
    return path


@contextlib.contextmanager
def open_h5(path: str | os.PathLike):
    """Open an HDF5 file read-only, turning unreadable / truncated files into a ToolkitError."""
    import h5py

    from toolkit.io import check_readable_file

    path = check_readable_file(path, "HDF5 file")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ToolkitError(f"{path}: not a readable HDF5 file (truncated or corrupt?): {e}") from e
    try:
        yield f
    finally:
        f.close()


def _check_dataset(path, f, key: str, spec: tuple, kinds: str, sizes: dict, n: int | None) -> int:
    import h5py

    ds = f[key]
    if not isinstance(ds, h5py.Dataset):
        raise ToolkitError(f"{path}: key '{key}' is a {type(ds).__name__}, expected a dataset of rows")
    shape = tuple(ds.shape)
    if key == "scale" and len(shape) == 1:  # (N,) is accepted for scale
        shape = shape + (1,)
    if spec == () and len(shape) == 2 and shape[1] == 1:  # indices stored (N, 1), as GazeNeRF's files do
        shape = shape[:1]
    if len(shape) != 1 + len(spec):
        raise ToolkitError(f"{path}: key '{key}' has shape {list(ds.shape)}, expected [N, {', '.join(map(str, spec))}]"
                           if spec else f"{path}: key '{key}' has shape {list(ds.shape)}, expected [N]")
    for s, d in zip(spec, shape[1:], strict=True):
        if isinstance(s, str):
            if sizes.setdefault(s, d) != d:
                raise ToolkitError(f"{path}: key '{key}' has {s} = {d}, other keys have {sizes[s]} "
                                   f"(shape {list(ds.shape)})")
        elif s != d:
            raise ToolkitError(f"{path}: key '{key}' has shape {list(ds.shape)}, expected trailing {list(spec)}")
    if ds.dtype.kind not in kinds or (kinds == "u" and ds.dtype != np.uint8):  # images are 8-bit, read / 255
        raise ToolkitError(f"{path}: key '{key}' has dtype {ds.dtype}, expected "
                           + {"u": "uint8", "f": "float", "iu": "integer"}[kinds])
    if n is not None and shape[0] != n:
        raise ToolkitError(f"{path}: key '{key}' has {shape[0]} rows, face_patch has {n}")
    return shape[0]


def _bad(path, key, what):
    raise ToolkitError(f"{path}: key '{key}' {what}")


def validate_subject_file(path: str | os.PathLike) -> dict[str, Any]:
    """Check a subject file's schema and label ranges up front; return its summary.

    Raises ToolkitError naming the file and key for: unreadable/truncated files, missing keys, wrong
    shapes or dtypes, row counts that disagree, empty subjects, and out-of-range labels (non-finite
    values, |pitch| > 90°, |yaw| > 180°, non-rotation ``w2c_Rmat``, non-positive focal lengths or scale,
    negative indices, landmarks far outside the image). Image data are checked by shape and dtype only.
    Returns ``{"path", "n", "height", "width", "n_vertices", "optional": [...], "attrs": {...}}``.
    """
    path = Path(path)
    with open_h5(path) as f:
        missing = [k for k in REQUIRED if k not in f]
        if missing:
            raise ToolkitError(f"{path}: missing key '{missing[0]}'" + (f" (and {missing[1:]})" if missing[1:] else ""))
        sizes: dict[str, int] = {}
        n = _check_dataset(path, f, "face_patch", REQUIRED["face_patch"][0], "u", sizes, None)
        if n == 0:
            raise ToolkitError(f"{path}: empty subject (0 rows in 'face_patch')")
        for k, (spec, kinds) in REQUIRED.items():
            _check_dataset(path, f, k, spec, kinds, sizes, n)
        optional = [k for k in OPTIONAL if k in f]
        for k in optional:
            _check_dataset(path, f, k, OPTIONAL[k][0], OPTIONAL[k][1], sizes, n)
        H, W = sizes["H"], sizes["W"]
        try:
            lab = {k: f[k][()] for k in REQUIRED if k not in IMAGE_KEYS and k != "vertice"}
            lab.update({k: f[k][()] for k in optional})
        except (OSError, KeyError) as e:
            raise ToolkitError(f"{path}: cannot read labels (truncated or corrupt?): {e}") from e
        for k, v in lab.items():
            if v.dtype.kind == "f" and not np.isfinite(v).all():
                _bad(path, k, "contains NaN or inf")
        for k in ("pitchyaw_head", "face_head_pose", "pitchyaw_cam"):
            if k in lab and ((np.abs(lab[k][:, 0]) > np.pi / 2 + 1e-4).any() or (np.abs(lab[k][:, 1]) > np.pi + 1e-4).any()):
                _bad(path, k, "is out of range: expected (pitch, yaw) radians with |pitch| <= pi/2, |yaw| <= pi")
        R = lab["w2c_Rmat"].astype(np.float64)
        if (np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() > 1e-3) or (np.linalg.det(R) < 0).any():
            _bad(path, "w2c_Rmat", "is not a rotation matrix in every row")
        K = lab["inmat"]
        if (K[:, 0, 0] <= 0).any() or (K[:, 1, 1] <= 0).any():
            _bad(path, "inmat", "has non-positive focal lengths")
        if (lab["scale"] <= 0).any():
            _bad(path, "scale", "has non-positive values")
        for k in ("cam_index", "frame_index"):
            lab[k] = lab[k].reshape(-1)
            if (lab[k] < 0).any():
                _bad(path, k, "has negative values")
        lm = lab["facial_landmarks"]
        if (lm < -W).any() or (lm[..., 0] > 2 * W).any() or (lm[..., 1] > 2 * H).any():
            _bad(path, "facial_landmarks", f"lies far outside the {W}x{H} image (pixels expected)")
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        return {"path": str(path), "n": n, "height": H, "width": W, "n_vertices": sizes.get("V"),
                "optional": optional, "subject_keys": [k for k in SUBJECT_KEYS if k in f], "attrs": attrs}
