"""The per-subject HDF5 format (GazeGaussian-preprocessed ETH-XGaze keys): schema, writing, validation.

One file per subject; N rows (images). Per-row datasets are listed in :data:`REQUIRED` (the keys of the
preprocessed ETH-XGaze files) and :data:`OPTIONAL` (written by the synthetic generator, read when
present). Subject-level datasets (:data:`SUBJECT_KEYS`) and attributes describe the generator's subject.
docs/data.md documents every key and the frames.

Every read goes through ``toolkit.h5``'s bounded reader (links, external and virtual storage, forged sizes,
allocation and chunk bounds), as do the other readers of these files (``GazeDataset``, ``train.data inspect``,
``geometry fit``).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.errors import ToolkitError, one_line
from toolkit.h5 import (
    MAX_ATTR_BYTES,
    MAX_ROW_CHUNKS,
    NUMERIC_KINDS,
    READ_ERRORS,
    check_chunk_reads,
    chunk_count,
    dtype_name,
    h5_dataset,
    has_key,
    open_h5,
    read_array,
    read_selection,
    row_nbytes,
)

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



# ----------------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------------

SIZE_RANGES = {"H": (8, 16384, "an image height in pixels"), "W": (8, 16384, "an image width in pixels"),
               "V": (1, 2**31 - 1, "a vertex count")}
"""The shared sizes of :data:`REQUIRED`: what a row's memory is checked against comes after these."""

INDEX_MAX = 2**31 - 1

KIND_NAMES = {"u": "uint8", "f": "float", "iu": "integer"}


def _check_dataset(path, f, key: str, spec: tuple, kinds: str, sizes: dict, n: int | None):
    """The per-row dataset ``key`` checked against its spec (dtype, rank, shared sizes, row count, one row's
    memory); returns it."""
    from toolkit.limits import check_allocation

    ds = h5_dataset(path, f, key, kinds, KIND_NAMES[kinds])
    if kinds == "u" and ds.dtype != np.uint8:  # images are 8-bit, read / 255
        raise ToolkitError(f"{path}: key '{key}' has dtype {dtype_name(ds.dtype)}, expected {KIND_NAMES[kinds]}")
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
            low, high, what = SIZE_RANGES[s]
            if s not in sizes and not low <= d <= high:
                raise ToolkitError(f"{path}: key '{key}' has {s} = {d}, expected {what} in [{low}, {high}]")
            if sizes.setdefault(s, d) != d:
                raise ToolkitError(f"{path}: key '{key}' has {s} = {d}, other keys have {sizes[s]} "
                                   f"(shape {list(ds.shape)})")
        elif s != d:
            raise ToolkitError(f"{path}: key '{key}' has shape {list(ds.shape)}, expected trailing {list(spec)}")
    if n is not None and shape[0] != n:
        raise ToolkitError(f"{path}: key '{key}' has {shape[0]} rows, face_patch has {n}")
    check_allocation(row_nbytes(ds), f"{path}: key '{key}': reading one row ({list(ds.shape)} {ds.dtype})")
    if chunk_count(ds, whole=False) > MAX_ROW_CHUNKS:
        raise ToolkitError(f"{path}: key '{key}': one row spans {chunk_count(ds, whole=False)} HDF5 chunks of "
                           f"{list(ds.chunks)}, expected at most {MAX_ROW_CHUNKS} (rewrite the file with larger chunks)")
    return ds


def _bad(path, key, what):
    raise ToolkitError(f"{path}: key '{key}' {what}")


def _read_labels(path, datasets: dict, n: int) -> dict[str, np.ndarray]:
    """Every label key read whole (images and meshes are read a row at a time), after bounding the memory: a
    small file may declare millions of rows of compressed constant data."""
    from toolkit.limits import check_allocation

    per_row = sum(math.prod(ds.shape[1:]) * ds.dtype.itemsize for ds in datasets.values())
    # + float64 temporaries of the rotation check, ~10 x 9 doubles a row
    check_allocation(n * (per_row + 720), f"{path}: reading the labels of {n} rows",
                     hint="the file declares more rows than this machine can check")
    check_chunk_reads(path, f"reading the labels of {n} rows", sum(chunk_count(ds) for ds in datasets.values()))
    return {k: read_selection(path, k, ds) for k, ds in datasets.items()}


def _check_labels(path, lab: dict[str, np.ndarray], H: int, W: int) -> None:
    """Label ranges: non-finite values in any float key would poison training silently; the rest name rows
    that no camera, head or gaze can produce."""
    for k, v in lab.items():
        if v.dtype.kind in "fc" and not np.isfinite(v).all():
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
    if "scale" in lab and (lab["scale"] <= 0).any():  # a peer layout may store none (GazeNeRF: scale 1)
        _bad(path, "scale", "has non-positive values")
    for k in ("cam_index", "frame_index"):
        if k not in lab:  # a peer layout without it (validate_subject_file's optional_keys)
            continue
        lab[k] = lab[k].reshape(-1)
        if (lab[k] < 0).any():
            _bad(path, k, "has negative values")
        if (lab[k] > INDEX_MAX).any():  # samples carry them as int64 tensors; the schema stores int32
            _bad(path, k, f"has values above {INDEX_MAX} (int32 indices expected)")
    lm = lab["facial_landmarks"]
    if (lm < -W).any() or (lm[..., 0] > 2 * W).any() or (lm[..., 1] > 2 * H).any():
        _bad(path, "facial_landmarks", f"lies far outside the {W}x{H} image (pixels expected)")


SUBJECT_SPECS: dict[str, tuple[tuple, str]] = {
    "neutral_vertice": ((None, 3), "f"), "mesh_faces": ((None, 3), "iu"), "eyeball_centers": ((2, 3), "f"),
    "eyeball_radii": ((2,), "f"), "identity_params": ((None,), "f"),
}
"""Subject-level arrays (None: any size >= 1): shape and dtype kinds."""


def check_subject_arrays(path, f) -> dict[str, np.ndarray]:
    """The subject-level arrays of :data:`SUBJECT_KEYS` the file has, read (bounded) and checked: shapes,
    dtypes, finite values, positive eyeball radii, face indices within the neutral mesh."""
    out = {}
    for key, (spec, kinds) in SUBJECT_SPECS.items():
        if not has_key(path, f, key):
            continue
        a = read_array(path, f, key)
        if a.dtype.kind not in kinds:
            _bad(path, key, f"has dtype {dtype_name(a.dtype)}, expected {KIND_NAMES[kinds]}")
        if a.ndim != len(spec) or any(s is not None and s != d for s, d in zip(spec, a.shape, strict=True)) or not a.size:
            want = ", ".join("V" if key == "neutral_vertice" and s is None else "F" if s is None else str(s)
                             for s in spec)
            _bad(path, key, f"has shape {list(a.shape)}, expected [{want}] (non-empty)")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            _bad(path, key, "contains NaN or inf")
        out[key] = a
    if "eyeball_radii" in out and (out["eyeball_radii"] <= 0).any():
        _bad(path, "eyeball_radii", "has non-positive values")
    faces, verts = out.get("mesh_faces"), out.get("neutral_vertice")
    if faces is not None and verts is not None and ((faces < 0).any() or (faces >= len(verts)).any()):
        _bad(path, "mesh_faces", f"has vertex indices outside [0, {len(verts)}) (neutral_vertice has {len(verts)} rows)")
    return out


def _attr(path, f, name: str):
    """One file attribute as a Python value (text decoded, numbers as scalars or arrays), its type and size
    checked before it is read."""
    import h5py

    try:
        aid = h5py.h5a.open(f.id, name.encode())
        shape, dt = aid.shape, aid.dtype
    except READ_ERRORS as e:
        raise ToolkitError(f"{path}: attribute '{name}' cannot be read (corrupt?): {one_line(e, 300)}") from e
    text = h5py.check_string_dtype(dt) is not None
    if not text and (dt.kind not in NUMERIC_KINDS or dt.subdtype is not None):
        raise ToolkitError(f"{path}: attribute '{name}' has type {dtype_name(dt)}, expected text or numbers")
    if shape is None:
        raise ToolkitError(f"{path}: attribute '{name}' has no value (an empty dataspace), expected text or numbers")
    nbytes = math.prod(shape) * dt.itemsize
    if nbytes > MAX_ATTR_BYTES:
        raise ToolkitError(f"{path}: attribute '{name}' holds {nbytes} bytes, expected at most {MAX_ATTR_BYTES} "
                           "(attributes hold short text and numbers)")
    try:
        v = f.attrs[name]
    except READ_ERRORS as e:
        raise ToolkitError(f"{path}: attribute '{name}' cannot be read (corrupt?): {one_line(e, 300)}") from e
    if isinstance(v, np.ndarray) and v.ndim == 0:
        v = v[()]
    if isinstance(v, np.ndarray) and v.dtype.kind in "OS":  # an array of strings
        return [_text(path, name, x) for x in v.tolist()]
    if isinstance(v, (bytes, np.bytes_, str)):
        return _text(path, name, v)
    if isinstance(v, np.generic):
        return v.item()
    return v


def _text(path, name: str, v) -> str:
    # h5py decodes variable-length strings with surrogateescape: a non-UTF-8 byte comes back as a lone surrogate
    try:
        return bytes(v).decode("utf-8") if isinstance(v, (bytes, np.bytes_)) else str(v.encode("utf-8"), "utf-8")
    except UnicodeError:
        raise ToolkitError(f"{path}: attribute '{name}' is not UTF-8 text") from None


def _check_known_attrs(path, attrs: dict) -> None:
    """The attributes readers use: ``format_version`` (this module), ``subject_params`` and ``ambient``
    (``train.data.pairing`` renders targets from them)."""
    from train.data.subject_params import IDENTITY_NAMES

    v = attrs.get("format_version", FORMAT_VERSION)
    if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= FORMAT_VERSION:
        raise ToolkitError(f"{path}: attribute 'format_version' is {v!r}, expected an integer in [1, {FORMAT_VERSION}]"
                           " (a file of a newer writer?)")
    v = attrs.get("ambient", 0.5)
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 <= v <= 1:
        raise ToolkitError(f"{path}: attribute 'ambient' is {v!r}, expected a number in [0, 1]")
    if "subject_params" in attrs:
        v = attrs["subject_params"]
        try:
            d = json.loads(v) if isinstance(v, str) else None
        except ValueError:
            d = None
        if not isinstance(d, dict):
            raise ToolkitError(f"{path}: attribute 'subject_params' is {repr(v)[:60]}, expected JSON text of the "
                               "generator's subject parameters")
        ident, seed = d.get("identity"), d.get("seed", 0)
        ok = isinstance(ident, list) and len(ident) == len(IDENTITY_NAMES) and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in ident)
        if not ok or not isinstance(seed, int) or isinstance(seed, bool):
            raise ToolkitError(f"{path}: attribute 'subject_params': expected {{\"identity\": [...], \"seed\": int}} "
                               f"with an identity of {len(IDENTITY_NAMES)} finite numbers")


def read_attrs(path, f) -> dict[str, Any]:
    """The file's attributes, each checked (type, size, UTF-8 text), the ones readers use by value."""
    try:
        names = list(f.attrs)
    except READ_ERRORS as e:
        raise ToolkitError(f"{path}: attributes cannot be read (corrupt?): {one_line(e, 300)}") from e
    attrs = {name: _attr(path, f, name) for name in names}
    _check_known_attrs(path, attrs)
    return attrs


def validate_subject_file(path: str | os.PathLike, optional_keys: tuple[str, ...] = (),
                          widths: dict[str, tuple] | None = None) -> dict[str, Any]:
    """Check a subject file's schema and label ranges up front; return its summary.

    Raises ToolkitError naming the file and key for: unreadable/truncated files, missing keys, links that do
    not resolve inside the file, external links and storage, wrong shapes or dtypes, row counts that disagree,
    empty subjects, rows or labels too large for the memory budget, out-of-range labels (non-finite values,
    |pitch| > 90°, |yaw| > 180°, non-rotation ``w2c_Rmat``, non-positive focal lengths or scale, negative
    indices, landmarks far outside the image), bad subject-level arrays and attributes of the wrong type.
    Image and mesh rows are checked by shape and dtype (``vertice`` rows for finite values when read).
    ``optional_keys``: keys of :data:`REQUIRED` a file may lack (a peer layout that does not write them).
    ``widths``: key -> trailing shape, for keys of :data:`REQUIRED` a peer layout stores at another width
    (GazeNeRF's 306-d ``latent_codes``).
    Returns ``{"path", "n", "height", "width", "n_vertices", "optional": [...], "attrs": {...}}``.
    """
    path = Path(path)
    with open_h5(path) as f:
        missing = [k for k in REQUIRED if k not in optional_keys and not has_key(path, f, k)]
        if missing:
            raise ToolkitError(f"{path}: missing key '{missing[0]}'" + (f" (and {missing[1:]})" if missing[1:] else ""))
        sizes: dict[str, int] = {}
        n = _check_dataset(path, f, "face_patch", REQUIRED["face_patch"][0], "u", sizes, None).shape[0]
        if n == 0:
            raise ToolkitError(f"{path}: empty subject (0 rows in 'face_patch')")
        optional = [k for k in OPTIONAL if has_key(path, f, k)]
        present = {k: ((widths or {}).get(k, v[0]), v[1]) for k, v in REQUIRED.items()
                   if k not in optional_keys or has_key(path, f, k)}
        specs = {**present, **{k: OPTIONAL[k] for k in optional}}
        datasets = {k: _check_dataset(path, f, k, spec, kinds, sizes, n) for k, (spec, kinds) in specs.items()}
        lab = _read_labels(path, {k: ds for k, ds in datasets.items() if k not in IMAGE_KEYS and k != "vertice"}, n)
        _check_labels(path, lab, sizes["H"], sizes["W"])
        subject = check_subject_arrays(path, f)
        attrs = read_attrs(path, f)
        return {"path": str(path), "n": n, "height": sizes["H"], "width": sizes["W"], "n_vertices": sizes.get("V"),
                "optional": optional, "subject_keys": list(subject), "attrs": attrs}
