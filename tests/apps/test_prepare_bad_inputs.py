"""apps.prepare refuses bad output locations up front: one error line, exit 2, every input unchanged and nothing
written. The face finder is replaced by one that fails, so each refusal is shown to come before any photo is
read (and the tests need neither mediapipe nor its models)."""

import re

import cv2
import h5py
import numpy as np
import pytest

from tests.fuzz.cli import assert_refused


def _q(path) -> str:
    """A path as a regex matching itself."""
    return re.escape(str(path))


class _NoFinder:
    """Stands in for apps.photo.faces.FaceFinder: reaching it means the output checks came too late."""

    def __init__(self, *a, **k):
        raise AssertionError("the face finder was started before the outputs were checked")


@pytest.fixture
def no_work(monkeypatch):
    import apps.photo.faces

    monkeypatch.setattr(apps.photo.faces, "FaceFinder", _NoFinder)


@pytest.fixture
def photo_dir(tmp_path):
    skdata = pytest.importorskip("skimage.data")
    d = tmp_path / "photos"
    d.mkdir()
    small = cv2.resize(skdata.astronaut(), (128, 128), interpolation=cv2.INTER_AREA)[..., ::-1]
    cv2.imwrite(str(d / "astro.png"), small)
    cv2.imwrite(str(d / "contact_sheet.png"), small)
    return d


@pytest.mark.parametrize("case", ["explicit", "default", "folder-default", "folder-explicit"])
def test_the_contact_sheet_never_replaces_an_input_photo(photo_dir, tmp_path, no_work, case):
    """--sheet naming an input photo, or its default OUT/contact_sheet.png being one (given as a file or found in
    a given folder), is refused naming --sheet and the photo."""
    sheet = photo_dir / "contact_sheet.png"
    out = tmp_path / "out"
    argv = {"explicit": [photo_dir / "astro.png", "--out", out, "--sheet", photo_dir / "astro.png"],
            "default": [sheet, "--out", photo_dir],
            "folder-default": [photo_dir, "--out", photo_dir],
            "folder-explicit": [photo_dir, "--out", out, "--sheet", sheet]}[case]
    named = photo_dir / ("astro.png" if case == "explicit" else "contact_sheet.png")
    line = assert_refused("apps.prepare", argv, rf"--sheet .*is the input photo \({_q(named)}\)",
                          inputs=[photo_dir], out_dir=photo_dir)
    assert not out.exists(), line


def test_a_subject_file_never_replaces_an_input(photo_dir, tmp_path, no_work):
    """OUT/<name>.h5 is refused when it is a photo given (whatever its name) or the --labels file."""
    fake = tmp_path / "astro.h5"
    fake.write_bytes((photo_dir / "astro.png").read_bytes())
    assert_refused("apps.prepare", [fake, "--out", tmp_path], rf"--out's output {_q(fake)}: is the input photo",
                   inputs=[fake], out_dir=tmp_path)
    labels = tmp_path / "o" / "astro.h5"
    labels.parent.mkdir()
    labels.write_text("image,gaze_pitch,gaze_yaw\n")
    assert_refused("apps.prepare", [photo_dir / "astro.png", "--out", labels.parent, "--labels", labels],
                   rf"--out's output {_q(labels)}: is the input file", inputs=[labels, photo_dir], out_dir=tmp_path)


@pytest.mark.parametrize("case, match", [
    ("sheet-under-file", r"--sheet {f}/s\.png: {f} is a file, not a folder"),
    ("out-under-file", r"--out {f}/p7: {f} is a file, not a folder"),
    ("sheet-is-folder", r"--sheet {t}/dir\.png: is a folder, expected a \.png file path"),
    ("h5-is-folder", r"--out {t}/o: the output {t}/o/astro\.h5 is a folder"),
], ids=["sheet-under-file", "out-under-file", "sheet-is-folder", "h5-is-folder"])
def test_output_locations_are_checked_before_any_work(photo_dir, tmp_path, no_work, case, match):
    """A sheet or output folder under a regular file, a sheet or subject file path that is a folder: refused
    before the first photo is read, so no subject file is left behind."""
    f = tmp_path / "regular_file"
    f.write_text("x")
    (tmp_path / "dir.png").mkdir()
    (tmp_path / "o" / "astro.h5").mkdir(parents=True)
    photo = photo_dir / "astro.png"
    argv = {"sheet-under-file": [photo, "--out", tmp_path / "o" / "p7", "--sheet", f / "s.png"],
            "out-under-file": [photo, "--out", f / "p7"],
            "sheet-is-folder": [photo, "--out", tmp_path / "o", "--sheet", tmp_path / "dir.png"],
            "h5-is-folder": [photo, "--out", tmp_path / "o"]}[case]
    assert_refused("apps.prepare", argv, match.format(f=_q(f), t=_q(tmp_path)), inputs=[photo_dir, f],
                   out_dir=tmp_path)


def test_a_data_file_pillow_knows_by_its_signature_is_not_a_readable_image(tmp_path):
    """An HDF5 file is a "stub" image of 0x0 pixels to Pillow: refused as not an image, not as an empty one."""
    from apps.photo.images import load_photo
    from toolkit.errors import ToolkitError

    path = tmp_path / "subject.h5"
    with h5py.File(path, "w") as f:
        f["face_patch"] = np.zeros((1, 4, 4, 3), np.uint8)
    with pytest.raises(ToolkitError, match=rf"^photo {_q(path)}: not a readable image \(HDF5 data"):
        load_photo(path)


def test_an_hdf5_file_given_as_a_photo_is_one_error_line(tmp_path):
    pytest.importorskip("mediapipe")
    path = tmp_path / "subject.h5"
    with h5py.File(path, "w") as f:
        f["face_patch"] = np.zeros((1, 4, 4, 3), np.uint8)
    out = tmp_path / "out"
    out.mkdir()
    assert_refused("apps.prepare", [path, "--out", out], rf"^error: photo {_q(path)}: not a readable image \(HDF5",
                   inputs=[path], out_dir=out)


def test_a_labels_folder_is_named_a_folder(tmp_path):
    from apps.photo.labels import read_labels
    from toolkit.errors import ToolkitError

    with pytest.raises(ToolkitError, match=rf"^--labels {_q(tmp_path)}: is a folder, expected a CSV file with columns"):
        read_labels(tmp_path)
    with pytest.raises(ToolkitError, match=r"no such file"):
        read_labels(tmp_path / "labels.csv")


def test_every_bad_row_of_a_labels_csv_is_listed(tmp_path):
    from apps.photo.labels import read_labels
    from toolkit.errors import ToolkitError

    labels = tmp_path / "labels.csv"
    labels.write_text("image,gaze_pitch,gaze_yaw\na.jpg,91,0\nb.jpg,10,5\n,1,1\nc.jpg,x,0\nb.jpg,0,0\n")
    with pytest.raises(ToolkitError, match=rf"^{_q(labels)} line 2, column 'gaze_pitch': .* \(and 3 more line\(s\) "
                                           r"with problems: 4, 5, 6\)$"):
        read_labels(labels)
    labels.write_text("image,gaze_pitch,gaze_yaw\na.jpg,9,0\nb.jpg,10,5\n")
    assert len(read_labels(labels)) == 2
