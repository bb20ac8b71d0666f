"""Subject-file layouts as data: the native one and the peers' (GazeGaussian, GazeNeRF, the ETH-XGaze release).

A :class:`Layout` says what a layout's HDF5 file holds (file names, keys and shapes, gaze sign, 3D frame, code
slices, split file); :func:`detect_layout` picks one from a file's keys, :func:`to_native` turns a layout's
arrays into the native conventions (docs/data.md) and :func:`from_native` exports them. Every peer fact below
cites the peer's file and line (ucwxb/GazeGaussian bb8fac9, AlessandroRuzzi/GazeNeRF eb0a5f1, xucong-zhang/ETH-XGaze
ef9bff0); where the peers' code does not settle a fact the layout's ``notes`` say so instead of guessing.

Shape specs are strings: dims joined by ``,``, alternatives by ``|``; ``N`` rows, ``H``/``W``/``V`` free sizes,
an integer an exact size, ``144+`` a size of at least 144.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from toolkit.errors import ToolkitError
from train.data.format import OPTIONAL, REQUIRED, SUBJECT_KEYS

NATIVE_CODES = (("identity", 80), ("expression", 64))
MODEL_CODES = ("identity", "expression")
"""The code slices the Gaussian model reads: a native ``latent_codes`` row is their concatenation, in this order,
their widths those of the file's layout (:func:`code_widths`)."""
CODE_KEYS = MappingProxyType({"texture": "latent_texture", "illumination": "latent_illumination"})
"""The native keys of a layout's other code slices: carried by the rows and samples, never fed to the model."""
INDEX_KEYS = ("cam_index", "frame_index")
LANDMARK_3D_KEYS = ("facial_landmarks_3d", "vertice")
MAX_SPLIT_BYTES = 1 << 20
"""Largest split file read: ETH-XGaze's lists 110 subjects in 3 KB."""


@dataclass(frozen=True)
class SplitForm:
    """How a layout's split file names its subjects: ``{train_key: [...], held_out_key: [...]}``, each entry a
    file name (``.h5`` optional) that the layout's loader opens as ``prefix + entry``."""

    file_name: str
    train_key: str
    held_out_key: str
    prefix: str = ""


@dataclass(frozen=True, eq=False)
class Layout:
    name: str
    description: str
    file_pattern: str
    required: Mapping[str, str]
    optional: Mapping[str, str]
    gaze_key: str | None
    gaze_frame: str
    pitch_sign: int
    """+1: pitch = asin(-g_y) (native, ETH-XGaze); -1: pitch = asin(+g_y). Yaw is atan2(-g_x, -g_z) in all."""
    frame_3d: str | None
    """``world`` (native), ``w2c-transposed`` (stored p, world q = (p - w2c_Tvec) @ w2c_Rmat^T), ``triangulated``
    (no 3D keys: w2c maps each row's head frame to its camera, so the world is that head frame, and the 3D
    landmarks are triangulated from the 2D ones of a frame's cameras: :func:`triangulate_frames`), None: no 3D keys
    and no cameras to make them with."""
    codes: tuple[tuple[str, int], ...]
    split: SplitForm
    renames: Mapping[str, str] = field(default_factory=dict)
    """stored key -> native key, where the meaning is the same and only the name differs."""
    notes: tuple[str, ...] = ()

    @property
    def keys(self) -> frozenset[str]:
        return frozenset(self.required) | frozenset(self.optional)

    @property
    def gaze_sign(self) -> str:
        return "pitch = asin(-g_y)" if self.pitch_sign > 0 else "pitch = asin(+g_y)"

    def spec(self, key: str) -> str | None:
        return self.required.get(key, self.optional.get(key))


def _native_spec(spec: tuple) -> str:
    dims = ",".join(["N", *map(str, spec)])
    if spec == ():  # indices: (N,) as written; (N, 1) accepted when reading (format._check_dataset)
        return "N|N,1"
    return dims + ("|N" if spec == (1,) else "")  # scale: (N, 1) as written, (N,) accepted


_GAZENERF_KEYS = {  # GazeNeRF dataset_pre_processing.py L258-381 (ETH-XGaze branch); uint8 indices, float64 labels
    "face_patch": "N,H,W,3", "head_mask": "N,H,W", "left_eye_mask": "N,H,W", "right_eye_mask": "N,H,W",
    "facial_landmarks": "N,68,2", "w2c_Rmat": "N,3,3", "w2c_Tvec": "N,3", "inmat": "N,3,3",
    "c2w_Rmat": "N,3,3", "c2w_Tvec": "N,3", "inv_inmat": "N,3,3", "pitchyaw_head": "N,2",
    "face_head_pose": "N,2", "cam_index": "N,1",
}

DITGAZE = Layout(
    name="ditgaze",
    description="this project's own files (train.data.format, docs/data.md)",
    file_pattern="*.h5",
    required=MappingProxyType({k: _native_spec(s) for k, (s, _) in REQUIRED.items()}),
    optional=MappingProxyType({**{k: _native_spec(s) for k, (s, _) in OPTIONAL.items()},
                               **{k: "any" for k in SUBJECT_KEYS}}),
    gaze_key="pitchyaw_head", gaze_frame="head", pitch_sign=1, frame_3d="world", codes=NATIVE_CODES,
    split=SplitForm("split.json", "train", "test"),  # train/data/dataset.py split_files
)

GAZEGAUSSIAN = Layout(
    name="gazegaussian",
    description="GazeGaussian's preprocessed ETH-XGaze (GazeNeRF's pipeline plus pose, scale and 3D keys)",
    file_pattern="xgaze_<subject>.h5",  # GazeGaussian dataloader/eth_xgaze.py L17-19, L276; README.md L88
    required=MappingProxyType({
        **{k: v for k, v in _GAZENERF_KEYS.items() if k not in ("c2w_Rmat", "c2w_Tvec", "inv_inmat")},
        # the keys its loader reads: dataloader/eth_xgaze.py L414-480
        "facial_landmarks_3d": "N,68,3", "vertice": "N,V,3", "pose": "N,6",
        "scale": "N,1",  # scale[idx, :] L480, scale[:, :, None] models/mesh_head.py L178
        "latent_codes": "N,144+",  # [:80] identity, [80:144] expression: L447-448, configs/gazegaussian_options.py L9-10
    }),
    # GazeNeRF's keys, which a file made by its pipeline keeps; GazeGaussian's loader never reads them
    optional=MappingProxyType({"frame_index": "N,1", "c2w_Rmat": "N,3,3", "c2w_Tvec": "N,3",
                               "inv_inmat": "N,3,3", "pitchyaw": "N,2", "pitchyaw_3d": "N,3"}),
    # README.md L39: preprocessing "mainly follows GazeNeRF"; utils/gaze_estimation_utils.py L43-47: pitch = arcsin(v[1])
    gaze_key="pitchyaw_head", gaze_frame="head", pitch_sign=-1,
    frame_3d="w2c-transposed",  # dataloader/eth_xgaze.py L440 (and L310): ldms_3d = (ldms_3d - wt) @ wr.T
    codes=NATIVE_CODES,
    split=SplitForm("train_test_split.json", "train", "val", prefix="xgaze_"),  # eth_xgaze.py L103-118, L163
    notes=(
        "GazeGaussian ships no preprocessing code: the gaze sign is GazeNeRF's (README.md L39), not checked on its files",
        "whether its fits have scale != 1 cannot be read from the code (it applies scale: eth_xgaze.py L316-319)",
        "its loader reads any number of 3D landmarks; 68 (iBUG) is the native schema's",
        "the dtypes of its own keys are not in its code; its loader casts them (eth_xgaze.py L302-316, L434-435)",
    ),
)

GAZENERF = Layout(
    name="gazenerf",
    description="GazeNeRF's preprocessed ETH-XGaze: NL3DMM codes and cameras, no pose, scale or 3D keys",
    file_pattern="xgaze_<subject>.h5",  # dataset_pre_processing.py L123; datasets/eth_xgaze.py L245
    required=MappingProxyType({**_GAZENERF_KEYS, "latent_codes": "N,306", "pitchyaw_3d": "N,3", "frame_index": "N,1"}),
    # pitchyaw: L355-361 (ETH-XGaze and MPII branches); face_center: L704-710 (MPII branch only)
    optional=MappingProxyType({"pitchyaw": "N,2", "face_center": "N,3"}),
    # utils/gaze_estimation_utils.py L45-51: pitch = arcsin(v[0, 1]), yaw = arctan2(-v[0, 0], -v[0, 2])
    # fitting_nl3dmm.py L276-279: w2c maps the NL3DMM head frame (the pose folded in, unit scale: L170)
    gaze_key="pitchyaw_head", gaze_frame="head", pitch_sign=-1, frame_3d="triangulated",
    codes=(("identity", 100), ("expression", 79), ("texture", 100), ("illumination", 27)),  # gazenerf_options.py L11-14
    split=SplitForm("train_test_split.json", "train", "val", prefix="xgaze_"),  # datasets/eth_xgaze.py L88, L144
    notes=(
        "w2c_Rmat/w2c_Tvec map the NL3DMM head frame to the camera: the head pose is folded in "
        "(surface_fitting/nl3dmm/fitting_nl3dmm.py L276-279), so there is no pose to convert: native rows get pose "
        "0 and scale 1 (the world is the row's head frame) and 3D landmarks triangulated per frame",
        "each image's head pose is fitted on its own in one virtual camera (fitting_nl3dmm.py L164-170, "
        "dataset_fitting_3dmm.py L43-54): a frame's rows share a head frame only as far as their fits agree, "
        "which the triangulation's reprojection error measures",
        "the 2D landmarks are face_alignment's get_landmarks (pre_processing/gen_landmark.py L27-29, L56), which "
        "states no pixel-centre convention; GazeNeRF fits its cameras to them with K-projected points "
        "(nl3dmm_renderer.py L129-134) and its principal point W/2 is the image centre (dataset_fitting_3dmm.py "
        "L44-47, nl3dmm_renderer.py L141-151), i.e. u = 0 is the left edge, as native: they are not shifted",
        "pitchyaw_head is in the annotation's head frame (dataset_pre_processing.py L404-430, "
        "gaze_estimation_utils.py L20-42), the cameras in the NL3DMM fit's: a camera-frame gaze derived from both "
        "carries whatever rotation lies between the two frames",
        "its loader takes identity, expression and texture codes from row 0 of a subject (datasets/eth_xgaze.py L346-347)",
        "frame_index is stored as uint8 (dataset_pre_processing.py L260-265): frames past 255 wrap, so a frame is "
        "a run of consecutive rows (L383-445 write a frame's cameras in turn), not an index value",
        "the gaze origin of pitchyaw_head is the mean of rows 0-5 of the full 50-point face model "
        "(dataset_pre_processing.py L425-430, gaze_estimation_utils.py L24-33), not the normalization's face centre",
    ),
)

XGAZE = Layout(
    name="xgaze",
    description="the ETH-XGaze release (xgaze_224 / xgaze_448): normalized face patches and gaze, no masks, 3D or codes",
    file_pattern="<train|test>/<subject>.h5",  # ETH-XGaze data_loader.py L87; normalization_example.py L206
    # normalization_example.py L295-310; the release's keys also in TWWinde/ETH--XGAZE h5reader.py L9-14
    required=MappingProxyType({"face_patch": "N,H,W,3", "face_head_pose": "N,2", "face_mat_norm": "N,3,3",
                               "cam_index": "N,1", "frame_index": "N,1"}),
    # face_gaze: absent for test subjects (data_loader.py L66, README.md L45-46); facial_landmarks: L299 writes it
    optional=MappingProxyType({"face_gaze": "N,2", "facial_landmarks": "N,68,2"}),
    gaze_key="face_gaze", gaze_frame="normalized camera", pitch_sign=1,  # normalization_example.py L313-314
    frame_3d=None, codes=(),
    split=SplitForm("train_test_split.json", "train", "test"),  # data_loader.py L31, L41, L64
    renames=MappingProxyType({"face_gaze": "pitchyaw_cam"}),
    notes=("the head-frame gaze is derived from face_gaze and face_head_pose: the normalization has no roll "
           "(normalization_example.py L56-62), so face_head_pose fixes the head rotation",),
)

LAYOUTS: dict[str, Layout] = {lay.name: lay for lay in (DITGAZE, GAZEGAUSSIAN, GAZENERF, XGAZE)}
KNOWN_KEYS = frozenset().union(*(lay.keys for lay in LAYOUTS.values()))


def _where(where: str) -> str:
    return f"{where}: " if where else ""


def _listed(keys) -> str:
    keys = sorted(keys)
    return f"{keys[:8]}{f' + {len(keys) - 8} more' if len(keys) > 8 else ''}"


def get_layout(name: str | Layout) -> Layout:
    if isinstance(name, Layout):
        return name
    if name not in LAYOUTS:
        raise ToolkitError(f"data.layout={name!r}: unknown layout, expected one of {', '.join(LAYOUTS)}")
    return LAYOUTS[name]


# --- Detection -----------------------------------------------------------------------------------------------

def _dim_fits(want: str, got: int) -> bool:
    if want.isdigit():
        return got == int(want)
    if want.endswith("+"):
        return got >= int(want[:-1])
    return True  # N, H, W, V


def shape_fits(spec: str, shape: tuple) -> bool:
    """Whether ``shape`` is one of the alternatives of ``spec`` (see the module docstring)."""
    if spec == "any":
        return True
    alts = [a.split(",") for a in spec.split("|")]
    return any(len(a) == len(shape) and all(_dim_fits(w, g) for w, g in zip(a, shape)) for a in alts)


def _misfits(layout: Layout, shapes: Mapping[str, tuple]) -> list[str]:
    return [f"'{k}' {list(s)} (expected {layout.spec(k)})" for k, s in shapes.items()
            if layout.spec(k) is not None and not shape_fits(layout.spec(k), tuple(s))]


def _fits(layout: Layout, keys: set[str], shapes: Mapping[str, tuple]) -> bool:
    # A key only other layouts write rules a layout out; keys no layout knows are ignored.
    return set(layout.required) <= keys and (keys & KNOWN_KEYS) <= layout.keys and not _misfits(layout, shapes)


def detect_layout(keys: set[str], shapes: Mapping[str, tuple] | None = None, where: str = "") -> Layout:
    """The one layout whose required keys the file has, whose other known keys it allows, and whose shapes
    it matches (the peers index ``cam_index[idx, :]``, so 1-D indices are native only); else one ToolkitError
    naming what was found and asking for ``data.layout=``."""
    keys, shapes = set(keys), dict(shapes or {})
    fit = [lay for lay in LAYOUTS.values() if _fits(lay, keys, shapes)]
    if len(fit) == 1:
        return fit[0]
    listed = _listed(keys & KNOWN_KEYS or keys)
    if fit:
        names = " or ".join(f"data.layout={lay.name}" for lay in fit)
        frames = "; ".join(f"{lay.name}: 3D {lay.frame_3d}, {lay.gaze_sign}" for lay in fit)
        raise ToolkitError(f"{_where(where)}the keys {listed} fit several layouts ({frames}); pass {names}")
    raise ToolkitError(f"{_where(where)}no known layout fits the keys {listed}; pass data.layout= one of "
                       f"{', '.join(LAYOUTS)}")


def check_layout(layout: str | Layout, keys: set[str], shapes: Mapping[str, tuple] | None = None,
                 where: str = "") -> Layout:
    """The user-named ``layout``, or one ToolkitError saying which of its required keys (or shapes) the file
    contradicts."""
    layout = get_layout(layout)
    missing = sorted(set(layout.required) - set(keys))
    if missing:
        raise ToolkitError(f"{_where(where)}data.layout={layout.name} requires keys {missing}, which the file "
                           f"lacks (it has {_listed(set(keys) & KNOWN_KEYS)})")
    bad = _misfits(layout, shapes or {})
    if bad:
        raise ToolkitError(f"{_where(where)}data.layout={layout.name}: key {bad[0]}")
    return layout


def describe_file(path: str | os.PathLike) -> tuple[set[str], dict[str, tuple]]:
    """A subject file's top-level keys and the shapes of those any layout knows, read through toolkit.h5."""
    from toolkit.errors import one_line
    from toolkit.h5 import READ_ERRORS, h5_dataset, open_h5

    with open_h5(path) as f:
        try:
            keys = set(f.keys())
        except READ_ERRORS as e:
            raise ToolkitError(f"{path}: cannot list keys (truncated or corrupt?): {one_line(e, 300)}") from e
        shapes = {}
        for k in sorted(keys & KNOWN_KEYS):
            try:
                shapes[k] = tuple(h5_dataset(path, f, k).shape)
            except ToolkitError:  # a bad dataset: left to the validator, whose message names what is wrong
                continue
        return keys, shapes


# --- Conversion ----------------------------------------------------------------------------------------------

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


def split_codes(layout: str | Layout, codes: np.ndarray) -> dict[str, np.ndarray]:
    """A layout's code rows cut into its named slices (``codes`` [N, C], C at least their total width)."""
    layout = get_layout(layout)
    codes, total = np.asarray(codes), sum(w for _, w in layout.codes)
    exact = layout.spec("latent_codes") == f"N,{total}"
    if codes.ndim != 2 or codes.shape[1] < total or (exact and codes.shape[1] != total):
        widths = " + ".join(f"{w} {n}" for n, w in layout.codes)
        raise ToolkitError(f"key 'latent_codes' has shape {list(codes.shape)}, expected [N, {total}] for "
                           f"{layout.name} ({widths})")
    starts = np.cumsum([0] + [w for _, w in layout.codes])
    return {name: codes[:, s:s + w] for (name, w), s in zip(layout.codes, starts)}


def code_widths(layout: str | Layout) -> tuple[int, int]:
    """(identity, expression): the widths of the native ``latent_codes`` a ``layout``'s files give (80, 64 for
    native and GazeGaussian files, 100, 79 for GazeNeRF's); a ToolkitError for a layout without codes."""
    layout = get_layout(layout)
    widths = dict(layout.codes)
    if not all(name in widths for name in MODEL_CODES):
        raise ToolkitError(f"data.layout={layout.name}: its files carry no identity and expression codes "
                           f"({layout.description})")
    return widths["identity"], widths["expression"]


def agreed_code_widths(files: Sequence[tuple[str | os.PathLike, str | Layout]]) -> tuple[int, int]:
    """The code widths (:func:`code_widths`) of every ``(path, layout)`` of a run's files, which must agree: one
    model reads them all. Else one line naming two files and their widths."""
    first, widths = None, None
    for path, layout in files:
        w = code_widths(layout)
        if widths is None:
            first, widths = path, w
        elif w != widths:
            raise ToolkitError(f"{path}: codes of {w[0]} identity + {w[1]} expression dims, but {first} has "
                               f"{widths[0]} + {widths[1]}; one model reads every file of a run, so their layouts' "
                               "codes must agree")
    if widths is None:
        raise ToolkitError("no subject files to take the code widths from")
    return widths


def _codes_to_native(layout: Layout, codes: np.ndarray, out: dict) -> None:
    """``latent_codes`` = the layout's identity then expression slice (the model's code, at the layout's
    widths); its other slices under :data:`CODE_KEYS` (GazeNeRF's texture and illumination)."""
    parts = split_codes(layout, codes)
    out["latent_codes"] = np.concatenate([parts[name] for name in MODEL_CODES], 1)
    out.update({CODE_KEYS[name]: a for name, a in parts.items() if name not in MODEL_CODES})


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
    component, and with the head z-axis from face_head_pose (L327-330) that fixes the head rotation."""
    p, y = head_pose[:, 0], head_pose[:, 1]
    z = np.stack([np.cos(p) * np.sin(y), np.sin(p), np.cos(p) * np.cos(y)], -1)
    x = np.stack([np.cos(y), np.zeros_like(y), -np.sin(y)], -1)
    M = np.stack([x, np.cross(z, x), z], -1)  # columns: the head axes in the camera frame
    p, y = gaze_cam[:, 0], gaze_cam[:, 1]  # native (pitch, yaw) -> direction, as toolkit.rotations
    g = np.einsum("nji,nj->ni", M, np.stack([-np.cos(p) * np.sin(y), -np.sin(p), -np.cos(p) * np.cos(y)], -1))
    return np.stack([np.arcsin(np.clip(-g[:, 1], -1, 1)), np.arctan2(-g[:, 0], -g[:, 2])], -1)


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


# --- Split files ---------------------------------------------------------------------------------------------

def _stems(path, layout: Layout, key: str, entries) -> list[str]:
    if not isinstance(entries, list):
        raise ToolkitError(f"{path}: '{key}' is a JSON {type(entries).__name__}, expected a list of subject file names")
    out = []
    for e in entries:
        if not isinstance(e, str) or not e.strip() or "/" in e or "\\" in e or e in (".", ".."):
            raise ToolkitError(f"{path}: '{key}' has the entry {e!r}, expected a file name such as "
                               f"'subject0000.h5'")
        out.append(layout.split.prefix + (e[:-3] if e.endswith(".h5") else e))
    return out


def read_split_file(path: str | os.PathLike, layout: str | Layout) -> tuple[list[str], list[str]]:
    """A split file of ``layout``'s form -> (training subjects, held-out subjects) as the stems of the files
    the layout's loader opens: ``split.json`` {"train", "test"} (native), ``train_test_split.json`` {"train",
    "val"} (GazeGaussian, GazeNeRF: "subject0012.h5" is file xgaze_subject0012.h5) or {"train", "test"}
    (the ETH-XGaze release). Other keys ("val_gaze", "test_specific") are ignored."""
    from toolkit.io import check_readable_file, parse_json_object

    layout = get_layout(layout)
    path = check_readable_file(path, "split file")
    if path.stat().st_size > MAX_SPLIT_BYTES:
        raise ToolkitError(f"{path}: {path.stat().st_size} bytes, a split file is expected under {MAX_SPLIT_BYTES}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ToolkitError(f"{path}: not a split file (not UTF-8 text: byte {e.start})") from None
    spec = parse_json_object(text, f"{path}: the split file")
    form = layout.split
    for key in (form.train_key, form.held_out_key):
        if key not in spec:
            other = [lay.name for lay in LAYOUTS.values() if {lay.split.train_key, lay.split.held_out_key} <= set(spec)]
            hint = f" (a {other[0]} split file? pass data.layout={other[0]})" if other else ""
            raise ToolkitError(f"{path}: no key '{key}', expected the {layout.name} form {{\"{form.train_key}\": "
                               f"[...], \"{form.held_out_key}\": [...]}}; it has {sorted(spec)[:8]}{hint}")
    train = _stems(path, layout, form.train_key, spec[form.train_key])
    held = _stems(path, layout, form.held_out_key, spec[form.held_out_key])
    both = sorted(set(train) & set(held))
    if both:
        raise ToolkitError(f"{path}: subject {both[0]} is both in '{form.train_key}' and '{form.held_out_key}'")
    if not train and not held:
        raise ToolkitError(f"{path}: '{form.train_key}' and '{form.held_out_key}' are both empty")
    return train, held


# --- Reading rows ---------------------------------------------------------------------------------------------

def row_layout(path: str | os.PathLike, requested: str = "auto") -> Layout:
    """The layout of a subject file that the training and redirection stages read row by row: detected from
    its keys (``requested`` "auto") or the named one, checked against the keys. A layout that cannot give every
    native row key but the mesh (the ETH-XGaze release: no masks, cameras or codes) is one line naming what is
    missing; GazeNeRF's gets its pose, scale and 3D landmarks from :func:`to_native`."""
    keys, shapes = describe_file(path)
    if requested != "auto":
        layout = check_layout(requested, keys, shapes, str(path))
    elif _written_here(path):  # this project's writer marks its files: the validator names what is wrong with one
        layout = DITGAZE
    else:
        try:
            layout = detect_layout(keys, shapes, str(path))
        except ToolkitError:
            # A file no layout fits: the closest one (most of its required keys present) says what is wrong,
            # through the native validator for native-looking files, else through check_layout.
            closest = max(LAYOUTS.values(), key=lambda lay: len(set(lay.required) & keys) / len(lay.required))
            if closest is not DITGAZE:
                check_layout(closest, keys, shapes, str(path))
                raise
            layout = DITGAZE
    lacking = sorted(set(REQUIRED) - native_keys(layout) - {"vertice"})  # the mesh: only with_mesh readers
    if lacking:
        raise ToolkitError(f"{path}: a {layout.name} file ({layout.description}) has no {', '.join(lacking)}, which "
                           f"the stages that render or pose heads need")
    return layout


def check_frames(path: str | os.PathLike, layout: str | Layout) -> None:
    """Up front, for a layout whose 3D landmarks are triangulated per frame (GazeNeRF's): every frame of the file
    at ``path`` is seen by two cameras or more (:func:`frame_rows`; the triangulation itself runs when the labels
    are read), or every frame by one (:func:`single_camera`: a file without 3D landmarks)."""
    from toolkit.h5 import has_key, open_h5, read_array

    if get_layout(layout).frame_3d != "triangulated":
        return
    with open_h5(path) as f:
        index = {k: read_array(path, f, k) for k in ("frame_index", "cam_index") if has_key(path, f, k)}
    if not single_camera(index):
        frame_rows(index["frame_index"], index.get("cam_index"), str(path))


def _written_here(path: str | os.PathLike) -> bool:
    """Whether the file carries the ``format_version`` attribute this project's writer (train.data.format)
    puts on every subject file; the peers' pipelines write none."""
    from toolkit.h5 import READ_ERRORS, open_h5

    with open_h5(path) as f:
        try:
            return "format_version" in f.attrs
        except READ_ERRORS:
            return False


def native_keys(layout: str | Layout) -> frozenset[str]:
    """The native row keys a ``layout``'s files give once converted (:func:`to_native`): what they store, renamed,
    and what their frames settle (GazeNeRF's pose, scale and 3D landmarks)."""
    layout = get_layout(layout)
    keys = {layout.renames.get(k, k) for k in layout.keys}
    if layout.frame_3d == "triangulated":
        keys |= {"pose", "scale", "facial_landmarks_3d"}
    return frozenset(keys)


def stored_widths(layout: str | Layout) -> dict[str, tuple[int, ...]]:
    """Trailing shapes of keys a ``layout`` stores at another width than the native schema, for the validator
    (``train.data.format.validate_subject_file``): GazeNeRF's 306-d ``latent_codes``."""
    spec = get_layout(layout).spec("latent_codes") or ""
    return {"latent_codes": (int(spec[2:]),)} if spec[2:].isdigit() else {}


def validate_file(path: str | os.PathLike, layout: str | Layout) -> dict:
    """``train.data.format.validate_subject_file`` of a file in ``layout`` (one :func:`row_layout` accepts): the
    native keys the layout does not store may be absent, its codes are as wide as it stores them."""
    from train.data.format import validate_subject_file

    layout = get_layout(layout)
    return validate_subject_file(path, tuple(sorted(set(REQUIRED) - set(layout.required))), stored_widths(layout))


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
                           "other rows; convert the file's arrays whole (train.data.layouts.to_native)")
    out = {k: v[0] for k, v in to_native(layout, {k: np.asarray(v)[None] for k, v in row.items()}).items()}
    out.setdefault("frame_index", np.int32(index))
    return out
