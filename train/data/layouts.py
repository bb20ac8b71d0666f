"""Subject-file layouts as data: the native one and the peers' (GazeGaussian, GazeNeRF, the ETH-XGaze release).

A :class:`Layout` says what a layout's HDF5 file holds (file names, keys and shapes, gaze sign, 3D frame, code
slices, split file); :func:`detect_layout` picks one from a file's keys. ``train.data.layout_conversion``
turns a layout's arrays into the native conventions (docs/data.md) and back, ``train.data.layout_files`` reads
its split files and decides the layout a stage reads a file in. Every peer fact below
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
    contradicts, or which keys of other layouts it has."""
    layout = get_layout(layout)
    missing = sorted(set(layout.required) - set(keys))
    if missing:
        raise ToolkitError(f"{_where(where)}data.layout={layout.name} requires keys {missing}, which the file "
                           f"lacks (it has {_listed(set(keys) & KNOWN_KEYS)})")
    bad = _misfits(layout, shapes or {})
    if bad:
        raise ToolkitError(f"{_where(where)}data.layout={layout.name}: key {bad[0]}")
    foreign = sorted((set(keys) & KNOWN_KEYS) - layout.keys)
    if foreign:  # another layout's file: read as this one, its gaze sign or 3D frame would be silently wrong
        others = [lay.name for lay in LAYOUTS.values() if _fits(lay, set(keys), shapes or {})]
        raise ToolkitError(f"{_where(where)}data.layout={layout.name}: the file has {foreign}, keys only other "
                           f"layouts write" + (f" (it is a {others[0]} file)" if len(others) == 1 else ""))
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


# --- Codes ---------------------------------------------------------------------------------------------------

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
