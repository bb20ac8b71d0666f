"""Reading a user's photos: files and folders, EXIF orientation, grey / RGBA / 16-bit to 8-bit BGR, and the EXIF
focal length as pixels.

Every problem with one photo is a ``ToolkitError`` naming the file (the caller reports it and goes on).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
"""The photo files a folder contributes (any case); a file named on the command line is read whatever its name."""

DIAGONAL_35MM = math.hypot(36.0, 24.0)
"""mm: the diagonal of a 35 mm film frame, the reference of EXIF's FocalLengthIn35mmFilm (CIPA DC-008: the
35 mm equivalent is defined by the diagonal)."""

EXIF_IFD, FOCAL_35MM_TAG = 0x8769, 0xA405


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


def photo_groups(inputs: list[str | os.PathLike]) -> list[tuple[str, list[Path]]]:
    """The inputs as (name, photos) groups, one output file each: a file is a group of its own named by its stem,
    a folder one group of its photos (:data:`PHOTO_SUFFIXES`, sorted, not recursive) named by the folder. A
    missing path or a folder without photos is a ToolkitError; two groups of one name are refused (their
    outputs would collide)."""
    groups: list[tuple[str, list[Path]]] = []
    for p in map(Path, inputs):
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in PHOTO_SUFFIXES)
            if not found:
                raise ToolkitError(f"{p}: no photos in this folder (expected {', '.join(PHOTO_SUFFIXES)} files)")
            groups.append((p.resolve().name or "photos", found))
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


def _to_rgb8(im, path: Path) -> np.ndarray:
    """A decoded Pillow image of any common mode -> [H, W, 3] uint8 RGB (alpha composited on white, 16-bit
    scaled down)."""
    from PIL import Image

    if im.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit grey (PNG) or 32-bit integer grey
        a = np.asarray(im, np.float64)
        top = 65535.0 if im.mode.startswith("I;16") or a.max() > 255 else 255.0
        g = np.clip(np.rint(a * 255.0 / top), 0, 255).astype(np.uint8)
        return np.repeat(g[..., None], 3, -1)
    if im.mode == "F":
        raise ToolkitError(f"photo {path}: a floating-point image; expected a photo (8- or 16-bit)")
    if im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info):
        rgba = im.convert("RGBA")
        white = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
        return np.asarray(Image.alpha_composite(white, rgba).convert("RGB"))
    return np.asarray(im.convert("RGB"))


def _focal_35mm(im) -> float | None:
    try:
        value = im.getexif().get_ifd(EXIF_IFD).get(FOCAL_35MM_TAG)
        value = float(value) if value is not None else None
    except (TypeError, ValueError, KeyError, AttributeError, OSError, ZeroDivisionError):
        return None
    return value if value is not None and math.isfinite(value) and 4 <= value <= 2000 else None


def _check_not_a_stub(path: Path) -> None:
    """Pillow recognizes some data formats by their signature (HDF5, GRIB, BUFR) as "stub" images of 0x0 pixels
    it cannot decode: such a file is refused as not an image, not by the size check as an empty one."""
    import warnings

    from PIL import Image, ImageFile

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                fmt, stub = im.format, isinstance(im, ImageFile.StubImageFile) or 0 in im.size
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):
        return  # missing, unreadable, not an image at all or too large: image_size words each
    if stub:
        raise ToolkitError(f"photo {path}: not a readable image ({fmt} data, not a picture)")


def load_photo(path: str | os.PathLike) -> Photo:
    """Decode a photo (JPEG, PNG or anything Pillow reads) upright as 8-bit BGR. Not an image, a truncated or
    corrupt file, an image over ``toolkit.images.MAX_IMAGE_PIXELS``: a ToolkitError naming the file."""
    import warnings

    from PIL import Image, ImageOps

    from toolkit.images import image_size
    from toolkit.limits import check_allocation

    path = Path(path)
    _check_not_a_stub(path)
    h, w = image_size(path, "photo")  # the header alone: a decompression bomb is refused before decoding
    check_allocation(h * w * 12, f"photo {path} ({w}x{h} pixels)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's warnings about odd EXIF data: the photo itself is fine
            with Image.open(path) as im:
                im.load()  # a truncated file fails here, not later
                focal = _focal_35mm(im)
                upright = ImageOps.exif_transpose(im)
                rgb = _to_rgb8(upright, path)
    except ToolkitError:
        raise
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        why = "truncated or corrupt" if "truncated" in str(e) or isinstance(e, SyntaxError) else e.__class__.__name__
        raise ToolkitError(f"photo {path}: not a readable image ({why}: {str(e)[:80]})") from None
    return Photo(path, np.ascontiguousarray(rgb[..., ::-1]), focal)


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
