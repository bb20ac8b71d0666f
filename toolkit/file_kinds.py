"""What a file is by its first bytes, for files a photo reader meets that are not photos it can decode: HEIC / HEIF /
AVIF stills (decodable with the right plugin), videos and camera raw files. Each is named as what it is, with the way
out, rather than as "not an image"; a camera raw file Pillow would open as a TIFF (its small embedded preview) is
refused rather than read as the photo.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

HEIF_BRANDS = {b"heic": "HEIC", b"heix": "HEIC", b"hevc": "HEIC", b"heim": "HEIC", b"heis": "HEIC",
               b"mif1": "HEIF", b"msf1": "HEIF", b"avif": "AVIF", b"avis": "AVIF"}
"""ISO base media file brands (bytes 8-12, after ``ftyp``; ISO/IEC 14496-12 section 4.3) of still-image formats."""

VIDEO_BRANDS = {b"isom", b"iso2", b"iso4", b"iso5", b"iso6", b"mp41", b"mp42", b"avc1", b"qt  ", b"M4V ", b"M4VH",
                b"M4VP", b"3gp4", b"3gp5", b"3gp6", b"3g2a", b"mmp4", b"MSNV", b"dash", b"f4v ", b"XAVC"}
"""ISO base media file brands of videos (MP4, MOV, 3GP, Sony's XAVC), from the MP4 registration authority's list."""

RAW_SUFFIXES = {s: s[1:].upper() for s in (".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2",
                                           ".raf", ".orf", ".rw2", ".pef", ".srw", ".x3f", ".3fr", ".iiq", ".erf",
                                           ".mrw", ".kdc", ".dcr", ".rwl", ".mos", ".mef", ".fff")}
"""Camera raw files by name: most are TIFF files whose first image is a small preview."""

DNG_VERSION_TAG = 0xC612
"""TIFF tag DNGVersion (Adobe's DNG specification 1.4, section "DNGVersion"): present in every DNG's first IFD."""


NEW_SUBFILE_TYPE_TAG, SUB_IFDS_TAG = 0x00FE, 0x014A
"""TIFF tags NewSubfileType (bit 0: a reduced-resolution version of another image) and SubIFDs (TIFF 6.0 and its
Technical Note 1): a first image that is a reduced version, with the others in sub-IFDs, is a raw file's preview."""


def file_head(path: str | os.PathLike, n: int = 12) -> bytes:
    """The first ``n`` bytes of a regular file (fewer for a shorter one; none for one that cannot be read, or a pipe
    or device, whose reading could block or consume what its real reader needs)."""
    if not Path(path).is_file():
        return b""
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return b""


def heif_kind(path: str | os.PathLike) -> str | None:
    """"HEIC" / "HEIF" / "AVIF" when the file starts as one (an ``ftyp`` box of those brands), else None."""
    head = file_head(path)
    return HEIF_BRANDS.get(head[8:12]) if len(head) == 12 and head[4:8] == b"ftyp" else None


def video_kind(path: str | os.PathLike) -> str | None:
    """"an MP4 / MOV video", "an AVI video" or "a Matroska / WebM video" when the file starts as one (whatever its
    name), else None."""
    head = file_head(path)
    if head[4:8] == b"ftyp" and head[8:12] in VIDEO_BRANDS:
        return "an MP4 / MOV video"
    if head[:4] == b"RIFF" and head[8:12] == b"AVI ":
        return "an AVI video"
    return "a Matroska / WebM video" if head[:4] == b"\x1aE\xdf\xa3" else None


def raw_kind(path: str | os.PathLike, tiff_tags: Mapping[int, object] | None = None) -> str | None:
    """The camera raw format of a file ("CR3", "CR2", "DNG", "NEF", ...) by its signature (CR3's ``ftyp crx``,
    CR2's header: a TIFF header, its first IFD at 16, then "CR" and major version 2), the tags of a TIFF's first
    IFD when the caller has it open (``tiff_tags``: DNGVersion, or a preview with sub-IFDs) or its name
    (:data:`RAW_SUFFIXES`), else None."""
    head = file_head(path)
    if head[4:12] == b"ftypcrx ":
        return "CR3"
    if head[:11] == b"II*\x00\x10\x00\x00\x00CR\x02":  # the whole CR2 header: a TIFF's pixels may start "CR"
        return "CR2"
    if tiff_tags is not None and DNG_VERSION_TAG in tiff_tags:
        return "DNG"
    if tiff_tags is not None and int(tiff_tags.get(NEW_SUBFILE_TYPE_TAG, 0)) & 1 and SUB_IFDS_TAG in tiff_tags:
        return "a preview first, the image in a sub-IFD"  # a NEF, ARW, PEF ... under another name
    return RAW_SUFFIXES.get(Path(path).suffix.lower())
