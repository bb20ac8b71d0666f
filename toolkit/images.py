"""Bounded image reading: a file's pixel size is read from its header before anything is decoded, and every
image the project reads is decoded one way (:func:`decode_image`).

A small PNG can declare 20000 x 20000 pixels (a 389 KB file decoding to 1.2 GB); :func:`image_size` reads the
header alone (Pillow opens lazily) and :func:`decode_image` / :func:`read_image` refuse, before decoding, an image
above :data:`MAX_IMAGE_PIXELS` or what :func:`toolkit.limits.check_allocation` allows.

Decoding (Pillow): the EXIF orientation applied (``ImageOps.exif_transpose``: a phone photo stored sideways comes
out upright); an RGB or palette photo tagged with an ICC colour profile other than sRGB (Display P3, Adobe RGB)
converted to sRGB; grey, 16-bit (scaled by 255/65535), palette, CMYK and YCbCr become 8-bit RGB; alpha is
composited on white (on black for a grey mask, :func:`read_image` with ``gray``); a multi-frame file gives its
first frame. HEIC / HEIF photos (an iPhone's default) decode through pillow-heif, part of the ``photos`` extra; one
whose colour space is given as ``nclx`` code points is converted by ``toolkit.colour.nclx_to_srgb``.
Camera raw files and videos are refused, named as what they are (``toolkit.file_kinds``).
"""

from __future__ import annotations

import functools
import os
import struct
from pathlib import Path

import numpy as np

from toolkit.colour import nclx_to_srgb
from toolkit.errors import ToolkitError
from toolkit.file_kinds import heif_kind, raw_kind, video_kind
from toolkit.limits import check_allocation

MAX_IMAGE_PIXELS = 64 * 1024 * 1024
"""Largest image read, in pixels (a 8192 x 8192 photo): above that an input is a mistake or a decompression bomb."""

EXIF_IFD = 0x8769
"""The EXIF sub-IFD (exposure, focal length, ...) of an image's EXIF data."""

_heif_opener_registered = False


def _open_heif_with_pillow_heif(path: Path) -> None:
    """Teach Pillow HEIC / HEIF through pillow-heif (the ``photos`` extra) when ``path`` is one and pillow-heif is
    installed; imported here, on the first such file, so that nothing else pays for it."""
    global _heif_opener_registered
    if _heif_opener_registered or heif_kind(path) not in ("HEIC", "HEIF"):
        return
    try:
        import pillow_heif
    except ImportError:
        return  # the file is then named as a HEIC Pillow cannot decode, with the extra to install
    pillow_heif.register_heif_opener()
    _heif_opener_registered = True


def _has_decoder(kind: str) -> bool:
    """Whether this Pillow decodes ``kind`` ("HEIC" / "HEIF" / "AVIF"): a file of it that fails is then damaged."""
    from PIL import features

    return _heif_opener_registered if kind != "AVIF" else bool(features.check("avif"))


def _unreadable(what: str, path: Path, why: str) -> ToolkitError:
    if path.is_file() and path.stat().st_size == 0:  # a copy or a download that failed
        return ToolkitError(f"{what} {path}: an empty file (0 bytes), expected an image (JPEG, PNG, TIFF, WebP, HEIC)")
    kind = heif_kind(path)
    if kind is not None and not _has_decoder(kind):
        way = ("install the 'photos' extra (pip install -e '.[photos]', which brings pillow-heif) or convert it"
               if kind != "AVIF" else "upgrade Pillow (>= 11.2 reads AVIF) or convert it")
        return ToolkitError(f"{what} {path}: a {kind} image, which the installed Pillow cannot decode; {way} to "
                            "JPEG or PNG (e.g. `heif-convert` or any photo viewer's export)")
    if (raw := raw_kind(path)) is not None:
        return _raw_error(what, path, raw)
    if (video := video_kind(path)) is not None:
        return ToolkitError(f"{what} {path}: {video}, not a picture; extract its frames first (e.g. `mkdir frames && "
                            f"ffmpeg -i '{path.name}' -vf fps=2 frames/%05d.png`) and give the folder of frames")
    return ToolkitError(f"{what} {path}: not a readable {kind + ' ' if kind else ''}image ({why})")


def _raw_error(what: str, path: Path, raw: str) -> ToolkitError:
    """A camera raw file: refused, since what Pillow reads of it is at most its preview."""
    return ToolkitError(f"{what} {path}: a camera raw file ({raw}), whose first image is at most a preview; develop it "
                        "to JPEG, PNG or 16-bit TIFF first (e.g. `darktable-cli`, `rawtherapee-cli` or the camera "
                        "maker's software)")


def _srgb_probe() -> "np.ndarray":
    """[1, 1024 + 729, 3] uint8: every grey level, each primary's 256 levels, and a 9-level grid of every channel."""
    ramp = np.arange(256, dtype=np.uint8)
    zero = np.zeros_like(ramp)
    ramps = [np.stack(c, -1) for c in ((ramp, ramp, ramp), (ramp, zero, zero), (zero, ramp, zero), (zero, zero, ramp))]
    grid = np.stack(np.meshgrid(*[np.linspace(0, 255, 9).astype(np.uint8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return np.concatenate([*ramps, grid])[None]


SRGB_TOLERANCE = 1
"""A profile whose conversion to sRGB moves no colour of :func:`_srgb_probe` by more than this many 8-bit levels is
sRGB (one of its many variants): the pixels are kept as stored."""


@functools.lru_cache(maxsize=8)
def _transform_to_srgb(icc: bytes):
    """littlecms's RGB -> sRGB transform of an ICC profile, or None when the profile is sRGB by content
    (:data:`SRGB_TOLERANCE`). Cached: a folder of one phone's photos carries one profile, built and probed once."""
    import io

    from PIL import Image, ImageCms

    transform = ImageCms.buildTransform(ImageCms.ImageCmsProfile(io.BytesIO(icc)), ImageCms.createProfile("sRGB"),
                                        "RGB", "RGB")
    probe = _srgb_probe()
    moved = np.asarray(ImageCms.applyTransform(Image.fromarray(probe), transform), np.int16) - probe
    return None if np.abs(moved).max() <= SRGB_TOLERANCE else transform


def to_srgb(im):
    """A Pillow RGB / RGBA / palette image tagged with an RGB ICC colour profile (``info["icc_profile"]``) converted
    to sRGB (littlecms through ``PIL.ImageCms``, perceptual intent; a palette or a transparent colour becomes RGB /
    RGBA first): a Display P3 or Adobe RGB photo read as if it were sRGB looks dull and its written-out redirections
    would too. Untagged, sRGB by content (:data:`SRGB_TOLERANCE`, whatever the profile's name), other modes, or a
    profile littlecms cannot use (grey, CMYK, broken): ``im`` itself, its pixels untouched."""
    from PIL import ImageCms

    icc = im.info.get("icc_profile")
    if not icc or im.mode not in ("RGB", "RGBA", "P", "PA"):
        return im
    try:
        transform = _transform_to_srgb(bytes(icc))
        if transform is None:
            return im
        # A palette or a transparent colour: to RGB(A) first, since the conversion would change the key colour.
        alpha = im.mode in ("RGBA", "PA") or "transparency" in im.info
        rgb = im.convert("RGBA" if alpha else "RGB")
        if not alpha:
            return ImageCms.applyTransform(rgb, transform)
        out = ImageCms.applyTransform(rgb.convert("RGB"), transform).convert("RGBA")
        out.putalpha(rgb.getchannel("A"))
        return out
    except (OSError, ValueError, TypeError, ImageCms.PyCMSError):
        return im  # a profile littlecms cannot use: the pixels as stored, as any viewer without colour management


def image_size(path: str | os.PathLike, what: str = "image") -> tuple[int, int]:
    """(height, width) of an image file from its header, nothing decoded, as stored (before any EXIF turn); a
    one-line ``ToolkitError`` naming ``what`` and the file when it is missing, unreadable, a data format Pillow
    recognizes by its signature but cannot decode (a "stub" image of 0x0 pixels: HDF5, GRIB, BUFR) or larger than
    :data:`MAX_IMAGE_PIXELS`."""
    import warnings

    from PIL import Image, ImageFile

    path = Path(path)
    if not path.is_file():
        raise ToolkitError(f"{what} {path}: no such file")
    _open_heif_with_pillow_heif(path)
    limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # Pillow's own bomb check: the one below words it
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                (w, h), fmt, stub = im.size, im.format, isinstance(im, ImageFile.StubImageFile)
                raw = raw_kind(path, im.tag_v2) if fmt == "TIFF" else None  # a TIFF-based raw: its preview
    except (OSError, ValueError, SyntaxError) as e:
        raise _unreadable(what, path, e.__class__.__name__) from None
    finally:
        Image.MAX_IMAGE_PIXELS = limit
    if raw is not None:
        raise _raw_error(what, path, raw)
    if stub or 0 in (w, h):
        raise ToolkitError(f"{what} {path}: not a readable image ({fmt} data, not a picture)")
    if w < 1 or h < 1 or w * h > MAX_IMAGE_PIXELS:
        raise ToolkitError(f"{what} {path}: {w}x{h} pixels (width x height); expected at most {MAX_IMAGE_PIXELS} "
                           f"pixels" + ("; downscale it (e.g. to 8000 pixels on the longer side)" if w and h else ""))
    return h, w


def is_picture(path: str | os.PathLike) -> bool:
    """Whether a file is a picture by its content (whatever its name): Pillow identifies it as an image with
    pixels, or it is a HEIC / HEIF / AVIF file or a camera raw file (``toolkit.file_kinds``: the reader names
    those). Nothing is decoded."""
    import warnings

    from PIL import Image, ImageFile

    path = Path(path)
    if not path.is_file():
        return False
    if heif_kind(path) is not None or raw_kind(path) is not None:
        return True
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                return not isinstance(im, ImageFile.StubImageFile) and 0 not in im.size
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):
        return False


def to_rgb8(im, what: str = "image", path: str | os.PathLike = "", *, background: int = 255) -> np.ndarray:
    """A decoded Pillow image of any common mode -> [H, W, 3] uint8 RGB: 16-bit and 32-bit integer grey scaled to
    8 bits (by 255/65535, or by 255/max for 32-bit values above 65535), alpha composited on grey level
    ``background`` (white by default), palette / CMYK / YCbCr / LAB converted; a floating-point image refused."""
    from PIL import Image

    if im.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):  # 16-bit grey (PNG, TIFF) or 32-bit integer grey
        a = np.asarray(im, np.float64)
        top = 255.0 if im.mode == "I" and a.max(initial=0) <= 255 else max(65535.0, a.max(initial=0))
        g = np.clip(np.rint(a * 255.0 / top), 0, 255).astype(np.uint8)
        return np.repeat(g[..., None], 3, -1)
    if im.mode == "F":
        raise ToolkitError(f"{what} {path}: a floating-point image; expected a photo (8- or 16-bit): save it as an "
                           "8-bit JPEG or PNG")
    if im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or (im.mode in ("P", "L", "RGB") and "transparency" in im.info):
        rgba = im.convert("RGBA")
        under = Image.new("RGBA", rgba.size, (background, background, background, 255))
        return np.asarray(Image.alpha_composite(under, rgba).convert("RGB"))
    if im.mode == "LAB":  # Pillow converts LAB to RGB only through a colour profile
        from PIL import ImageCms

        lab, srgb = ImageCms.createProfile("LAB"), ImageCms.createProfile("sRGB")
        return np.asarray(ImageCms.applyTransform(im, ImageCms.buildTransform(lab, srgb, "LAB", "RGB")))
    return np.asarray(im.convert("RGB"))


def decode_image(path: str | os.PathLike, what: str = "image", *, background: int = 255):
    """An image file decoded upright -> ([H, W, 3] uint8 RGB, its EXIF data as Pillow reads it, before the turn).

    The size is checked from the header first (:func:`image_size`); the EXIF orientation is applied, a colour
    profile converted to sRGB (:func:`to_srgb`), every mode becomes 8-bit RGB and alpha is composited on grey
    level ``background`` (:func:`to_rgb8`). Not an image, a
    truncated or corrupt file, a HEIC without pillow-heif (the ``photos`` extra), an image too large: a one-line
    ``ToolkitError`` naming ``what`` and the file."""
    import warnings

    from PIL import Image, ImageOps

    path = Path(path)
    h, w = image_size(path, what)  # the header alone: a decompression bomb is refused before decoding
    check_allocation(h * w * 12, f"{what} {path} ({w}x{h} pixels)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's warnings about odd EXIF data: the image itself is fine
            with Image.open(path) as im:
                im.load()  # a truncated file fails here, not later
                exif = im.getexif()
                try:  # the Exif IFD (focal length, ...) read now, while the file is open
                    exif.get_ifd(EXIF_IFD)
                except (KeyError, ValueError, TypeError, OSError, SyntaxError, struct.error):
                    pass
                upright = to_srgb(ImageOps.exif_transpose(im))  # the turn first: a conversion drops the EXIF
                rgb = to_rgb8(upright, what, path, background=background)
                if "nclx_profile" in upright.info and not upright.info.get("icc_profile"):  # HEIC code points
                    rgb = nclx_to_srgb(rgb, upright.info["nclx_profile"])
    except ToolkitError:
        raise
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        why = "truncated or corrupt" if "truncated" in str(e) or isinstance(e, SyntaxError) else e.__class__.__name__
        raise _unreadable(what, path, f"{why}: {str(e)[:80]}") from None
    return np.ascontiguousarray(rgb), exif


def read_image(path: str | os.PathLike, what: str = "image", *, gray: bool = False) -> np.ndarray:
    """An image file decoded upright by :func:`decode_image` -> [H, W, 3] uint8 BGR, or with ``gray`` [H, W] uint8
    luma (ITU-R 601, as OpenCV's) with alpha composited on black: a mask's transparent part is not the mask."""
    import cv2

    rgb, _ = decode_image(path, what, background=0 if gray else 255)
    if gray:
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(rgb[..., ::-1])
