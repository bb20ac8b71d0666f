"""The labels CSV of ``apps.redirect``: its columns, read and validated (``apps.labels_csv`` turns the
rows into the redirect app's inputs; see docs/redirect.md).

One row per image; columns (header names exact, any order; an empty optional cell = not given):

=============================  ========  =====================================================================
column                         required  meaning
=============================  ========  =====================================================================
``image``                      yes       image path, relative to the CSV's folder (or absolute); square, all
                                         images the same size, any format OpenCV reads
``head_pitch``, ``head_yaw``   yes       head pose, degrees: (pitch, yaw) of the face direction (head −z) in the
                                         *normalized* camera's frame, the convention of ``face_head_pose``
                                         (pitch in ±90, yaw in ±180)
``head_roll``                  no        roll about the face direction, degrees (default 0: the ETH-XGaze
                                         normalization removes roll by construction)
``gaze_pitch``, ``gaze_yaw``   no*       the image's own gaze, degrees, normalized camera frame (ETH-XGaze
                                         labels; pitch in ±90, yaw in ±180); *needed on rows without ``code``,
                                         and on every row with ``apps.redirect --fit-weights``
``focal``                      no        focal length in pixels of this image (default ``--focal``, else the
                                         project's normalized camera: size · NORM_DISTANCE / NORM_CROP)
``distance``                   no        camera-to-face-centre distance in metres (default ``--distance``,
                                         else NORM_DISTANCE = 0.6)
``mask``                       no        head mask image (non-zero = head), same size as the image; default:
                                         the trained model's splatted head silhouette
``code``                       no        ``.npy`` file with the shape code (identity 80 + expression 64: 144 numbers
                                         for a model trained on native data; the run's widths otherwise);
                                         default: fitted on the image (``train.evaluation.fitting.test_time_fit``)
=============================  ========  =====================================================================

Everything is validated before any rendering: each problem is one :class:`toolkit.ToolkitError` naming
the CSV line and column (or the image file) and what was expected.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError, bad_rows_error
from toolkit.images import read_image

REQUIRED_COLUMNS = ("image", "head_pitch", "head_yaw")
MAX_FOCAL = 1000
"""Largest focal length, in image widths (pixels per pixel of width): a field of view of 0.06°."""
MAX_DISTANCE = 100.0
"""Largest camera-to-face distance, metres."""
OPTIONAL_COLUMNS = ("head_roll", "gaze_pitch", "gaze_yaw", "focal", "distance", "mask", "code")


@dataclass
class LabelRow:
    """One validated CSV row (angles in radians, paths resolved)."""

    line: int
    image: Path
    head: tuple[float, float, float]  # pitch, yaw, roll
    gaze: tuple[float, float] | None  # camera frame
    focal: float  # pixels of the stored image
    distance: float  # metres
    mask: Path | None
    code: np.ndarray | None  # [identity + expression], the model's widths


def _image_size(path: Path, what: str) -> tuple[int, int]:
    """(height, width); decoded once (its size checked from the header first), so that a file whose pixels do
    not decode is refused with every other check of the CSV rather than mid-run."""
    img = read_image(path, what, gray=True)
    return int(img.shape[0]), int(img.shape[1])


def labels_csv_file(path: str | os.PathLike) -> Path:
    """The labels CSV a dataset argument names, resolved: the file itself, or ``labels.csv`` in a folder."""
    p = Path(path)
    return (p / "labels.csv" if p.is_dir() else p).resolve()


def is_labels_csv(path: str | os.PathLike) -> bool:
    """Whether a dataset argument names a labels CSV (a ``.csv`` file, or a folder holding ``labels.csv``)."""
    p = Path(path)
    return p.suffix.lower() == ".csv" or (p.is_dir() and (p / "labels.csv").is_file())


def read_labels(csv_path: str | os.PathLike, *, focal: float | None = None, distance: float | None = None,
                default_distance: float = 0.6, default_crop: float = 0.26,
                code_widths: tuple[int, int] = (80, 64)) -> tuple[list[LabelRow], int]:
    """Validate a labels CSV and every file it names -> (rows, image size S).

    ``focal``/``distance`` are the defaults for rows that leave those cells empty; without them the
    project's normalized camera (``default_distance``, ``default_crop``) decides the focal length.
    ``code_widths``: (identity, expression) of the model's code, which a row's ``code`` must match.
    """
    p = labels_csv_file(csv_path)
    if not p.is_file():
        raise ToolkitError(f"{p}: no such labels CSV (expected columns {', '.join(REQUIRED_COLUMNS)}, ...)")
    for name, v, hi in (("--focal", focal, math.inf), ("--distance", distance, MAX_DISTANCE)):
        if v is not None and not (math.isfinite(v) and 0 < v <= hi):
            raise ToolkitError(f"{name} must be a positive number{f', at most {hi:g} metres' if hi < math.inf else ''}, "
                               f"got {v}")
    header, raw = _read_table(p)
    rows: list[LabelRow] = []
    size: tuple[int, int] | None = None
    bad: list[tuple[int, str]] = []  # every row is checked: one run of the command names all lines to mend
    for line, r in raw:
        try:
            if None in r:  # cells beyond the header's: csv.DictReader files them under None, and would be lost
                raise ToolkitError(f"{p} line {line}: {len(header) + len(r[None])} cells, the header has {len(header)}")
            cells = _Cells(p, line, {(k or "").strip(): (v or "").strip() if isinstance(v, str) else ""
                                     for k, v in r.items()})
            row, hw = _label_row(cells, size, focal=focal, distance=distance, default_distance=default_distance,
                                 default_crop=default_crop, code_widths=code_widths)
        except ToolkitError as e:
            if f"line {line}" not in str(e):  # a flag's problem (--focal), not the row's: the same for every row
                raise
            bad.append((line, str(e)))
            continue
        size = size or hw
        rows.append(row)
    if bad:
        raise bad_rows_error(bad)
    return rows, size[0]


def _read_table(p: Path) -> tuple[list[str], list[tuple[int, dict]]]:
    """The CSV's header (checked: no column twice, the required ones present, none unknown, the gaze columns
    together) and its data rows as (line number, {column: cell})."""
    try:
        with open(p, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            raw = [(reader.line_num, r) for r in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ToolkitError(f"{p}: not a readable CSV file ({e})") from None
    twice = sorted({c for c in header if header.count(c) > 1})
    if twice:  # csv.DictReader would keep the last of them silently
        raise ToolkitError(f"{p}: column(s) {twice} appear more than once in the header")
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise ToolkitError(f"{p}: missing column(s) {missing}; the header has {header}")
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        raise ToolkitError(f"{p}: unknown column(s) {unknown}; columns are {list(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)}")
    if ("gaze_pitch" in header) != ("gaze_yaw" in header):
        raise ToolkitError(f"{p}: columns gaze_pitch and gaze_yaw go together; only one is present")
    if not raw:
        raise ToolkitError(f"{p}: no data rows")
    return header, raw


@dataclass
class _Cells:
    """One CSV row's stripped cells, read as numbers or paths with errors naming the line and column."""

    csv_path: Path
    line: int
    cells: dict[str, str]
    where: str = ""  # "<csv> line <n>", for the errors

    def __post_init__(self):
        self.where = f"{self.csv_path} line {self.line}"

    def num(self, col: str, *, required: bool = False, lo: float = -math.inf, hi: float = math.inf,
            positive: bool = False, unit: str = "degrees") -> float | None:
        s, where = self.cells.get(col, ""), self.where
        if s == "":
            if required:
                raise ToolkitError(f"{where}, column '{col}': empty; expected a number")
            return None
        try:
            v = float(s)
        except ValueError:
            raise ToolkitError(f"{where}, column '{col}': expected a number, got {s!r}") from None
        if not math.isfinite(v):
            raise ToolkitError(f"{where}, column '{col}': expected a finite number, got {s!r}")
        if positive and v <= 0:
            raise ToolkitError(f"{where}, column '{col}': expected a positive number, got {s!r}")
        if not lo <= v <= hi:
            raise ToolkitError(f"{where}, column '{col}': expected {unit} in [{lo:g}, {hi:g}], got {s!r}")
        return v

    def path(self, col: str) -> Path | None:
        s = self.cells.get(col, "")
        if not s.isprintable():  # a quoted cell can hold a line break or a NUL: no file is named so
            raise ToolkitError(f"{self.where}, column '{col}': expected a file path, got {s!r}")
        return None if s == "" else Path(s) if Path(s).is_absolute() else self.csv_path.parent / s


def _label_row(c: _Cells, size: tuple[int, int] | None, *, focal: float | None, distance: float | None,
               default_distance: float, default_crop: float,
               code_widths: tuple[int, int] = (80, 64)) -> tuple[LabelRow, tuple[int, int]]:
    """One data row, validated with every file it names -> (the row, its image's (height, width)); ``size`` is
    the first image's, which every image must match (None for the first row)."""
    where = c.where
    img_path = c.path("image")
    if img_path is None:
        raise ToolkitError(f"{where}, column 'image': empty; expected an image path")
    hw = _image_size(img_path, f"{where}, column 'image':")
    if hw[0] != hw[1]:
        raise ToolkitError(f"{where}, column 'image': {img_path} is {hw[1]}x{hw[0]} (width x height); "
                           "expected a square crop")
    if size is None:
        size = hw
    elif hw != size:
        raise ToolkitError(f"{where}, column 'image': {img_path} is {hw[1]}x{hw[0]}; the first image is "
                           f"{size[1]}x{size[0]} (all images must have the same size)")
    # Pitch is an asin (±90°); yaw an atan2 (±180°: extreme ETH-XGaze cameras see |yaw| > 90°).
    head = tuple(math.radians(c.num(col, required=col != "head_roll", lo=-lim, hi=lim) or 0.0)
                 for col, lim in (("head_pitch", 90), ("head_yaw", 180), ("head_roll", 180)))
    gp, gy = c.num("gaze_pitch", lo=-90, hi=90), c.num("gaze_yaw", lo=-180, hi=180)
    if (gp is None) != (gy is None):
        raise ToolkitError(f"{where}: gaze_pitch and gaze_yaw must both be given or both be empty")
    gaze = None if gp is None else (math.radians(gp), math.radians(gy))
    # A focal length beyond MAX_FOCAL image widths (a field of view under 0.06°) or a distance beyond
    # MAX_DISTANCE is a typo; left through, it overflows the projection into NaN far from this line.
    f = c.num("focal", positive=True, lo=0, hi=MAX_FOCAL * hw[1], unit="pixels")
    d = c.num("distance", positive=True, lo=0, hi=MAX_DISTANCE, unit="metres")
    d = d if d is not None else (distance if distance is not None else default_distance)
    if f is None and focal is not None and focal > MAX_FOCAL * hw[1]:
        raise ToolkitError(f"--focal {focal:g}: expected at most {MAX_FOCAL} image widths ({MAX_FOCAL * hw[1]} pixels "
                           f"for the {hw[1]}-pixel images of {c.csv_path})")
    if f is None:
        f = focal if focal is not None else size[0] * default_distance / default_crop
    mask_path = c.path("mask")
    if mask_path is not None:
        mhw = _image_size(mask_path, f"{where}, column 'mask':")
        if mhw != hw:
            raise ToolkitError(f"{where}, column 'mask': {mask_path} is {mhw[1]}x{mhw[0]}; expected the image's "
                               f"size {hw[1]}x{hw[0]}")
    code = _read_code(c.path("code"), where, code_widths)
    if code is None and gaze is None:
        raise ToolkitError(f"{where}: no 'code' given, so the code is fitted on the image, which needs the "
                           "image's own gaze: fill gaze_pitch and gaze_yaw (or give a code)")
    return LabelRow(c.line, img_path, head, gaze, float(f), float(d), mask_path, code), hw


def _read_code(code_path: Path | None, where: str, code_widths: tuple[int, int] = (80, 64)) -> np.ndarray | None:
    """The row's ``code`` file -> [identity + expression] float32 (None when the cell is empty), checked."""
    if code_path is None:
        return None
    if not code_path.is_file():
        raise ToolkitError(f"{where}, column 'code': {code_path}: no such file")
    try:
        code = np.load(code_path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:  # EOFError: an empty file
        raise ToolkitError(f"{where}, column 'code': {code_path}: not a .npy array ({e})") from None
    if np.asarray(code).size != sum(code_widths):
        raise ToolkitError(f"{where}, column 'code': {code_path}: expected {sum(code_widths)} numbers (identity "
                           f"{code_widths[0]} + expression {code_widths[1]})")
    code = np.asarray(code, np.float32).reshape(-1)
    if not np.isfinite(code).all():
        raise ToolkitError(f"{where}, column 'code': {code_path}: contains NaN or inf")
    return code
