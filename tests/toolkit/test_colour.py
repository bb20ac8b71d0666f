"""toolkit.colour against published colour-science values, and HEIC files that give their colour space as an nclx
box (ITU-T H.273 code points) instead of an ICC profile."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from toolkit import colour
from toolkit.colour import (
    SRGB_PRIMARIES,
    nclx_to_srgb,
    primaries_to_srgb,
    rgb_to_xyz,
    srgb_decode,
    srgb_encode,
)

P3_PRIMARIES = ((0.680, 0.320), (0.265, 0.690), (0.150, 0.060))
BT2020_PRIMARIES = ((0.708, 0.292), (0.170, 0.797), (0.131, 0.046))
# Linear Display P3 -> linear sRGB as published (CSS Color Module Level 4's conversion code), to seven decimals.
P3_TO_SRGB = np.array([[1.2249402, -0.2249402, 0.0], [-0.0420570, 1.0420570, 0.0], [-0.0196376, -0.0786360, 1.0982736]])


def test_matrices_are_the_published_ones():
    np.testing.assert_allclose(rgb_to_xyz(SRGB_PRIMARIES)[0], [0.4124, 0.3576, 0.1805], atol=1e-4)
    np.testing.assert_allclose(rgb_to_xyz(BT2020_PRIMARIES)[0], [0.6370, 0.1446, 0.1689], atol=1e-4)
    np.testing.assert_allclose(primaries_to_srgb(P3_PRIMARIES), P3_TO_SRGB, atol=2e-6)
    np.testing.assert_allclose(primaries_to_srgb(SRGB_PRIMARIES), np.eye(3), atol=1e-12)


def test_the_srgb_curve_round_trips_and_is_continuous():
    x = np.linspace(0, 1, 10001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)
    knee = 0.0031308
    assert abs(12.92 * knee - (1.055 * knee ** (1 / 2.4) - 0.055)) < 1e-7


def _nclx(primaries, white=colour.D65_XY, transfer=13):
    keys = {}
    for name, xy in zip(("red", "green", "blue", "white"), (*primaries, white)):
        keys[f"color_primary_{name}_x"], keys[f"color_primary_{name}_y"] = xy
    return {"color_primaries": 12, "transfer_characteristics": transfer, **keys}


def test_nclx_primaries_are_converted_and_srgb_ones_left_alone(monkeypatch):
    rgb = np.random.default_rng(0).integers(0, 256, (40, 30, 3), dtype=np.uint8)
    linear = srgb_decode(rgb / 255.0) @ P3_TO_SRGB.T
    inside = ((linear >= 0) & (linear <= 1)).all(-1)
    got = nclx_to_srgb(rgb, _nclx(P3_PRIMARIES))
    assert got.dtype == np.uint8 and got.shape == rgb.shape and inside.mean() > 0.3
    assert np.abs(got.astype(float) - np.rint(srgb_encode(linear) * 255))[inside].max() <= 1
    monkeypatch.setattr(colour, "CHUNK_PIXELS", 7)  # chunks change nothing
    np.testing.assert_array_equal(nclx_to_srgb(rgb, _nclx(P3_PRIMARIES)), got)
    for unchanged in (_nclx(SRGB_PRIMARIES), _nclx(P3_PRIMARIES, transfer=16), {"color_primaries": 12}):
        assert nclx_to_srgb(rgb, unchanged) is rgb  # sRGB's primaries, an HDR curve (PQ), no chromaticities


def test_a_display_p3_heic_without_an_icc_profile_is_converted(tmp_path):
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif (the 'photos' extra) is not installed")
    from toolkit.images import decode_image

    colours = np.array([[200, 100, 50], [60, 140, 90], [128, 128, 128], [90, 40, 120]], np.uint8)
    pixels = np.repeat(np.repeat(colours[None], 8, 0), 8, 1)  # 8-pixel blocks
    path = tmp_path / "IMG_0005.HEIC"  # RGB coded losslessly (matrix 0, 4:4:4), P3 primaries (12), sRGB curve (13)
    pillow_heif.from_pillow(Image.fromarray(pixels)).save(path, quality=-1, chroma=444, color_primaries=12,
                                                          transfer_characteristics=13, matrix_coefficients=0)
    rgb, _ = decode_image(path, "photo")
    want = np.rint(srgb_encode(srgb_decode(colours / 255.0) @ P3_TO_SRGB.T) * 255)
    np.testing.assert_allclose(rgb[4, 4::8], want, atol=1)
    assert np.abs(rgb[4, 4::8].astype(float) - colours).max() > 8  # read as if sRGB it would be this far off


def test_stress_every_level_and_extreme_primaries_stay_finite_and_in_range():
    levels = np.stack(np.meshgrid(*[np.arange(0, 256, 15, dtype=np.uint8)] * 3, indexing="ij"), -1).reshape(1, -1, 3)
    for primaries in (P3_PRIMARIES, BT2020_PRIMARIES, ((0.7347, 0.2653), (0.0, 1.0), (0.0001, -0.077))):
        out = nclx_to_srgb(levels, _nclx(primaries))
        assert out.dtype == np.uint8 and out.shape == levels.shape


def test_a_damaged_nclx_box_leaves_the_pixels_as_coded():
    rgb = np.full((4, 4, 3), 90, np.uint8)
    broken = (((0.64, 0.0), (0.3, 0.6), (0.15, 0.06)),  # y = 0: no luminance
              ((0.2, 0.2), (0.3, 0.3), (0.4, 0.4)),  # on one line: a singular matrix
              ((float("nan"), 0.33), (0.3, 0.6), (0.15, 0.06)))
    for primaries in broken:
        assert nclx_to_srgb(rgb, _nclx(primaries)) is rgb
