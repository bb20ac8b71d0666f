"""``apps.redirect`` on photos: prepare the faces on the fly, fit and render them, and write per face a grid and
(``--paste-back``) the redirected face pasted back into its photo (docs/redirect.md, "Your own photos").

    python -m apps.redirect RUN_DIR photo.jpg [more.png folder/ ...] OUT_DIR --gazes grid:3x3:20 [--paste-back]

INPUT is one or more photo files (JPEG, PNG, WebP, TIFF, BMP, ...: any picture Pillow reads, whatever its name)
and/or folders of them (a folder holding no ``labels.csv`` and no HDF5 file; its files named as photos,
``apps.photo.images.PHOTO_SUFFIXES``, not recursive). Every face is found and normalized as
``apps.prepare`` does it, in the run's frame (``apps.photo.face_model.run_target``: its head geometry,
normalization and ``data.res``), into a temporary subject file; each face is then fitted as ``--fit-weights``
fits a row (the default for photos: the run never saw the face) and rendered at every target gaze. OUT_DIR
receives:

- ``redirected.h5``: the rows ``apps.redirect`` writes for any input, plus each input face's ``warp``,
  ``face_box`` and ``source_size`` (``apps.photo.rows.EXTRA_ROW_KEYS``) per output row, and the photos as the
  attribute ``source_files`` (JSON, indexed by ``frame_index``);
- ``<photo>_face<k>_grid.png`` per face (k = 1, 2, ... largest first): the input crop, then one tile per gaze;
- with ``--paste-back``, ``<photo>_face<k>_<pitch>_<yaw>.png`` per face and gaze (degrees, head frame, to 0.1°):
  the photo at its own resolution with that face redirected, feathered inside the head mask; every other
  pixel is the decoded photo's, bit for bit (hence PNG: a JPEG would re-encode them all).

A photo without a usable face is one line naming it; the others go on (exit status 2, one ``error:`` line,
only when no photo gave a face). Every file is written atomically.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError

OUT_NAME = "redirected.h5"
"""The HDF5 file photo input writes into OUT_DIR."""
TILE_RANGE = (128, 256)
"""Side of a grid tile in pixels: the crop's size, brought into this range."""
LABEL_PX = 18
"""Height of a tile's label strip."""
GRID_COLUMNS = 10
"""Tiles in one row of a grid; more wrap."""
GRID_MAX_GAZES = 99
"""Gazes shown in a grid (every one is in redirected.h5 and, with --paste-back, pasted)."""
UNDO_KEYS = ("warp", "face_box", "source_size")
"""The input rows' keys copied to every output row: what pastes an output row back into its photo."""


DATASET_SUFFIXES = (".h5", ".hdf5", ".csv")
"""INPUT files that are datasets whatever their content; any other existing file that is a picture is a photo."""


def is_photo_input(path: str | os.PathLike) -> bool:
    """Whether an INPUT argument names photos: a file named as one (``apps.photo.images.PHOTO_SUFFIXES``; existing
    or not: a missing one is refused as such later) or, whatever its name, a picture by its content (not named as
    a dataset: :data:`DATASET_SUFFIXES`), or a folder of photos holding no ``labels.csv`` and no HDF5 file."""
    from apps.labels_table import is_labels_csv
    from apps.photo.images import PHOTO_SUFFIXES
    from toolkit.file_kinds import video_kind
    from toolkit.images import is_picture

    p = Path(path)
    if not p.is_dir():  # a video too: the photo reader names it, with the way to its frames
        suffix = p.suffix.lower()
        return suffix in PHOTO_SUFFIXES or (suffix not in DATASET_SUFFIXES and (is_picture(p) or bool(video_kind(p))))
    if is_labels_csv(p) or any(p.glob("*.h5")) or any(p.glob("*.hdf5")):
        return False
    from apps.photo.images import other_media, photos_in

    return bool(photos_in(p)) or other_media(p) is not None  # raw files or videos: the photo reader names them


def photo_files(given: list[str]) -> list[Path]:
    """The photos of the INPUT arguments, in order (a folder's sorted); one ToolkitError for a missing file or
    two photos of one name (their outputs would collide)."""
    from apps.photo.images import folder_photos
    from apps.prepare import MAX_SOURCE_NAMES_BYTES

    files: list[Path] = []
    for g in map(Path, given):
        if not g.exists():
            raise ToolkitError(f"{g}: no such file or folder")
        files += folder_photos(g) if g.is_dir() else [g]
    seen: dict[str, Path] = {}
    for p in files:
        if p.stem in seen:
            raise ToolkitError(f"{p} and {seen[p.stem]}: both would write outputs named {p.stem}_face*; rename one "
                               "or redirect them one at a time")
        seen[p.stem] = p
    if len(json.dumps([str(p) for p in files])) > MAX_SOURCE_NAMES_BYTES:
        raise ToolkitError(f"{len(files)} photos: their names exceed the {MAX_SOURCE_NAMES_BYTES} bytes the output's "
                           "source_files attribute holds; redirect them in smaller groups")
    return files


def resolve_inputs(args: argparse.Namespace) -> None:
    """Sort the INPUT arguments (``args.dataset``, a list) into photo input (``args.photos``, the files; fitting
    on: ``args.fit_weights``) or one dataset (``args.dataset``, a path); the photo-only flags are refused
    without photos (one-line ToolkitErrors)."""
    given = args.dataset_args = list(args.dataset)
    kinds = [is_photo_input(p) for p in given]
    args.photos = []
    if any(kinds):
        if not all(kinds):
            raise ToolkitError(f"{given[kinds.index(False)]}: not a photo (JPEG, PNG, ...) or a folder of photos; "
                               "photo input cannot be mixed with an HDF5 file or a labels CSV")
        args.photos = photo_files(given)
        args.fit_weights = True  # the run never saw these faces
        args.dataset = given[0]
        return
    if len(given) > 1:
        raise ToolkitError(f"{len(given)} inputs given: only photos (JPEG, PNG, ... files, folders of them) may be "
                           "several; give one HDF5 file, labels CSV or folder")
    args.dataset = given[0]
    for flag, on, why in (("--paste-back", args.paste_back, "pastes the redirected faces into their photos"),
                          ("--largest-face", args.largest_face, "picks a face of each photo")):
        if on:
            raise ToolkitError(f"{flag} {why}: it needs photo input (JPEG, PNG, ... files or folders of them), not "
                               f"{given[0]}")


def check_photo_out(args: argparse.Namespace) -> None:
    """The output folder's checks for photo input, before any work (one-line ToolkitErrors)."""
    from toolkit.io import check_not_an_input, check_output_folder

    out = Path(args.out)
    if out.suffix.lower() in (".h5", ".hdf5"):
        raise ToolkitError(f"out {out}: photo input writes a folder ({OUT_NAME}, face grids, pasted photos); give a "
                           "folder name, not an HDF5 file")
    check_output_folder(out, f"out {out}")
    for p in args.photos:
        if p.resolve().parent == out.resolve():
            raise ToolkitError(f"out {out}: holds the input photo {p}; a later run would read the PNGs written "
                               "beside it as photos: give another folder")
    check_not_an_input(out, [args.run_dir], "out", "run directory")
    if args.focal is not None and not (math.isfinite(args.focal) and 1 <= args.focal <= 1e6):
        raise ToolkitError(f"--focal must be in [1, 1e+06] pixels, got {args.focal}")
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise ToolkitError("photo input runs in one process: start it without torchrun")


def gaze_tag(gaze: np.ndarray) -> str:
    """[2] (pitch, yaw) radians -> their degrees to 0.1° as a file name's part: ``-20_+12.5``."""
    p, y = (round(math.degrees(float(v)), 1) + 0.0 for v in gaze)  # + 0.0: no "-0"
    return f"{p:+g}_{y:+g}"


def photo_settings(args: argparse.Namespace) -> dict:
    """What photo input's rows depend on beyond the run, for the chunks' settings (a resumed run re-prepares the
    photos): the photos, their sizes and times, and the preparation's options."""
    from toolkit.io import file_stamp

    stamp = hashlib.sha1(";".join(file_stamp(p) for p in args.photos).encode()).hexdigest()
    return {"dataset": [str(p.resolve()) for p in args.photos], "input_stamp": stamp,
            "photo_options": {"largest_face": args.largest_face, "focal": args.focal}}


def prepare_faces(args: argparse.Namespace, target) -> tuple[list, list[tuple[int, int]], list]:
    """Every usable face of ``args.photos`` as a row (``apps.photo.rows.FaceRow``) in ``target``'s frame ->
    (rows, (photo index, face number k from 1) per row, each photo's [focal px, source] or None). A photo or a
    face that cannot be used is a ``skipped`` line on stderr; no usable face at all is a ToolkitError (a single
    photo's: its reason, naming it)."""
    from apps.photo.faces import FaceFinder
    from apps.photo.images import load_photo, naming_photo, photo_focal, photo_problem
    from apps.photo.rows import photo_rows

    photos, rows, faces, focals, failed = args.photos, [], [], [], []
    with FaceFinder() as finder:
        for i, path in enumerate(photos):
            try:
                photo = load_photo(path)
                got, problems = photo_rows(photo, finder, target, frame_index=i, largest_face=args.largest_face,
                                           focal=args.focal)
            except ToolkitError as e:
                failed.append(naming_photo(path, str(e)))
                focals.append(None)
                if len(photos) > 1:  # a single photo's reason is the error line itself
                    print(f"skipped {photo_problem(path, str(e))}", file=sys.stderr)
                continue
            focals.append(list(photo_focal(photo, args.focal)))
            for p in problems:
                print(f"skipped {path}: {p}", file=sys.stderr)
            rows += got
            faces += [(i, k + 1) for k in range(len(got))]
    if not rows:
        raise ToolkitError(failed[0] if len(photos) == 1 else
                           f"none of the {len(photos)} photos gave a usable face (each reason above)")
    return rows, faces, focals


def redirect_photos(args: argparse.Namespace, gazes: np.ndarray, redirect_dataset, fit_steps_for) -> None:
    """Photo input, end to end (module docstring): ``gazes`` [G, 2] radians, head frame; ``args.out`` the
    output folder. ``redirect_dataset`` and ``fit_steps_for`` are ``apps.redirect``'s (passed in: that module
    imports this one)."""
    from apps.photo.face_model import run_target
    from apps.photo.rows import write_rows
    from apps.prepare import file_attrs
    from train.trained_run import TrainedRun

    tags = [gaze_tag(g) for g in gazes]
    if args.paste_back and len(set(tags)) < len(tags):
        twice = next(t for t in tags if tags.count(t) > 1)
        raise ToolkitError(f"--gazes {args.gazes!r}: two gazes round to {twice} (degrees to 0.1°), the name of one "
                           "pasted photo; give distinct gazes")
    run = TrainedRun.open(args.run_dir)
    fit_steps_for(args, run.config, None)  # its checks before the photos are read
    target = run_target(args.run_dir)  # the run's head, normalization and data.res
    rows, faces, focals = prepare_faces(args, target)
    out_dir = Path(args.out)
    attrs = {k: v for k, v in file_attrs(args.photos, focals, target, "iris-geometry").items() if k != "source"}
    attrs["source_file"] = str(args.dataset) if len(args.dataset_args) == 1 else json.dumps(args.dataset_args)
    undo = {k: np.stack([r.arrays[k] for r in rows]) for k in UNDO_KEYS}
    with tempfile.TemporaryDirectory(prefix="apps-redirect-") as tmp:
        prepared = write_rows(Path(tmp) / "faces.h5", rows, target, attrs)
        args.dataset, args.out = str(prepared), str(out_dir / OUT_NAME)
        redirect_dataset(args, gazes, run, attrs=attrs, photos=photo_settings(args), extra_rows=undo)
    grids, pasted = write_face_outputs(out_dir, args, rows, faces, target.size)
    print(f"wrote {grids} face grid(s)" + (f" and {pasted} pasted photo(s)" if args.paste_back else "") +
          f" to {out_dir}")


def write_face_outputs(out_dir: Path, args: argparse.Namespace, rows: list, faces: list[tuple[int, int]],
                       size: int) -> tuple[int, int]:
    """Per rendered face, its grid and (``args.paste_back``) its pasted photos, from ``out_dir/redirected.h5``
    and the input ``rows`` (``faces``: their (photo index, k)); ``size`` the crops' side the rows' ``warp`` maps
    into. Returns (grids, pasted photos) written."""
    import h5py

    from apps.photo.images import load_photo
    from apps.photo.paste import paste_back

    grids = pasted = 0
    with h5py.File(out_dir / OUT_NAME, "r") as h:
        source = h["source_row"][:]
        for i, path in enumerate(args.photos):
            mine = [r for r in np.unique(source) if faces[r][0] == i]
            photo = load_photo(path) if args.paste_back and mine else None
            for r in mine:
                sel = np.flatnonzero(source == r)
                crops, masks, gz = h["face_patch"][sel], h["head_mask"][sel], h["pitchyaw_head"][sel]
                a, stem = rows[r].arrays, f"{path.stem}_face{faces[r][1]}"
                write_png(out_dir / f"{stem}_grid.png", face_grid(a["face_patch"], a["pitchyaw_head"], crops, masks[0], gz))
                grids += 1
                if photo is None:
                    continue
                if tuple(photo.size) != tuple(int(v) for v in a["source_size"]):
                    raise ToolkitError(f"{path}: changed while it was redirected ({photo.size[0]}x{photo.size[1]} "
                                       f"pixels, was {a['source_size'][0]}x{a['source_size'][1]})")
                for crop, mask, g in zip(crops, masks, gz):
                    write_png(out_dir / f"{stem}_{gaze_tag(g)}.png",
                              paste_back(photo.bgr, crop, mask, a["warp"], warp_size=size))
                    pasted += 1
    return grids, pasted


def grid_tile_side(crop_size: int) -> int:
    """The side of a grid tile for crops of ``crop_size`` pixels (:data:`TILE_RANGE`)."""
    return int(np.clip(crop_size, *TILE_RANGE))


def _tile(bgr: np.ndarray, label: str, side: int) -> np.ndarray:
    """[S, S, 3] uint8 -> [side + LABEL_PX, side, 3]: resized, a label strip below."""
    import cv2

    interp = cv2.INTER_AREA if bgr.shape[0] > side else cv2.INTER_LINEAR
    img = cv2.resize(bgr, (side, side), interpolation=interp) if bgr.shape[0] != side else bgr
    strip = np.full((LABEL_PX, side, 3), 255, np.uint8)
    cv2.putText(strip, label, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([img, strip], 0)


def _label(gaze: np.ndarray) -> str:
    p, y = (round(math.degrees(float(v)), 1) + 0.0 for v in gaze)
    return f"p{p:+g} y{y:+g}"


def face_grid(crop: np.ndarray, gaze: np.ndarray, renders: np.ndarray, head_mask: np.ndarray,
              gazes: np.ndarray) -> np.ndarray:
    """One face's grid -> [rows · (T + LABEL_PX), cols · T, 3] uint8 BGR (T = :func:`grid_tile_side`): the input
    crop [S, S, 3] (labelled with its estimated gaze [2]), then each render [G, S, S, 3] over the input crop,
    blended inside the head mask [S, S] as the paste-back blends (``apps.photo.paste.feathered_alpha``),
    labelled with its gaze (``gazes`` [G, 2] radians, head frame: ``p<pitch> y<yaw>`` degrees); at most
    :data:`GRID_COLUMNS` tiles a row and :data:`GRID_MAX_GAZES` gazes."""
    from apps.photo.paste import FEATHER, feathered_alpha

    S = crop.shape[0]
    side = grid_tile_side(S)
    alpha = feathered_alpha(head_mask, FEATHER * S)[..., None]
    tiles = [_tile(crop, f"input {_label(gaze)}", side)]
    for img, g in zip(renders[:GRID_MAX_GAZES], gazes[:GRID_MAX_GAZES]):
        tiles.append(_tile(np.rint(alpha * img + (1 - alpha) * crop).astype(np.uint8), _label(g), side))
    if len(renders) > GRID_MAX_GAZES:
        tiles.append(_tile(np.full_like(crop, 255), f"+{len(renders) - GRID_MAX_GAZES} more gazes", side))
    cols = min(GRID_COLUMNS, len(tiles))
    tiles += [np.full_like(tiles[0], 255)] * (-len(tiles) % cols)
    return np.concatenate([np.concatenate(tiles[i:i + cols], 1) for i in range(0, len(tiles), cols)], 0)


def write_png(path: Path, bgr: np.ndarray) -> None:
    """[H, W, 3] uint8 BGR -> a PNG file, written atomically."""
    import cv2

    from toolkit.io import atomic_write_bytes

    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise ToolkitError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())
