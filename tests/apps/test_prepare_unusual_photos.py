"""Unusual but valid photos (apps.photo, toolkit.images.decode_image): EXIF orientations, every common pixel mode,
formats beyond JPEG/PNG, panoramas and faces cut by the photo's edge. Each is read as it looks, or refused in
one line saying what to do."""


import numpy as np
import pytest
from PIL import Image

from toolkit.errors import ToolkitError
from toolkit.images import decode_image, read_image

# ----------------------------------------------------------------------------------------------------------------
# Decoding (no face detection)
# ----------------------------------------------------------------------------------------------------------------


def _picture(h=48, w=64):
    """[h, w, 3] uint8 RGB: smooth gradients, no two corners alike (a wrong turn or flip shows)."""
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 255 // (w - 1), y * 255 // (h - 1), (x + 2 * y) * 255 // (w + 2 * h - 3)], -1).astype(np.uint8)


def _exif(orientation):
    ex = Image.Exif()
    ex[0x0112] = orientation
    return ex.tobytes()


# Orientation tag -> the transpose a camera stored the upright picture with (the viewer undoes it)
STORED = {3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270,
          5: Image.Transpose.TRANSPOSE}


@pytest.mark.parametrize("orientation", sorted(STORED))
@pytest.mark.parametrize("fmt", ["PNG", "WEBP", "TIFF"])
def test_the_exif_orientation_is_applied(tmp_path, orientation, fmt):
    up = _picture()
    path = tmp_path / f"p.{fmt.lower()}"
    Image.fromarray(up).transpose(STORED[orientation]).save(path, fmt, exif=_exif(orientation), lossless=True)
    rgb, _ = decode_image(path)
    assert rgb.shape == up.shape and np.abs(rgb.astype(int) - up).max() <= 1
    assert np.array_equal(read_image(path), rgb[..., ::-1])


def test_modes_become_8_bit_rgb(tmp_path):
    up = _picture()
    grey = np.asarray(Image.fromarray(up).convert("L"))
    cases = {
        "l.png": (Image.fromarray(grey), np.repeat(grey[..., None], 3, -1)),
        "i16.png": (Image.fromarray(grey.astype(np.uint16) * 257), np.repeat(grey[..., None], 3, -1)),
        "p.png": (Image.fromarray(up).quantize(256), None),
        "cmyk.jpg": (Image.fromarray(up).convert("CMYK"), up),
        "bmp.bmp": (Image.fromarray(up), up),
    }
    for name, (im, want) in cases.items():
        im.save(tmp_path / name, **({"quality": 100} if name.endswith(".jpg") else {}))
        rgb, _ = decode_image(tmp_path / name)
        want = np.asarray(im.convert("RGB")) if want is None else want
        assert rgb.dtype == np.uint8 and rgb.shape == up.shape, name
        assert np.abs(rgb.astype(int) - want).mean() < 3, name  # CMYK: JPEG's loss only


def test_alpha_is_white_for_pictures_and_not_a_mask_in_grey(tmp_path):
    """A transparent band: white in colour (as load_photo always composited it; cv2.imread showed the black
    stored under it), 0 in a grey mask; opaque pixels untouched."""
    rgba = np.dstack([_picture(), np.full((48, 64), 255, np.uint8)])
    rgba[:10] = (0, 0, 0, 0)
    Image.fromarray(rgba).save(tmp_path / "a.png")
    bgr = read_image(tmp_path / "a.png")
    assert (bgr[:10] == 255).all() and np.array_equal(bgr[10:], rgba[10:, :, 2::-1])
    grey = read_image(tmp_path / "a.png", gray=True)
    assert (grey[:10] == 0).all() and grey[10:].mean() > 50
    pal = Image.fromarray(rgba[..., :3]).quantize(255)  # palette with a transparent index
    pal.save(tmp_path / "pt.png", transparency=int(np.asarray(pal)[0, 0]))
    assert (read_image(tmp_path / "pt.png")[:10] == 255).all()


def test_a_floating_point_image_and_a_heic_are_one_line_saying_what_to_do(tmp_path, monkeypatch):
    import sys

    import toolkit.images
    from apps.photo.images import load_photo

    monkeypatch.setitem(sys.modules, "pillow_heif", None)  # its import fails, as where the 'photos' extra is absent
    monkeypatch.setattr(toolkit.images, "_heif_opener_registered", False)

    Image.fromarray(np.zeros((8, 8), np.float32)).save(tmp_path / "f.tiff")
    with pytest.raises(ToolkitError, match=r"^photo \S*f\.tiff: a floating-point image.*save it as an 8-bit"):
        load_photo(tmp_path / "f.tiff")
    heic = tmp_path / "IMG_0001.HEIC"  # an iPhone photo's start: an ftyp box of brand heic
    heic.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + bytes(64))
    with pytest.raises(ToolkitError, match=r"^photo \S*IMG_0001\.HEIC: a HEIC image, .*install the 'photos' extra .*pillow-heif.* or convert it to "
                       r"JPEG or PNG"):
        load_photo(heic)


def test_photo_files_of_other_formats_and_names_are_photo_input(tmp_path):
    """apps.redirect took a WebP, TIFF or BMP photo (which apps.prepare reads) for a dataset and refused its
    output folder; any picture not named as a dataset is photo input now, and folders list those formats."""
    from apps.photo.images import photo_groups
    from apps.redirect_photo import is_photo_input

    for name, fmt in (("a.webp", "WEBP"), ("b.TIFF", "TIFF"), ("c.bmp", "BMP"), ("d.jfif", "JPEG"), ("e", "PNG")):
        Image.fromarray(_picture()).save(tmp_path / name, fmt)
        assert is_photo_input(tmp_path / name), name
    (tmp_path / "notes.txt").write_text("not a picture")
    assert not is_photo_input(tmp_path / "notes.txt") and not is_photo_input(tmp_path / "x.h5")
    assert [p.name for p in photo_groups([tmp_path])[0][1]] == ["a.webp", "b.TIFF", "c.bmp"]


def _videos(folder):
    """Real containers written by OpenCV's FFmpeg: MP4 and MOV (an ``ftyp`` box, ISO/IEC 14496-12 section 4.3),
    AVI (``RIFF....AVI ``) and Matroska (the EBML magic 1A 45 DF A3)."""
    import cv2

    written = {}
    for name, codec in (("clip.mp4", "mp4v"), ("clip2.MOV", "mp4v"), ("clip3.avi", "MJPG"), ("clip4.mkv", "MJPG")):
        w = cv2.VideoWriter(str(folder / name), cv2.VideoWriter_fourcc(*codec), 10, (64, 48))
        for i in range(3):
            w.write(np.full((48, 64, 3), 60 * i, np.uint8))
        w.release()
        written[name] = folder / name
    return written


def test_a_video_is_named_as_one_with_the_way_to_its_frames(tmp_path):
    from apps.photo.images import load_photo
    from apps.redirect_photo import is_photo_input
    from toolkit.file_kinds import video_kind

    kinds = {"clip.mp4": "an MP4 / MOV video", "clip2.MOV": "an MP4 / MOV video", "clip3.avi": "an AVI video",
             "clip4.mkv": "a Matroska / WebM video"}
    for name, path in _videos(tmp_path).items():
        assert video_kind(path) == kinds[name]
        renamed = path.with_name(f"{name}.data")  # known by content, whatever its name
        renamed.write_bytes(path.read_bytes())
        assert video_kind(renamed) == kinds[name] and is_photo_input(renamed)  # the photo reader then names it
        with pytest.raises(ToolkitError, match=rf"^photo \S*{name}: {kinds[name]}, not a picture; extract its frames "
                                               rf"first \(e\.g\. `mkdir frames && ffmpeg -i '{name}' -vf fps=2 "
                                               rf"frames/%05d\.png`\)"):
            load_photo(path)
    Image.fromarray(_picture()).save(tmp_path / "p.png")
    heic = tmp_path / "IMG.HEIC"
    heic.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + bytes(64))
    assert video_kind(tmp_path / "p.png") is None and video_kind(heic) is None and video_kind(tmp_path / "no") is None
    Image.fromarray(_picture()).save(tmp_path / "DSC_0001.NEF", format="TIFF")  # a camera raw: its reader names it
    assert is_photo_input(tmp_path / "DSC_0001.NEF")


def test_a_folder_of_raw_files_or_videos_names_them_and_a_pipe_is_not_read(tmp_path):
    import os

    from apps.photo.images import photo_groups
    from apps.redirect_photo import is_photo_input

    raws = tmp_path / "raws"
    raws.mkdir()
    for name in ("DSC_0001.NEF", "DSC_0002.NEF", "IMG_0003.CR2"):
        Image.fromarray(_picture()).save(raws / name, format="TIFF")
    _videos(raws)
    assert is_photo_input(raws)  # the photo reader's line, not a dataset reader's
    with pytest.raises(ToolkitError, match=r"raws: no photos in this folder \(expected .*\); it holds 3 camera raw "
                                           r"file\(s\) \(CR2, NEF\): develop them to JPEG or PNG first; 4 video\(s\)"):
        photo_groups([raws])
    os.mkfifo(tmp_path / "pipe")  # no writer: reading it would block
    assert not is_photo_input(tmp_path / "pipe")


def test_apps_prepare_refuses_a_video_in_one_line(tmp_path):
    from tests.fuzz.cli import assert_refused

    video = _videos(tmp_path)["clip.mp4"]
    assert_refused("apps.prepare", [video, "--out", tmp_path / "out"], r"clip\.mp4: an MP4 / MOV video, not a picture",
                   inputs=[video], out_dir=tmp_path / "out")


# ----------------------------------------------------------------------------------------------------------------
# Faces (mediapipe)
# ----------------------------------------------------------------------------------------------------------------


def _rows(rgb, finder, tmp_path, name="p.png", **save):
    from apps.photo.face_model import default_target
    from apps.photo.images import load_photo
    from apps.photo.rows import photo_rows

    im = rgb if isinstance(rgb, Image.Image) else Image.fromarray(rgb)
    im.save(tmp_path / name, **save)
    return photo_rows(load_photo(tmp_path / name), finder, default_target(64))[0]


def test_a_sideways_phone_photo_is_found_upright_where_the_upright_one_is(astronaut, finder, tmp_path):
    wide = np.pad(astronaut, ((0, 0), (300, 100), (0, 0)), mode="edge")  # not square: a turn would show
    want = _rows(wide, finder, tmp_path)[0].arrays
    for o in (6, 8):
        stored = Image.fromarray(wide).transpose(STORED[o])
        got = _rows(stored, finder, tmp_path, f"exif{o}.jpg", exif=_exif(o), quality=95)[0].arrays
        assert tuple(got["source_size"]) == (912, 512)
        assert np.abs(got["face_box"] - want["face_box"]).max() < 3
        assert np.abs(got["warp"] @ [500, 100, 1] / (got["warp"] @ [500, 100, 1])[2]
                      - want["warp"] @ [500, 100, 1] / (want["warp"] @ [500, 100, 1])[2]).max() < 2


@pytest.mark.parametrize("shape, at", [((600, 6000), (2744, 44)), ((6000, 600), (44, 2744))], ids=["wide", "tall"])
def test_a_face_in_a_panorama_is_found(astronaut, finder, tmp_path, shape, at):
    """The whole 6000-pixel panorama shows the detector its 92-pixel face at 3 pixels: it is found in tiles."""
    pano = np.full((*shape, 3), 120, np.uint8)
    pano[at[1]:at[1] + 512, at[0]:at[0] + 512] = astronaut
    ref = _rows(astronaut, finder, tmp_path)[0].arrays["face_box"]
    rows = _rows(pano, finder, tmp_path, "pano.jpg", quality=95)
    assert len(rows) == 1 and np.abs(rows[0].arrays["face_box"] - ref - [*at, *at]).max() < 3


def test_every_face_of_a_group_strip_is_found_once(astronaut, finder, tmp_path):
    strip = np.concatenate([astronaut if i % 2 == 0 else astronaut[:, ::-1] for i in range(5)], 1)  # 2560 x 512
    boxes = sorted(r.arrays["face_box"][0] for r in _rows(strip, finder, tmp_path))
    assert len(boxes) == 5 and all(b - a > 400 for a, b in zip(boxes, boxes[1:]))


def test_a_face_cut_through_an_eye_is_refused_and_one_cut_beside_it_kept(astronaut, finder, tmp_path):
    from tests.fuzz.cli import assert_refused

    assert len(_rows(astronaut[:, 182:], finder, tmp_path)) == 1  # the face's outline cut, both eyes whole
    Image.fromarray(astronaut[:, 200:]).save(tmp_path / "cut.png")
    out = tmp_path / "out"
    out.mkdir()
    assert_refused("apps.prepare", [tmp_path / "cut.png", "--out", out],
                   r"cut\.png: face 1 of 1: the face is cut off by the photo's edge \(its image-left eye is outside "
                   r"the photo\): use a photo showing the whole face", inputs=[tmp_path / "cut.png"], out_dir=out)


def test_an_iphone_style_heic_tagged_display_p3_gives_the_jpegs_face(astronaut, finder, tmp_path):
    """A phone's photo as it comes off the phone: HEIC, stored sideways (the turn in the file), tagged Display P3:
    read upright and in sRGB, its face is where the plain photo's is."""
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif (the 'photos' extra) is not installed")
    from benchmarks.images import display_p3_profile

    wide = np.pad(astronaut, ((0, 0), (300, 100), (0, 0)), mode="edge")
    want = _rows(wide, finder, tmp_path)[0].arrays
    path = tmp_path / "IMG_0004.HEIC"
    exif = Image.Exif()
    exif[0x0112] = 6
    exif.get_ifd(0x8769)[0xA405] = 26  # FocalLengthIn35mmFilm, as an iPhone's main camera writes it
    pillow_heif.from_pillow(Image.fromarray(wide).transpose(STORED[6])).save(
        path, quality=95, exif=exif.tobytes(), icc_profile=display_p3_profile())
    from apps.photo.face_model import default_target
    from apps.photo.images import load_photo
    from apps.photo.rows import photo_rows

    photo = load_photo(path)
    assert photo.focal_35mm == 26.0
    got = photo_rows(photo, finder, default_target(64))[0][0].arrays
    assert tuple(got["source_size"]) == (912, 512)
    assert np.abs(got["face_box"] - want["face_box"]).max() < 3
