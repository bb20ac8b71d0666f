"""``--labels labels.csv``: the user's own gaze of each photo instead of the iris estimate.

Columns (header names exact, any order, others refused): ``image`` (the photo's path relative to the CSV's folder,
or absolute, or its file name alone when unique among the inputs), ``gaze_pitch``, ``gaze_yaw`` (degrees, the
photo camera's frame, ETH-XGaze convention: pitch = asin(−g_y) positive up, yaw = atan2(−g_x, −g_z) positive
towards the image left; |pitch| < 90, |yaw| < 180). Every problem is one line naming the file, line and column.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError, bad_rows_error

COLUMNS = ("image", "gaze_pitch", "gaze_yaw")
MAX_BYTES = 64 * 1024 * 1024
"""Largest labels file read (a line is far shorter than 1 KB: millions of photos)."""


def _number(path: Path, line: int, col: str, text: str, limit: float) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v) or abs(v) >= limit:
        raise ToolkitError(f"{path} line {line}, column '{col}': expected degrees in (-{limit:g}, {limit:g}), "
                           f"got {text!r}")
    return v


def read_labels(path: str | os.PathLike) -> dict[Path, np.ndarray]:
    """The CSV as {resolved image path: (pitch, yaw) radians in the photo camera frame}."""
    path = Path(path)
    if path.is_dir():
        raise ToolkitError(f"--labels {path}: is a folder, expected a CSV file with columns {', '.join(COLUMNS)}")
    if not path.is_file():
        raise ToolkitError(f"--labels {path}: no such file")
    if path.stat().st_size > MAX_BYTES:
        raise ToolkitError(f"--labels {path}: {path.stat().st_size} bytes; expected at most {MAX_BYTES}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ToolkitError(f"--labels {path}: not UTF-8 text (expected a CSV with columns {', '.join(COLUMNS)})") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows or [c.strip() for c in rows[0]] != [c for c in rows[0]] or sorted(rows[0]) != sorted(COLUMNS):
        raise ToolkitError(f"--labels {path}: expected the header {','.join(COLUMNS)} (any order), got "
                           f"{','.join(rows[0]) if rows else 'an empty file'}")
    header = rows[0]
    out: dict[Path, np.ndarray] = {}
    bad: list[tuple[int, str]] = []
    for line, row in enumerate(rows[1:], start=2):
        if row and any(c.strip() for c in row):
            try:
                img, gaze = _label(path, line, header, row, out)
            except ToolkitError as e:
                bad.append((line, str(e)))
                continue
            out[img] = gaze
    if bad:
        raise bad_rows_error(bad)
    if not out:
        raise ToolkitError(f"--labels {path}: no rows")
    return out


def _label(path: Path, line: int, header: list[str], row: list[str], seen: dict) -> tuple[Path, np.ndarray]:
    """One CSV row -> (resolved image path, (pitch, yaw) radians); ``seen`` the rows read before it."""
    if len(row) != len(header):
        raise ToolkitError(f"{path} line {line}: {len(row)} cells, the header has {len(header)}")
    cell = dict(zip(header, (c.strip() for c in row)))
    if not cell["image"]:
        raise ToolkitError(f"{path} line {line}, column 'image': empty")
    img = Path(cell["image"])
    img = (img if img.is_absolute() else path.parent / img).resolve()
    if img in seen:
        raise ToolkitError(f"{path} line {line}, column 'image': {cell['image']} is labelled twice")
    return img, np.radians([_number(path, line, "gaze_pitch", cell["gaze_pitch"], 90.0),
                            _number(path, line, "gaze_yaw", cell["gaze_yaw"], 180.0)])


def labels_for(labels: dict[Path, np.ndarray], photos: list[Path], where: str) -> dict[Path, np.ndarray]:
    """Each photo's labelled gaze, by its resolved path or else its unique file name; a photo without one is a
    ToolkitError (before any work)."""
    by_name: dict[str, list[Path]] = {}
    for p in labels:
        by_name.setdefault(p.name, []).append(p)
    out = {}
    for photo in photos:
        key = photo.resolve()
        if key not in labels:
            named = by_name.get(photo.name, [])
            if len(named) != 1:
                raise ToolkitError(f"{where}: no row for the photo {photo} (column 'image' names it relative to the "
                                   "CSV's folder, or by its file name alone)")
            key = named[0]
        out[photo] = labels[key]
    return out
