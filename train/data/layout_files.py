"""Reading a layout's files: its split file, the layout a stage reads a file in, and the checks made before any
row is read (:mod:`train.data.layouts` holds the layouts, :mod:`train.data.layout_conversion` the conversion)."""

from __future__ import annotations

import os

from toolkit.errors import ToolkitError
from train.data.format import REQUIRED
from train.data.layouts import (
    DITGAZE,
    LAYOUTS,
    MAX_SPLIT_BYTES,
    Layout,
    check_layout,
    describe_file,
    detect_layout,
    get_layout,
)
from train.data.triangulation import frame_rows, single_camera


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
