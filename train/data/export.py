"""``python -m train.data export --layout gazegaussian SRC_DIR OUT_DIR``: native subject files in a peer's layout.

Each ``SRC_DIR/<stem>.h5`` becomes ``OUT_DIR/xgaze_<stem>.h5`` (GazeGaussian dataloader/eth_xgaze.py L17-19,
L276 open ``xgaze_`` + the split entry) with the labels in that layout's conventions (``train.data.layouts
.from_native``: pitch sign, the 3D keys' frame, [N, 1] indices and scale, GazeNeRF's derived camera keys), and
``OUT_DIR/train_test_split.json`` in its form ({"train", "val", "val_gaze", "test", "test_specific"}, entries
``<stem>.h5``: GazeGaussian configs/dataset/eth_xgaze/train_test_split.json L84-100). Reading the files back
(``GazeDataset``, layout detected) gives the native labels. ``--layout ditgaze`` writes whole copies in this
project's current form (subject arrays and attributes kept, [N, 1] indices) with ``split.json``.

All or nothing: every source file is checked before anything is written, the files are written into a staging
folder inside ``OUT_DIR`` and moved into place once all are written; ``OUT_DIR`` may hold only the files this
export writes (an earlier export of the same subjects), so that two datasets never mix in it.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError
from toolkit.io import atomic_h5, check_not_an_input
from toolkit.limits import check_allocation

IMAGE_KEYS = ("face_patch", "head_mask", "left_eye_mask", "right_eye_mask")


def _native_file(path: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict]:
    """(every per-row key, the subject-level arrays, the attributes) of a native subject file, read whole through
    the bounded reader (validated by :func:`export` first)."""
    from toolkit.h5 import has_key, open_h5, read_array
    from train.data.format import OPTIONAL, REQUIRED, check_subject_arrays, read_attrs

    with open_h5(path) as f:
        keys = [k for k in (*REQUIRED, *OPTIONAL) if has_key(path, f, k)]
        check_allocation(sum(f[k].size * f[k].dtype.itemsize for k in keys) * 2, f"exporting {path}",
                         "export fewer rows per file")
        return {k: read_array(path, f, k) for k in keys}, check_subject_arrays(path, f), read_attrs(path, f)


def _write_peer(path: Path, rows: dict[str, np.ndarray]) -> None:
    """One exported file: images one chunk a row with lzf, as GazeNeRF's pipeline stores them (its
    dataset_pre_processing.py L258-381), labels whole."""
    with atomic_h5(path) as f:
        for k, v in rows.items():
            big = k in IMAGE_KEYS or k == "vertice"
            f.create_dataset(k, data=v, chunks=(1, *v.shape[1:]) if big else None,
                             compression="lzf" if big else None)


def _write_copy(path: Path, rows: dict[str, np.ndarray], subject: dict[str, np.ndarray], attrs: dict) -> None:
    """A native file in the current form: [N, 1] indices (files of before 2026-11-27 stored [N])."""
    from train.data.format import write_subject_h5
    from train.data.layouts import INDEX_KEYS

    rows = {k: v.reshape(-1, 1) if k in INDEX_KEYS else v for k, v in rows.items()}
    write_subject_h5(path, rows, subject=subject, attrs={k: v for k, v in attrs.items() if k != "format_version"})


def _split(files: list[Path], prefix: str) -> dict[str, list[str]]:
    """The source split (its ``split.json``, else the last quarter held out) in the target's form; a subject the
    split file leaves out of both parts stays out of both."""
    from train.data.dataset import split_files

    if len(files) < 2:
        train, held = files, []
    else:
        train, held = split_files(files, "train"), split_files(files, "test")
    train, held = [f"{f.stem}.h5" for f in train], [f"{f.stem}.h5" for f in held]
    return {"train": train, "val": held, "val_gaze": held, "test": [], "test_specific": []} if prefix else \
        {"train": train, "test": held}


def export(src: str | os.PathLike, out: str | os.PathLike, layout: str = "gazegaussian") -> list[Path]:
    """Export the native subject files of ``src`` (a folder, its ``split.json`` deciding train / held out) to
    ``out`` in ``layout`` (gazegaussian; ditgaze: whole copies in the current form); returns the files written."""
    from train.data.dataset import check_no_other_dataset, find_subject_files
    from train.data.format import validate_subject_file
    from train.data.layout_files import row_layout
    from train.data.layouts import get_layout

    target = get_layout(layout)
    files = find_subject_files(src)
    out = Path(out)
    check_not_an_input(out, [Path(src), *files], "OUT_DIR", "dataset")
    rows_of = {}
    for f in files:  # every source checked before anything is written
        if row_layout(f).name != "ditgaze":
            raise ToolkitError(f"{f}: export reads this project's own files; this one is {row_layout(f).name}")
        rows_of[f] = validate_subject_file(f)["n"]
    split = _split(files, target.split.prefix)
    names = [f"{target.split.prefix}{f.stem}.h5" for f in files]
    check_no_other_dataset(out, [*names, target.split.file_name], "OUT_DIR", "export")
    made = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".export.", suffix=".tmp", dir=out))
    except OSError as e:
        raise ToolkitError(f"OUT_DIR {out}: cannot write here ({e.strerror or e})") from None
    try:
        try:
            _write_all(files, names, target, staging, rows_of)
            (staging / target.split.file_name).write_text(json.dumps(split, indent=2) + "\n", encoding="utf-8")
        except ToolkitError as e:  # a full disk names the staging file: the user knows OUT_DIR
            raise ToolkitError(str(e).replace(f"{staging}{os.sep}", f"{out}{os.sep}")) from None
        except OSError as e:
            raise ToolkitError(f"OUT_DIR {out}: {e.strerror or e}; nothing was exported") from None
        for name in [*names, target.split.file_name]:  # the split file last: a folder with it is complete
            os.replace(staging / name, out / name)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if made:  # nothing of this export is left, not even the folder it made
            shutil.rmtree(out, ignore_errors=True)
        raise
    shutil.rmtree(staging, ignore_errors=True)
    return [out / name for name in names]


def _write_all(files: list[Path], names: list[str], target, staging: Path, rows_of: dict[Path, int]) -> None:
    """Each of ``files`` exported under its name in ``names`` into the folder ``staging``; ``rows_of`` each file's
    row count when it was validated."""
    from train.data.layout_conversion import from_native

    for f, name in zip(files, names, strict=True):
        rows, subject, attrs = _native_file(f)
        if len(rows["face_patch"]) != rows_of[f]:
            raise ToolkitError(f"{f}: changed while it was read")
        if target.name == "ditgaze":
            _write_copy(staging / name, rows, subject, attrs)
        else:
            _write_peer(staging / name, from_native(target, rows))
