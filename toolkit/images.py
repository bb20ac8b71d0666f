"""Bounded image reading: a file's pixel size is read from its header before anything is decoded.

A small PNG can declare 20000 x 20000 pixels (a 389 KB file decoding to 1.2 GB); :func:`image_size` reads the
header alone (Pillow opens lazily) and :func:`read_image` refuses, before decoding, an image above
:data:`MAX_IMAGE_PIXELS` or what :func:`toolkit.limits.check_allocation` allows.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError
from toolkit.limits import check_allocation

MAX_IMAGE_PIXELS = 64 * 1024 * 1024
"""Largest image read, in pixels (a 8192 x 8192 photo): above that an input is a mistake or a decompression bomb."""


def image_size(path: str | os.PathLike, what: str = "image") -> tuple[int, int]:
    """(height, width) of an image file from its header, nothing decoded; a one-line ``ToolkitError`` naming
    ``what`` and the file when it is missing, unreadable or larger than :data:`MAX_IMAGE_PIXELS`."""
    import warnings

    from PIL import Image

    path = Path(path)
    if not path.is_file():
        raise ToolkitError(f"{what} {path}: no such file")
    limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # Pillow's own bomb check: the one below words it
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                w, h = im.size
    except (OSError, ValueError, SyntaxError) as e:
        raise ToolkitError(f"{what} {path}: not a readable image ({e.__class__.__name__})") from None
    finally:
        Image.MAX_IMAGE_PIXELS = limit
    if w < 1 or h < 1 or w * h > MAX_IMAGE_PIXELS:
        raise ToolkitError(f"{what} {path}: {w}x{h} pixels (width x height); expected at most {MAX_IMAGE_PIXELS} "
                           f"pixels")
    return h, w


def read_image(path: str | os.PathLike, what: str = "image", *, gray: bool = False) -> np.ndarray:
    """An image file decoded by OpenCV ([H, W, 3] BGR uint8, or [H, W] with ``gray``), its size checked from the
    header first (:func:`image_size`)."""
    import cv2

    h, w = image_size(path, what)
    check_allocation(h * w * 3 * 2, f"{what} {path} ({w}x{h} pixels)")  # 16-bit files decode to 2 bytes a channel
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise ToolkitError(f"{what} {path}: not a readable image")
    return img
