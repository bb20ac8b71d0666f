"""Finding and posing faces in hard but real photos (apps.photo.faces, apps.photo.head_pose): a portrait stored
sideways with no orientation tag, a sliver of a photo and an empty file in a folder, a small face behind a false
detection, and a telephoto's long focal length."""

import numpy as np
import pytest
from PIL import Image

from apps.photo.face_model import default_face_model
from apps.photo.head_pose import solve_pnp


def _portrait_canvas(astronaut):
    """[512, 1600, 3]: the face at the left of a wide grey canvas, so that a turn by a quarter shows (not square)."""
    canvas = np.full((512, 1600, 3), 90, np.uint8)
    canvas[:, 50:562] = astronaut
    return canvas


def _turned_box(box, turns, height, width):
    """A box of an upright [height, width] image in that image turned by ``np.rot90(·, turns)`` (counter-clockwise):
    one turn puts (x, y) at (y, width - x), three at (height - y, x)."""
    x0, y0, x1, y1 = box
    return np.array([y0, width - x1, y1, width - x0] if turns == 1 else [height - y1, x0, height - y0, x1])


@pytest.mark.parametrize("turns", [1, 3])
def test_a_portrait_stored_sideways_without_a_tag_is_found_where_it_is(astronaut, finder, turns):
    """The detector sees such a photo turned upright; its box must come back in the stored photo's pixels (a
    non-square photo: width and height swap under the turn)."""
    canvas = _portrait_canvas(astronaut)
    upright = finder.detect(canvas)[0][0]
    stored = np.ascontiguousarray(np.rot90(canvas, turns))
    want = _turned_box(upright, turns, *canvas.shape[:2])
    assert np.abs(finder.detect(stored, 4 - turns)[0][0] - want).max() < 4
    faces, unfitted = finder.faces(stored)
    assert len(faces) == 1 and unfitted == 0
    mesh_box = np.concatenate([faces[0].points[:, :2].min(0), faces[0].points[:, :2].max(0)])
    up_faces, _ = finder.faces(canvas)
    up_box = np.concatenate([up_faces[0].points[:, :2].min(0), up_faces[0].points[:, :2].max(0)])
    assert np.abs(mesh_box - _turned_box(up_box, turns, *canvas.shape[:2])).max() < 6


def test_a_sliver_of_a_photo_is_no_face_and_not_a_crash(finder):
    """1 x 3000 pixels: scaled for the detector, its short side rounds to 0 pixels unless kept at one."""
    for shape in ((3000, 1, 3), (1, 3000, 3), (2100, 3, 3)):
        assert finder.faces(np.zeros(shape, np.uint8)) == ([], 0)


def test_a_sliver_in_a_folder_is_skipped_and_the_other_photos_prepared(astronaut, finder, tmp_path, capsys):
    """(``finder``: skipped without mediapipe, which apps.prepare needs.)"""
    from apps import prepare

    folder = tmp_path / "photos"
    folder.mkdir()
    Image.fromarray(astronaut).save(folder / "a.png")
    Image.new("RGB", (1, 3000)).save(folder / "b_line.png")
    (folder / "c_empty.jpg").touch()  # a failed copy: skipped on the same kind of line as a photo without a face
    assert prepare.main([str(folder), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "photos.h5").is_file()
    err = capsys.readouterr().err
    assert f"skipped {folder / 'b_line.png'}: no face found" in err and "a.png" not in err
    assert f"skipped {folder / 'c_empty.jpg'}: an empty file (0 bytes), expected an image" in err


def test_a_false_detection_does_not_stop_the_search_in_tiles(astronaut, finder, monkeypatch):
    """A small face in a large photo (found in tiles only) behind a detection the mesh cannot fit, as the detector
    gives on a turned pass over an empty area: the tiles are still searched, and the false box counted."""
    pano = np.full((600, 6000, 3), 120, np.uint8)
    pano[44:556, 2744:3256] = astronaut
    detect = type(finder).detect

    def with_a_false_box(self, rgb, quarter_turns=0):
        if rgb.shape == pano.shape and quarter_turns == 1:
            return [(np.array([100.0, 100.0, 400.0, 400.0]), 0.7, 0.0)]  # flat grey there: no mesh fits
        return detect(self, rgb, quarter_turns)

    monkeypatch.setattr(type(finder), "detect", with_a_false_box)
    faces, unfitted = finder.faces(pano)
    assert len(faces) == 1 and unfitted == 1
    assert 2744 < faces[0].points[:, 0].mean() < 3256


@pytest.mark.parametrize("focal", [1e3, 1.2e4, 1e5, 1e6])
def test_the_head_pose_holds_up_to_the_longest_focal_length_accepted(focal):
    """A face 100 px wide at focal lengths up to ``--focal``'s 1e6 px: nearly an orthographic view, where SQPnP
    refuses the points; the pose comes back within a degree and the depth within 1 %."""
    import cv2

    model = default_face_model()
    points = model.landmarks[:68].astype(np.float64)
    R = cv2.Rodrigues(np.array([0.1, 0.3, 0.05]))[0]
    t = np.array([0.02, -0.01, focal * np.ptp(points[:, 0]) / 100])
    K = np.array([[focal, 0, 1000], [0, focal, 700], [0, 0, 1.0]])
    x = points @ R.T + t
    uv = x[:, :2] / x[:, 2:] * focal + K[:2, 2] + np.random.default_rng(0).normal(0, 0.5, (68, 2))
    R_got, t_got, rms = solve_pnp(uv, K, model.landmarks)
    angle = np.degrees(np.arccos(np.clip((np.trace(R_got.T @ R) - 1) / 2, -1, 1)))
    assert angle < 1.0 and abs(t_got[2] / t[2] - 1) < 0.01 and rms < 1.5
