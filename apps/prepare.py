"""A user's own photos as native subject files, fully offline (docs/photos.md).

    python -m apps.prepare PHOTOS... --out OUT_DIR [--like RUN_DIR] [--size 512] [--largest-face]
                           [--labels labels.csv] [--focal F] [--scale S]

Every face of every photo (JPEG, PNG, WebP, TIFF, ... files, or folders of them) is found and fitted (mediapipe's
face mesh as iBUG-68 landmarks and iris centres, apps.photo), its head pose solved by PnP against the project's
head model, normalized as ETH-XGaze normalizes (the camera turned to the face centre, a crop of ``--size`` pixels
covering ``--crop`` metres from ``--distance``), masked and labelled, and written as one row: one file
``OUT_DIR/<name>.h5`` per photo given as a file (its stem) and per folder (its name, one row per face of each of
its photos), readable by ``GazeDataset`` and ``python -m apps.redirect``. The gaze is estimated from the irises
(attribute ``gaze_source`` "iris-geometry") or read from ``--labels`` ("labels-csv"). ``OUT_DIR/contact_sheet.png``
shows what was found.

A photo that cannot be used (not an image, truncated, no face, a face under 64 pixels, a face cut off through an
eye, a face the landmarker or the head model cannot fit) is one line naming it and the reason; the others go
on. Exit status 2 only when no photo gave a face. Every file is written atomically. Needs the optional extra
``photos`` (mediapipe).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Sequence

from toolkit.errors import CliParser, ToolkitError, run_cli

MAX_SOURCE_NAMES_BYTES = 60_000
"""The ``source_files`` attribute (the photos' names as JSON) must stay under the format's 64 KiB attributes."""
SIZE_RANGE = (32, 2048)


def build_parser() -> argparse.ArgumentParser:
    ap = CliParser(prog="python -m apps.prepare", description=__doc__.split("\n")[0])
    ap.add_argument("photos", nargs="+", help="photo files (JPEG, PNG, WebP, TIFF, ...) and/or folders of them")
    ap.add_argument("--out", required=True, help="output folder: one <name>.h5 per photo file or folder")
    ap.add_argument("--like", default=None, help="a trained run directory: its head geometry, normalization "
                                                 "distance and crop, and data.res (the frame the model was trained in)")
    ap.add_argument("--size", type=int, default=None, help="crop size in pixels (default: the run's data.res, else 512)")
    ap.add_argument("--distance", type=float, default=None, help="normalized camera distance, metres (default: the "
                                                                 "run's, else 0.6)")
    ap.add_argument("--crop", type=float, default=None, help="metres the crop covers at the face (default: the "
                                                             "run's, else 0.26)")
    ap.add_argument("--focal", type=float, default=None, help="focal length of every photo in pixels (default: "
                                                              "EXIF 35 mm equivalent, else 1.2 x the longer side)")
    ap.add_argument("--scale", type=float, default=None, help="head scale of every face (default: from the iris "
                                                              "size, else 1)")
    ap.add_argument("--largest-face", action="store_true", help="keep only the largest face of each photo")
    ap.add_argument("--labels", default=None, help="CSV with columns image, gaze_pitch, gaze_yaw (degrees, photo "
                                                   "camera frame): the photos' own gazes instead of the iris estimate")
    ap.add_argument("--sheet", default=None, help="contact sheet PNG (default OUT/contact_sheet.png)")
    return ap


def check_args(args: argparse.Namespace) -> None:
    """The flags' own checks, before any photo is read (one-line ToolkitErrors)."""
    if args.size is not None and not SIZE_RANGE[0] <= args.size <= SIZE_RANGE[1]:
        raise ToolkitError(f"--size must be in [{SIZE_RANGE[0]}, {SIZE_RANGE[1]}] pixels, got {args.size}")
    for flag, v, lo, hi in (("--distance", args.distance, 0.05, 10.0), ("--crop", args.crop, 0.05, 2.0),
                            ("--focal", args.focal, 1.0, 1e6), ("--scale", args.scale, 0.5, 2.0)):
        if v is not None and not (math.isfinite(v) and lo <= v <= hi):
            raise ToolkitError(f"{flag} must be in [{lo:g}, {hi:g}], got {v}")
    if args.sheet is not None and Path(args.sheet).suffix.lower() != ".png":
        raise ToolkitError(f"--sheet {args.sheet}: expected a file name ending in .png")


def sheet_path(args: argparse.Namespace) -> tuple[Path, str]:
    """The contact sheet's path and how to name it in an error line (the flag, or that it is the flag's default)."""
    if args.sheet:
        return Path(args.sheet), "--sheet"
    return Path(args.out) / "contact_sheet.png", "--sheet (default OUT/contact_sheet.png)"


def check_outputs(args: argparse.Namespace, groups: list[tuple[str, list[Path]]]) -> None:
    """Every output location, before any photo is read, so that a refusal leaves nothing written: the output
    folder and the contact sheet can be made there, and neither a subject file nor the sheet replaces an input
    (a photo, also one found in a given folder, the labels CSV or the run directory)."""
    from toolkit.io import check_not_an_input, check_output_folder

    out = check_output_folder(args.out, f"--out {args.out}")
    sheet, flag = sheet_path(args)
    if sheet.is_dir():
        raise ToolkitError(f"{flag} {sheet}: is a folder, expected a .png file path")
    check_output_folder(sheet.parent, f"{flag} {sheet}")
    photos = [p for _, files in groups for p in files] + list(args.photos)
    others = [q for q in (args.labels, args.like) if q]
    for output, what in [(sheet, flag)] + [(out / f"{name}.h5", "--out's output") for name, _ in groups]:
        check_not_an_input(output, photos, what, "photo")
        check_not_an_input(output, others, what, "file")
    for name, _ in groups:
        h5 = out / f"{name}.h5"
        if h5.is_dir():
            raise ToolkitError(f"--out {out}: the output {h5} is a folder, expected a file path")


def make_target(args: argparse.Namespace):
    """The head model and normalization: the run's (``--like``) or the project's defaults, flags overriding."""
    from apps.photo.face_model import default_target, run_target

    target = run_target(args.like, args.size) if args.like else default_target(args.size or 512)
    if args.distance is not None:
        target.distance = args.distance
    if args.crop is not None:
        target.crop = args.crop
    return target


def file_attrs(photos: list[Path], focals: list, target, gaze_source: str) -> dict:
    names = json.dumps([str(p) for p in photos])
    return {"source": "apps.prepare", "gaze_source": gaze_source, "source_files": names,
            "photo_focal": json.dumps(focals), "n_cameras": 1, "face_model": target.model.source,
            "normalization": json.dumps({"distance": target.distance, "crop": target.crop}),
            "landmarks": "mediapipe FaceMesh (refined, 478 points) as iBUG-68: apps.photo.landmarks68"}


def prepare_group(name: str, photos: list[Path], finder, target, args, labels, report) -> tuple[Path | None, list]:
    """One output file from a group of photos; returns (its path or None, sheet strips) and reports each
    problem through ``report(photo, reason)``."""
    from apps.photo.images import load_photo, photo_focal
    from apps.photo.rows import photo_rows, write_rows
    from apps.photo.sheet import sheet_strip

    rows, strips, focals = [], [], []
    for i, path in enumerate(photos):
        try:
            photo = load_photo(path)
            got, problems = photo_rows(photo, finder, target, frame_index=i, largest_face=args.largest_face,
                                       focal=args.focal, scale=args.scale, gaze=None if labels is None else labels[path])
        except ToolkitError as e:
            report(path, str(e))
            focals.append(None)
            continue
        focals.append(list(photo_focal(photo, args.focal)))
        for p in problems:
            report(path, p)
        rows += got
        strips += [sheet_strip(path.name, photo.bgr, r.source_landmarks, r.arrays) for r in got]
    if not rows:
        return None, strips
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    attrs = file_attrs(photos, focals, target, "iris-geometry" if labels is None else "labels-csv")
    return write_rows(out / f"{name}.h5", rows, target, attrs), strips


def main(argv: Sequence[str] | None = None) -> int:
    from apps.photo.faces import FaceFinder
    from apps.photo.images import naming_photo, photo_groups, photo_problem

    args = build_parser().parse_args(argv)
    check_args(args)
    groups = photo_groups(args.photos)
    every = [p for _, files in groups for p in files]
    check_outputs(args, groups)
    for _, files in groups:
        if len(json.dumps([str(p) for p in files])) > MAX_SOURCE_NAMES_BYTES:
            raise ToolkitError(f"{files[0].parent}: {len(files)} photos; their names exceed the {MAX_SOURCE_NAMES_BYTES}"
                               " bytes a file's source_files attribute holds: split the folder")
    labels = None
    if args.labels:
        from apps.photo.labels import labels_for, read_labels

        labels = labels_for(read_labels(args.labels), every, f"--labels {args.labels}")
    target = make_target(args)
    problems: list[str] = []

    def report(photo: Path, reason: str) -> None:
        problems.append(naming_photo(photo, reason))
        if len(every) > 1:  # a single photo's problem is the error line itself
            print(f"skipped {photo_problem(photo, reason)}", file=sys.stderr)

    written, strips = [], []
    with FaceFinder() as finder:
        for name, files in groups:
            path, got = prepare_group(name, files, finder, target, args, labels, report)
            strips += got
            if path is not None:
                written.append(path)
    if not written:
        raise ToolkitError(problems[0] if len(every) == 1 else
                           f"none of the {len(every)} photos gave a usable face (each reason above)")
    from apps.photo.sheet import write_contact_sheet

    sheet = sheet_path(args)[0]
    write_contact_sheet(sheet, strips, len(strips))
    print(f"wrote {len(written)} file(s) to {args.out}: {len(strips)} faces from {len(every) - len(problems)} of "
          f"{len(every)} photos; contact sheet {sheet}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
