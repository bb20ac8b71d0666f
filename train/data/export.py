"""``python -m train.data export --layout gazegaussian SRC_DIR OUT_DIR``: native subject files in a peer's layout.

Each ``SRC_DIR/<stem>.h5`` becomes ``OUT_DIR/xgaze_<stem>.h5`` (GazeGaussian dataloader/eth_xgaze.py L17-19,
L276 open ``xgaze_`` + the split entry) with the labels in that layout's conventions (``train.data.layouts
.from_native``: pitch sign, the 3D keys' frame, [N, 1] indices and scale, GazeNeRF's derived camera keys), and
``OUT_DIR/train_test_split.json`` in its form ({"train", "val", "val_gaze", "test", "test_specific"}, entries
``<stem>.h5``: GazeGaussian configs/dataset/eth_xgaze/train_test_split.json L84-100). Reading the files back
(``GazeDataset``, layout detected) gives the native labels.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError
from toolkit.io import atomic_h5, atomic_write_text, check_not_an_input
from toolkit.limits import check_allocation

IMAGE_KEYS = ("face_patch", "head_mask", "left_eye_mask", "right_eye_mask")


def _native_rows(path: Path) -> dict[str, np.ndarray]:
    """Every per-row key of a native subject file, read whole through the bounded reader (validated first)."""
    from toolkit.h5 import has_key, open_h5, read_array
    from train.data.format import OPTIONAL, REQUIRED, validate_subject_file

    info = validate_subject_file(path)
    with open_h5(path) as f:
        keys = [k for k in (*REQUIRED, *OPTIONAL) if has_key(path, f, k)]
        check_allocation(sum(f[k].size * f[k].dtype.itemsize for k in keys) * 2, f"exporting {path}",
                         "export fewer rows per file")
        rows = {k: read_array(path, f, k) for k in keys}
    if info["n"] != len(rows["face_patch"]):
        raise ToolkitError(f"{path}: changed while it was read")
    return rows


def _write(path: Path, rows: dict[str, np.ndarray]) -> None:
    """One exported file: images one chunk a row with lzf, as GazeNeRF's pipeline stores them (its
    dataset_pre_processing.py L258-381), labels whole."""
    with atomic_h5(path) as f:
        for k, v in rows.items():
            big = k in IMAGE_KEYS or k == "vertice"
            f.create_dataset(k, data=v, chunks=(1, *v.shape[1:]) if big else None,
                             compression="lzf" if big else None)


def export(src: str | os.PathLike, out: str | os.PathLike, layout: str = "gazegaussian") -> list[Path]:
    """Export the native subject files of ``src`` (a folder, its ``split.json`` deciding train / held out) to
    ``out`` in ``layout`` (gazegaussian; ditgaze copies); returns the files written."""
    from train.data.dataset import find_subject_files, split_files
    from train.data.layout_conversion import from_native
    from train.data.layout_files import row_layout
    from train.data.layouts import get_layout

    target = get_layout(layout)
    files = find_subject_files(src)
    out = Path(out)
    check_not_an_input(out, [Path(src), *files], "OUT_DIR", "dataset")
    for f in files:
        if row_layout(f).name != "ditgaze":
            raise ToolkitError(f"{f}: export reads this project's own files; this one is {row_layout(f).name}")
    held = set(split_files(files, "test")) if len(files) > 1 else set()
    prefix = target.split.prefix
    written = []
    for f in files:
        dest = out / f"{prefix}{f.stem}.h5"
        _write(dest, from_native(target, _native_rows(f)))
        written.append(dest)
    entries = {"train": [f"{f.stem}.h5" for f in files if f not in held],
               "val": [f"{f.stem}.h5" for f in files if f in held]}
    split = {**entries, "val_gaze": entries["val"], "test": [], "test_specific": []} if prefix else \
        {"train": entries["train"], "test": entries["val"]}
    atomic_write_text(out / target.split.file_name, json.dumps(split, indent=2) + "\n")
    return written
