"""Photos as phones and cameras write them: ICC colour profiles other than sRGB, and HEIC files.

The wide-gamut profiles are built byte by byte from the ICC v2 specification (``benchmarks.images.matrix_profile``
cites its sections); the expected sRGB values come from the colour-science definitions alone (``expected_srgb``: the
primaries' matrices and IEC 61966-2-1's sRGB curve), independently of littlecms.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from benchmarks.images import P3, SRGB, d65_to_d50, expected_srgb, matrix_profile
from toolkit.colour import rgb_to_xyz, srgb_encode
from toolkit.errors import ToolkitError
from toolkit.images import decode_image

# Colours inside both gamuts (no clipping), a grey ramp and the corners' neighbours.
COLOURS = np.array([[200, 100, 50], [60, 140, 90], [128, 128, 128], [30, 30, 200], [240, 220, 180], [90, 40, 120]],
                   np.uint8)


@pytest.mark.parametrize("fmt", ["jpeg", "png", "tiff", "webp"])
def test_a_display_p3_photo_is_converted_to_srgb(tmp_path, fmt):
    icc = matrix_profile(d65_to_d50() @ P3, 2.2, "Display P3 (test)")
    pixels = np.repeat(COLOURS[None], 4, 0)
    path = tmp_path / f"p3.{fmt}"
    Image.fromarray(pixels).save(path, icc_profile=icc, **({"quality": 100} if fmt in ("jpeg", "webp") else {}))
    stored = np.asarray(Image.open(path).convert("RGB"))[0].astype(float)  # a lossy format's own rounding
    rgb, _ = decode_image(path)
    assert rgb.dtype == np.uint8
    np.testing.assert_allclose(rgb[0], expected_srgb(stored, 2.2, P3), atol=2)
    assert np.abs(rgb[0].astype(float) - stored).max() > 8  # a wide-gamut photo read as sRGB would be this far off


def test_a_linear_srgb_profile_is_encoded_with_the_srgb_curve(tmp_path):
    icc = matrix_profile(d65_to_d50() @ SRGB, 1.0, "linear primaries (test)")
    path = tmp_path / "linear.png"
    Image.fromarray(np.repeat(COLOURS[None], 2, 0)).save(path, icc_profile=icc)
    rgb, _ = decode_image(path)
    np.testing.assert_allclose(rgb[0], np.rint(srgb_encode(COLOURS / 255.0) * 255.0), atol=2)


def test_untagged_srgb_tagged_and_broken_profiles_leave_the_pixels_as_stored(tmp_path):
    from PIL import ImageCms

    pixels = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    for name, icc in [("none", None), ("srgb", srgb), ("broken", b"not a profile" * 20)]:
        path = tmp_path / f"{name}.png"
        Image.fromarray(pixels).save(path, **({"icc_profile": icc} if icc else {}))
        rgb, _ = decode_image(path)
        np.testing.assert_array_equal(rgb, pixels, err_msg=name)


def test_srgb_is_known_by_its_colours_not_its_name(tmp_path):
    """littlecms's own sRGB profile renamed keeps the pixels as stored; a linear profile named sRGB is converted."""
    from PIL import ImageCms

    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    renamed = srgb.replace("sRGB built-in".encode("utf-16-be"), "c2 (a web tool)".encode("utf-16-be")[:26])
    assert renamed != srgb
    linear = matrix_profile(d65_to_d50() @ SRGB, 1.0, "sRGB linear")
    pixels = np.repeat(COLOURS[None], 2, 0)
    for name, icc in [("renamed", renamed), ("linear", linear)]:
        Image.fromarray(pixels).save(tmp_path / f"{name}.png", icc_profile=icc)
    np.testing.assert_array_equal(decode_image(tmp_path / "renamed.png")[0], pixels)
    np.testing.assert_allclose(decode_image(tmp_path / "linear.png")[0][0],
                               np.rint(srgb_encode(COLOURS / 255.0) * 255.0), atol=2)


def test_alpha_palette_and_a_transparent_colour_survive_the_conversion(tmp_path):
    icc = matrix_profile(d65_to_d50() @ P3, 2.2, "Display P3 (test)")
    want = expected_srgb(COLOURS.astype(float), 2.2, P3)
    rgba = np.concatenate([np.repeat(COLOURS[None], 2, 0), np.full((2, len(COLOURS), 1), 255, np.uint8)], -1)
    rgba[1, 0, 3] = 0  # one transparent pixel: white once composited
    Image.fromarray(rgba).save(tmp_path / "rgba.png", icc_profile=icc)
    got = decode_image(tmp_path / "rgba.png")[0]
    np.testing.assert_allclose(got[0], want, atol=2)
    assert (got[1, 0] == 255).all()
    Image.fromarray(np.repeat(COLOURS[None], 2, 0)).quantize(8).save(tmp_path / "palette.png", icc_profile=icc)
    np.testing.assert_allclose(decode_image(tmp_path / "palette.png")[0][0], want, atol=2)
    key = np.repeat(COLOURS[None], 2, 0)
    key[1, 0] = (1, 2, 3)
    Image.fromarray(key).save(tmp_path / "trns.png", icc_profile=icc, transparency=(1, 2, 3))  # a tRNS colour
    got = decode_image(tmp_path / "trns.png")[0]
    assert (got[1, 0] == 255).all()
    np.testing.assert_allclose(got[0], want, atol=2)


ICC_DIR = Path("/usr/share/color/icc")  # Debian's icc-profiles-free, which `make setup` installs


@pytest.mark.parametrize("name", ["compatibleWithAdobeRGB1998.icc", "sRGB.icc"])
def test_profiles_as_distributed_are_read(tmp_path, name):
    """Profiles as cameras and editors embed them, not built here: Adobe RGB (1998) (primaries (0.64, 0.33),
    (0.21, 0.71), (0.15, 0.06), D65, gamma 563/256, its specification) is converted to the formulas' sRGB; a v4
    sRGB profile is known as sRGB and leaves the pixels as stored."""
    if not (ICC_DIR / name).is_file():
        pytest.skip(f"{ICC_DIR / name} is not installed (Debian package icc-profiles-free)")
    pixels = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "photo.png", icc_profile=(ICC_DIR / name).read_bytes())
    rgb, _ = decode_image(tmp_path / "photo.png")
    if name == "sRGB.icc":
        np.testing.assert_array_equal(rgb, pixels)
        return
    adobe = rgb_to_xyz([(0.64, 0.33), (0.21, 0.71), (0.15, 0.06)])
    linear = (pixels / 255.0) ** (563 / 256) @ (np.linalg.inv(SRGB) @ adobe).T
    inside = ((linear >= 0) & (linear <= 1)).all(-1)  # out of sRGB's gamut the intent decides: not compared
    assert inside.mean() > 0.3
    want = expected_srgb(pixels.astype(float), 563 / 256, adobe)
    assert np.abs(rgb.astype(float) - want)[inside].max() <= 2


def test_the_test_colour_spaces_are_the_published_ones():
    """The fixtures' matrices against published values, so that an error they share cannot cancel out: Display
    P3's RGB -> XYZ (D65) and its D50-adapted colorants as Apple's profile stores them (rXYZ, gXYZ, bXYZ)."""
    np.testing.assert_allclose(P3[0], [0.48657, 0.26567, 0.19822], atol=2e-4)
    np.testing.assert_allclose(SRGB[0], [0.41239, 0.35758, 0.18048], atol=2e-4)
    np.testing.assert_allclose((d65_to_d50() @ P3)[:, 0], [0.5151, 0.2412, -0.0011], atol=2e-3)


def test_an_exif_turned_p3_photo_is_turned_and_converted(tmp_path):
    icc = matrix_profile(d65_to_d50() @ P3, 2.2, "Display P3 (test)")
    pixels = np.zeros((4, 6, 3), np.uint8)
    pixels[:, :] = COLOURS[0]
    pixels[0, 0] = COLOURS[1]
    exif = Image.Exif()
    exif[0x0112] = 6  # stored turned: shown turned 90 degrees clockwise
    path = tmp_path / "turned.png"
    Image.fromarray(pixels).save(path, icc_profile=icc, exif=exif.tobytes())
    rgb, _ = decode_image(path)
    assert rgb.shape == (6, 4, 3)
    np.testing.assert_allclose(rgb[0, -1], expected_srgb(COLOURS[1].astype(float), 2.2, P3), atol=2)


@pytest.fixture
def heic_writer():
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif (the 'photos' extra) is not installed")
    return pillow_heif


def test_a_heic_photo_decodes_upright(tmp_path, heic_writer):
    from PIL import ImageOps

    pixels = np.full((40, 60, 3), 30, np.uint8)
    pixels[:10, :20] = 230  # a bright block at the top left as stored
    image = Image.fromarray(pixels)
    exif = Image.Exif()
    exif[0x0112] = 6
    path = tmp_path / "IMG_0001.HEIC"
    heic_writer.from_pillow(image).save(path, quality=-1, exif=exif.tobytes())  # lossless, turned like a phone's
    rgb, _ = decode_image(path, "photo")
    want = np.asarray(ImageOps.exif_transpose(_with_orientation(image, 6)))
    assert rgb.shape == want.shape == (60, 40, 3)
    assert np.abs(rgb.astype(int) - want).max() <= 6  # HEVC's chroma rounding
    assert rgb[:5, -5:].min() > 200 and rgb[-5:, :5].max() < 60


def _with_orientation(image: Image.Image, orientation: int) -> Image.Image:
    exif = Image.Exif()
    exif[0x0112] = orientation
    copy = image.copy()
    copy.info["exif"] = exif.tobytes()
    return copy


def test_a_damaged_heic_is_named_as_one_when_pillow_heif_reads_heic(tmp_path, heic_writer):
    path = tmp_path / "IMG_0002.HEIC"
    heic_writer.from_pillow(Image.new("RGB", (32, 24), (90, 120, 30))).save(path, quality=-1)
    path.write_bytes(path.read_bytes()[:-40])  # cut short, as an interrupted copy
    with pytest.raises(ToolkitError, match=r"^photo \S*IMG_0002\.HEIC: not a readable HEIC image \("):
        decode_image(path, "photo")


def test_a_display_p3_heic_is_converted_to_srgb(tmp_path, heic_writer):
    icc = matrix_profile(d65_to_d50() @ P3, 2.2, "Display P3 (test)")
    path = tmp_path / "IMG_0003.HEIC"
    heic_writer.from_pillow(Image.fromarray(np.repeat(COLOURS[None], 16, 0).repeat(4, 1))).save(
        path, quality=-1, icc_profile=icc)
    rgb, _ = decode_image(path, "photo")
    stored = np.asarray(Image.open(path).convert("RGB"))[8, 2::4].astype(float)  # HEVC's own rounding
    np.testing.assert_allclose(rgb[8, 2::4], expected_srgb(stored, 2.2, P3), atol=2)
