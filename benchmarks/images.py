"""Photo decoding (``toolkit.images.decode_image``): milliseconds per photo against colour error, for the files
phones and cameras write: JPEG untagged, tagged sRGB (recognized as sRGB, kept as stored) and tagged Display P3
(converted to sRGB), PNG tagged Display P3, and HEIC (through pillow-heif, the ``photos`` extra; left out with a note
when absent) at 1 and 12 megapixels.

    .venv/bin/python benchmarks/images.py                 # 5 repeats
    .venv/bin/python benchmarks/images.py --repeats 2

The photo: a smooth random picture (bicubic upsampling of noise: a photo's spectrum, which HEVC and JPEG compress
as they compress photos). Colour error: mean and max absolute difference in 8-bit levels against what the decoded
pixels should be: the source pixels for untagged and HEIC files (the codec's own loss), and for tagged files the
source's colours converted to sRGB by the colour-science formulas (:func:`expected_srgb`), beside the error of
reading the same file as if it were sRGB. Median of ``--repeats`` after a warm-up.

The Display P3 profile is built byte by byte from the ICC v2 specification (ICC.1:2001-04): the 128-byte header
(section 6.1), the tag table (6.2), XYZType (6.5.26), curveType (6.5.3) and textDescriptionType (6.5.17), with
Display P3's primaries (SMPTE EG 432-1) adapted to the D50 connection space by Bradford (ICC.1 Annex E).
"""

from __future__ import annotations

import struct
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import OUT_DIR, count, format_table, machine_info, save_plot, timeit  # noqa: E402
from toolkit.colour import D65_XY, SRGB_PRIMARIES, bradford, rgb_to_xyz, srgb_encode, xy_to_xyz  # noqa: E402
from toolkit.errors import CliParser, run_cli  # noqa: E402

D50 = np.array([0.9642, 1.0, 0.8249])
"""The ICC profile connection space's illuminant (the header's illuminant field), the white colorants are adapted to."""
P3_PRIMARIES = ((0.680, 0.320), (0.265, 0.690), (0.150, 0.060))
"""Display P3's red, green, blue chromaticities (SMPTE EG 432-1), white D65."""
P3 = rgb_to_xyz(P3_PRIMARIES)
SRGB = rgb_to_xyz(SRGB_PRIMARIES)


def d65_to_d50() -> np.ndarray:
    """Bradford's chromatic adaptation from D65 to the ICC connection space's D50, a 3x3 matrix on XYZ."""
    return bradford(xy_to_xyz(D65_XY), D50)


def _s15(v: float) -> bytes:
    return struct.pack(">i", round(v * 65536))  # s15Fixed16Number


def matrix_profile(rgb_to_xyz_d50: np.ndarray, gamma: float, name: str) -> bytes:
    """An ICC v2 RGB display profile: colorant columns (D50), one pure-gamma tone curve per channel, a name."""
    text = name.encode("ascii") + b"\0"
    desc = b"desc" + bytes(4) + struct.pack(">I", len(text)) + text + bytes(4 + 4 + 2 + 1 + 67)
    xyz = lambda v: b"XYZ " + bytes(4) + b"".join(_s15(c) for c in v)  # noqa: E731
    curve = b"curv" + bytes(4) + struct.pack(">IH", 1, round(gamma * 256)) + bytes(2)  # u8Fixed8 gamma
    tags = [(b"desc", desc), (b"wtpt", xyz(D50)), (b"rXYZ", xyz(rgb_to_xyz_d50[:, 0])),
            (b"gXYZ", xyz(rgb_to_xyz_d50[:, 1])), (b"bXYZ", xyz(rgb_to_xyz_d50[:, 2])),
            (b"rTRC", curve), (b"gTRC", curve), (b"bTRC", curve), (b"cprt", b"text" + bytes(4) + b"none\0\0\0\0")]
    offset, table, body = 128 + 4 + 12 * len(tags), b"", b""
    for sig, data in tags:
        data += bytes(-len(data) % 4)  # every tag starts on a 4-byte boundary
        table += sig + struct.pack(">II", offset + len(body), len(data))
        body += data
    header = (struct.pack(">I", offset + len(body)) + b"none" + bytes([2, 0x10, 0, 0]) + b"mntr" + b"RGB "
              + b"XYZ " + bytes(12) + b"acsp" + bytes(4 + 4 + 4 + 4 + 8) + struct.pack(">I", 0)
              + b"".join(_s15(c) for c in D50) + bytes(4 + 16 + 28))
    return header + struct.pack(">I", len(tags)) + table + body


def display_p3_profile() -> bytes:
    """Display P3's primaries and white, with a pure 2.2 gamma (the real profile's curve is sRGB's)."""
    return matrix_profile(d65_to_d50() @ P3, 2.2, "Display P3 (gamma 2.2)")


def expected_srgb(values: np.ndarray, gamma: float = 2.2, matrix: np.ndarray = P3) -> np.ndarray:
    """8-bit values [..., 3] of a gamma-``gamma`` RGB space of primaries ``matrix`` (D65) -> 8-bit sRGB, rounded."""
    linear = (np.asarray(values, np.float64) / 255.0) ** gamma
    return np.rint(srgb_encode(linear @ (np.linalg.inv(SRGB) @ matrix).T) * 255.0)


def smooth_photo(megapixels: float, seed: int = 0) -> np.ndarray:
    """[H, W, 3] uint8, 4:3, bicubic upsampling of 8x smaller noise."""
    from PIL import Image

    h = int(round((megapixels * 1e6 * 3 / 4) ** 0.5))
    w = h * 4 // 3
    noise = np.random.default_rng(seed).integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8)
    return np.asarray(Image.fromarray(noise).resize((w, h), Image.BICUBIC))


def write_variants(pixels: np.ndarray, folder: Path) -> dict[str, tuple[Path, np.ndarray]]:
    """{variant: (file, the sRGB pixels it should decode to)}; HEIC only with pillow-heif."""
    from PIL import Image, ImageCms

    image, p3 = Image.fromarray(pixels), display_p3_profile()
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    out = {}
    for name, suffix, kw in [("JPEG q95", "jpg", {"quality": 95}),
                             ("JPEG q95, sRGB", "srgb.jpg", {"quality": 95, "icc_profile": srgb}),
                             ("JPEG q95, Display P3", "p3.jpg", {"quality": 95, "icc_profile": p3}),
                             ("PNG, Display P3", "p3.png", {"icc_profile": p3})]:
        path = folder / f"photo.{suffix}"
        image.save(path, **kw)
        stored = np.asarray(Image.open(path).convert("RGB"))  # the codec's loss is not the decoder's
        out[name] = (path, expected_srgb(stored) if "P3" in name else pixels)
    try:
        import pillow_heif
    except ImportError:
        print("(HEIC left out: pillow-heif, the 'photos' extra, is not installed)")
        return out
    pillow_heif.from_pillow(image).save(folder / "photo.heic", quality=90)
    out["HEIC q90"] = (folder / "photo.heic", pixels)
    return out


def measure(sizes_mp, repeats: int) -> list[dict]:
    from toolkit.images import decode_image

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for mp in sizes_mp:
            pixels = smooth_photo(mp)
            for name, (path, want) in write_variants(pixels, Path(tmp)).items():
                got = decode_image(path)[0].astype(np.float64)
                err = np.abs(got - want)
                as_srgb = np.abs(pixels.astype(np.float64) - want).mean() if "P3" in name else float("nan")
                ms = 1e3 * timeit(lambda p=path: decode_image(p), repeats=repeats, warmup=1)
                rows.append({"megapixels": round(pixels.shape[0] * pixels.shape[1] / 1e6, 1), "file": name,
                             "ms / photo": ms, "mean err (levels)": err.mean(), "max err": err.max(),
                             "read as sRGB: mean err": as_srgb})
    return rows


def main(argv=None) -> int:
    ap = CliParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=count("--repeats"), default=5)
    args = ap.parse_args(argv)
    print(machine_info())
    rows = measure((1.0, 12.0), args.repeats)
    print(format_table(rows))
    series = {}
    for r in rows:
        series.setdefault(r["file"], ([], []))
        series[r["file"]][0].append(r["megapixels"])
        series[r["file"]][1].append(r["ms / photo"])
    path = save_plot(OUT_DIR / "images.png", series, xlabel="photo megapixels", ylabel="ms / photo", logx=True,
                     logy=True, title="toolkit.images.decode_image: decode time by file kind")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
