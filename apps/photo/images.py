"""Reading a user's photos: files and folders, decoded upright as 8-bit BGR (``toolkit.images.decode_image``: EXIF
orientation, grey / RGBA / palette / 16-bit / CMYK), and the EXIF focal length as pixels.

Every problem with one photo is a ``ToolkitError`` naming the file (the caller reports it and goes on).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError
from toolkit.images import EXIF_IFD

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".tif", ".tiff", ".bmp", ".heic", ".heif", ".avif")
"""The photo files a folder contributes (any case); a file named on the command line is read whatever its name.
HEIC / HEIF decode through pillow-heif (the ``photos`` extra), AVIF through Pillow; without a decoder such a file is
named (install the extra, or convert it), not passed over."""

DIAGONAL_35MM = math.hypot(36.0, 24.0)
"""mm: the diagonal of a 35 mm film frame, the reference of EXIF's FocalLengthIn35mmFilm (CIPA DC-008: the
35 mm equivalent is defined by the diagonal)."""

FOCAL_35MM_TAG = 0xA405


@dataclass
class Photo:
    """One decoded photo: ``bgr`` [H, W, 3] uint8 upright (EXIF orientation applied), ``focal_35mm`` the EXIF
    35 mm-equivalent focal length in mm (None when the file has none)."""

    path: Path
    bgr: np.ndarray
    focal_35mm: float | None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.bgr.shape[1], self.bgr.shape[0]


def photos_in(folder: Path) -> list[Path]:
    """A folder's photos: its files named as one (:data:`PHOTO_SUFFIXES`, any case), sorted, not recursive."""
    return sorted(q for q in folder.iterdir() if q.is_file() and q.suffix.lower() in PHOTO_SUFFIXES)


def other_media(folder: Path) -> str | None:
    """What a folder holds that is meant as photos but is not: "3 camera raw files (NEF): develop them first",
    videos; None when it holds neither (``toolkit.file_kinds``)."""
    from toolkit.file_kinds import raw_kind, video_kind

    files = [q for q in folder.iterdir() if q.is_file()]
    raws = [kind for q in files if (kind := raw_kind(q))]
    videos = sum(video_kind(q) is not None for q in files)
    said = [f"{len(raws)} camera raw file(s) ({', '.join(sorted(set(raws)))}): develop them to JPEG or PNG first"
            ] if raws else []
    said += [f"{videos} video(s): extract their frames first (e.g. with ffmpeg)"] if videos else []
    return "; ".join(said) or None


def folder_photos(folder: Path) -> list[Path]:
    """:func:`photos_in`, or a ToolkitError for a folder without photos, naming the raw files or videos it holds."""
    found = photos_in(folder)
    if not found:
        other = other_media(folder)
        raise ToolkitError(f"{folder}: no photos in this folder (expected {', '.join(PHOTO_SUFFIXES)} files)"
                           + (f"; it holds {other}" if other else ""))
    return found


def photo_groups(inputs: list[str | os.PathLike]) -> list[tuple[str, list[Path]]]:
    """The inputs as (name, photos) groups, one output file each: a file is a group of its own named by its stem,
    a folder one group of its photos (:data:`PHOTO_SUFFIXES`, sorted, not recursive) named by the folder. A
    missing path or a folder without photos is a ToolkitError; two groups of one name are refused (their
    outputs would collide)."""
    groups: list[tuple[str, list[Path]]] = []
    for p in map(Path, inputs):
        if p.is_dir():
            groups.append((p.resolve().name or "photos", folder_photos(p)))
        elif p.is_file():
            groups.append((p.stem, [p]))
        else:
            raise ToolkitError(f"{p}: no such file or folder")
    seen: dict[str, Path] = {}
    for name, files in groups:
        first = files[0] if len(files) == 1 else files[0].parent
        if name in seen:
            raise ToolkitError(f"{first}: its output {name}.h5 would replace that of {seen[name]}; rename one of them")
        seen[name] = first
    return groups


def _focal_35mm(exif) -> float | None:
    try:
        value = exif.get_ifd(EXIF_IFD).get(FOCAL_35MM_TAG)
        value = float(value) if value is not None else None
    except (TypeError, ValueError, KeyError, AttributeError, OSError, ZeroDivisionError):
        return None
    return value if value is not None and math.isfinite(value) and 4 <= value <= 2000 else None


def load_photo(path: str | os.PathLike) -> Photo:
    """Decode a photo (JPEG, PNG or anything Pillow reads) upright as 8-bit BGR (``toolkit.images.decode_image``:
    the EXIF orientation applied, every mode as 8-bit RGB, alpha on white). Not an image, a truncated or corrupt
    file, a HEIC Pillow cannot decode, a camera raw file or a video (named as such), an image over
    ``toolkit.images.MAX_IMAGE_PIXELS``: a ToolkitError naming the file."""
    from toolkit.images import decode_image

    path = Path(path)
    rgb, exif = decode_image(path, "photo")
    return Photo(path, np.ascontiguousarray(rgb[..., ::-1]), _focal_35mm(exif))


def naming_photo(path: Path, text: str) -> str:
    """``text``, a photo's problem, led by the photo's path unless it names the photo already: a single photo's
    error line."""
    return text if str(path) in text else f"{path}: {text}"


def photo_problem(path: Path, text: str) -> str:
    """"PATH: reason", the line a photo left out is reported with, whether or not ``text`` names the photo (the
    readers' errors start "photo PATH: ")."""
    for named in (f"photo {path}: ", f"{path}: "):
        if text.startswith(named):
            return f"{path}: {text[len(named):]}"
    return naming_photo(path, text)


def photo_focal(photo: Photo, focal: float | None = None, default_factor: float = 1.2) -> tuple[float, str]:
    """The photo's focal length in pixels and where it came from: ``focal`` when given ("--focal"), else the
    EXIF 35 mm equivalent scaled by the diagonal (f_px = f_35 · diagonal_px / 43.27 mm; "exif"), else
    ``default_factor`` × the longer side ("default": about a 50 mm lens on a 3:2 frame, a portrait lens or a
    phone photo cropped to the face)."""
    w, h = photo.size
    if focal is not None:
        return float(focal), "--focal"
    if photo.focal_35mm is not None:
        return photo.focal_35mm * math.hypot(w, h) / DIAGONAL_35MM, "exif"
    return default_factor * max(w, h), "default"


def photo_intrinsics(width: int, height: int, focal_px: float) -> np.ndarray:
    """[3, 3] float64 K of a photo: square pixels, principal point at the image centre (W/2, H/2: the centre in
    the u = 0 left-edge convention)."""
    return np.array([[focal_px, 0.0, width / 2], [0.0, focal_px, height / 2], [0.0, 0.0, 1.0]])
