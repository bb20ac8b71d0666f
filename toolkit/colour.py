"""Colour spaces by their primaries: RGB -> XYZ matrices, Bradford adaptation, the sRGB transfer curve, and the
conversion of an image coded in other primaries (a HEIC's ``nclx`` colour box: ITU-T H.273 code points) to sRGB.

An image tagged with an ICC profile is converted by littlecms (``toolkit.images.to_srgb``); this module serves the
images that say their colour space by code points instead, and the tests that check both against the formulas.
"""

from __future__ import annotations

import numpy as np

D65_XY = (0.3127, 0.3290)
"""CIE D65's chromaticity, the white of sRGB, Display P3 and BT.2020."""
BRADFORD = np.array([[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]])
"""Bradford's cone response matrix (ICC.1 Annex E), for chromatic adaptation between whites."""
SRGB_PRIMARIES = ((0.640, 0.330), (0.300, 0.600), (0.150, 0.060))
"""sRGB's (and BT.709's) red, green, blue chromaticities (IEC 61966-2-1)."""
SRGB_TRANSFER = 13
"""ITU-T H.273 TransferCharacteristics of IEC 61966-2-1's sRGB curve: the only one converted here (an HDR or a
video curve is left as it is)."""


ENCODE_STEPS = 1 << 16
"""Linear-light steps of the table :func:`nclx_to_srgb` encodes with."""
CHUNK_PIXELS = 1 << 20
"""Pixels converted at a time by :func:`nclx_to_srgb` (~50 MB of float32 work arrays)."""


def xy_to_xyz(xy) -> np.ndarray:
    """A chromaticity (x, y) -> XYZ with Y = 1."""
    x, y = xy
    return np.array([x / y, 1.0, (1.0 - x - y) / y])


def rgb_to_xyz(primaries_xy, white_xy=D65_XY) -> np.ndarray:
    """The [3, 3] linear RGB -> XYZ matrix of red, green, blue chromaticities ``primaries_xy`` under the white
    ``white_xy`` (columns: the primaries' XYZ, scaled so that RGB (1, 1, 1) is the white at Y = 1)."""
    columns = np.stack([xy_to_xyz(p) for p in primaries_xy], 1)
    return columns * np.linalg.solve(columns, xy_to_xyz(white_xy))


def bradford(src_white_xyz, dst_white_xyz) -> np.ndarray:
    """The [3, 3] XYZ -> XYZ matrix adapting colours seen under ``src_white_xyz`` to ``dst_white_xyz``."""
    cone_src, cone_dst = BRADFORD @ np.asarray(src_white_xyz), BRADFORD @ np.asarray(dst_white_xyz)
    return np.linalg.inv(BRADFORD) @ np.diag(cone_dst / cone_src) @ BRADFORD


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1's sRGB curve, linear [0, 1] (clipped) -> encoded [0, 1]."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """The inverse of :func:`srgb_encode`: encoded [0, 1] -> linear [0, 1]."""
    return np.where(encoded <= 0.04045, encoded / 12.92, np.power((encoded + 0.055) / 1.055, 2.4))


def primaries_to_srgb(primaries_xy, white_xy=D65_XY) -> np.ndarray:
    """The [3, 3] linear RGB (``primaries_xy`` under ``white_xy``) -> linear sRGB matrix, whites adapted by
    Bradford."""
    to_d65 = bradford(xy_to_xyz(white_xy), xy_to_xyz(D65_XY))
    return np.linalg.inv(rgb_to_xyz(SRGB_PRIMARIES)) @ to_d65 @ rgb_to_xyz(primaries_xy, white_xy)


def nclx_to_srgb(rgb: np.ndarray, nclx: dict) -> np.ndarray:
    """[H, W, 3] uint8 coded in the primaries of an ``nclx`` box (pillow-heif's ``info["nclx_profile"]``: the
    ``color_primary_*_x/_y`` chromaticities and ``transfer_characteristics``) -> [H, W, 3] uint8 sRGB. ``rgb``
    itself, unchanged, when the curve is not sRGB's (:data:`SRGB_TRANSFER`), the primaries are sRGB's within
    0.001 (most HEIC files: BT.709 primaries) or the chromaticities span no colour space (a damaged box)."""
    keys = [f"color_primary_{c}_{a}" for c in ("red", "green", "blue", "white") for a in ("x", "y")]
    if nclx.get("transfer_characteristics") != SRGB_TRANSFER or not all(k in nclx for k in keys):
        return rgb
    xy = np.array([nclx[k] for k in keys], np.float64).reshape(4, 2)
    if np.abs(xy - np.array([*SRGB_PRIMARIES, D65_XY])).max() < 1e-3:
        return rgb
    if not (np.isfinite(xy).all() and (xy[:, 1] > 0).all()):
        return rgb  # a damaged box: the pixels as coded, as a viewer without colour management shows them
    try:
        matrix = primaries_to_srgb(xy[:3], xy[3]).T.astype(np.float32)
    except np.linalg.LinAlgError:  # primaries on one line span no colour space
        return rgb
    if not np.isfinite(matrix).all():
        return rgb
    levels = srgb_decode(np.arange(256) / 255.0).astype(np.float32)  # linear light of each 8-bit level
    # Encoding by a table over 2^16 linear steps, not pow() per value: twice as fast; of all 2^24 colours 0.13 %
    # differ from the float64 formula, by one level.
    encode = np.rint(srgb_encode(np.arange(ENCODE_STEPS) / (ENCODE_STEPS - 1)) * 255.0).astype(np.uint8)
    flat, out = rgb.reshape(-1, 3), np.empty(rgb.size, np.uint8).reshape(-1, 3)
    for start in range(0, len(flat), CHUNK_PIXELS):  # float32 work memory bounded whatever the photo's size
        part = slice(start, start + CHUNK_PIXELS)
        linear = np.clip(levels[flat[part]] @ matrix, 0.0, 1.0)
        out[part] = encode[np.rint(linear * (ENCODE_STEPS - 1)).astype(np.int32)]
    return out.reshape(rgb.shape)
