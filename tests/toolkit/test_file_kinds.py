"""Files a photo reader meets that are not photos it can decode, known by their first bytes: videos, camera raw
files (which Pillow would otherwise open as a TIFF and read their small preview as the photo)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image, TiffImagePlugin

from toolkit.errors import ToolkitError
from toolkit.file_kinds import DNG_VERSION_TAG, raw_kind
from toolkit.images import decode_image, image_size, is_picture


def _dng(path):
    """A DNG as cameras and converters write it: a TIFF whose first IFD, a small RGB preview (NewSubfileType 1),
    carries DNGVersion 1.4.0.0 (Adobe's DNG specification 1.4, "DNGVersion" and "NewSubFileType")."""
    tags = TiffImagePlugin.ImageFileDirectory_v2()
    tags[DNG_VERSION_TAG] = (1, 4, 0, 0)
    tags[0x00FE] = 1
    tags[0x010F] = "Canon"
    Image.fromarray(np.full((171, 256, 3), 90, np.uint8)).save(path, format="TIFF", tiffinfo=tags)
    return path


RAW_LINE = r"^photo \S*{}: a camera raw file \({}\), whose first image is at most a preview; develop it to JPEG"


def test_a_dng_is_refused_whatever_its_name_not_read_as_its_preview(tmp_path):
    for name in ("IMG_0001.DNG", "IMG_0002.tif"):
        path = _dng(tmp_path / name)
        assert is_picture(path)
        for read in (decode_image, image_size):
            with pytest.raises(ToolkitError, match=RAW_LINE.format(name.replace(".", r"\."), "DNG")):
                read(path, "photo")


def test_canon_raw_signatures_and_raw_names_are_refused(tmp_path):
    """CR2: "CR", major version 2 after the TIFF header (bytes 8-10); CR3: an ISO base media file of brand
    ``crx ``; a NEF (a TIFF whose first image is a 160x120 preview) by its name."""
    files = {"a.cr2": b"II*\x00\x10\x00\x00\x00CR\x02\x00\x00\x00\x00\x00" + bytes(64),
             "b.bin": b"\x00\x00\x00\x18ftypcrx \x00\x00\x00\x01crx isom" + bytes(64)}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    Image.fromarray(np.zeros((120, 160, 3), np.uint8)).save(tmp_path / "c.NEF", format="TIFF")
    for name, kind in (("a.cr2", "CR2"), ("b.bin", "CR3"), ("c.NEF", "NEF")):
        assert raw_kind(tmp_path / name) == kind and is_picture(tmp_path / name)
        with pytest.raises(ToolkitError, match=RAW_LINE.format(name.replace(".", r"\."), kind)):
            decode_image(tmp_path / name, "photo")


def test_a_plain_tiff_is_a_photo(tmp_path):
    pixels = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "scan.tif")
    assert raw_kind(tmp_path / "scan.tif") is None
    np.testing.assert_array_equal(decode_image(tmp_path / "scan.tif")[0], pixels)


def test_a_libtiff_tiff_whose_pixels_start_cr_is_a_photo(tmp_path, monkeypatch):
    """libtiff writes the pixels before the IFD: an uncompressed TIFF's bytes 8-9 are its first pixel, here "CR"
    (67, 82); only the whole CR2 header (first IFD at 16, "CR", version 2) marks a Canon raw."""
    monkeypatch.setattr(TiffImagePlugin, "WRITE_LIBTIFF", True)
    pixels = np.full((4, 4, 3), 9, np.uint8)
    pixels[0, 0] = (67, 82, 0)
    Image.fromarray(pixels).save(tmp_path / "scan.tif", compression="raw")
    assert (tmp_path / "scan.tif").read_bytes()[8:10] == b"CR"
    assert raw_kind(tmp_path / "scan.tif") is None
    np.testing.assert_array_equal(decode_image(tmp_path / "scan.tif")[0], pixels)


def test_a_raw_under_a_tiff_name_is_known_by_its_preview_and_sub_ifds(tmp_path):
    """A NEF renamed .tif: its first image is flagged a reduced-resolution version (NewSubfileType bit 0) and the
    others hang off SubIFDs (TIFF 6.0 Technical Note 1), as Nikon's and Sony's raws are laid out."""
    tags = TiffImagePlugin.ImageFileDirectory_v2()
    tags[0x00FE] = 1
    tags[0x014A] = (0,)
    tags.tagtype[0x014A] = 4  # LONG offsets
    tags[0x010F] = "NIKON CORPORATION"
    Image.fromarray(np.zeros((120, 160, 3), np.uint8)).save(tmp_path / "DSC_0001.tif", format="TIFF", tiffinfo=tags)
    with pytest.raises(ToolkitError, match=r"a camera raw file \(a preview first, the image in a sub-IFD\)"):
        decode_image(tmp_path / "DSC_0001.tif", "photo")
