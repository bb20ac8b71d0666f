"""python -m apps.redirect RUN_DIR photo.jpg OUT_DIR: photos prepared on the fly, each face fitted and rendered at
the target gazes, a grid per face and (--paste-back) the redirected face pasted back into its photo."""

import contextlib
import io

import cv2
import h5py
import numpy as np
import pytest

from apps import redirect
from apps.redirect_photo import LABEL_PX, grid_tile_side
from tests.fuzz.cli import assert_refused

GAZES = "grid:2x2:20"  # (pitch, yaw) rows: (-20, -20), (-20, +20), (+20, -20), (+20, +20)
TAGS = ["-20_-20", "-20_+20", "+20_-20", "+20_+20"]


@pytest.fixture(scope="module")
def redirected(tiny_trained_run, tmp_path_factory):
    """The astronaut (a JPEG) and a photo without a face (the coffee cup), redirected in one run."""
    pytest.importorskip("mediapipe")
    skdata = pytest.importorskip("skimage.data")
    d = tmp_path_factory.mktemp("photos")
    cv2.imwrite(str(d / "astronaut.jpg"), np.ascontiguousarray(skdata.astronaut()[..., ::-1]))
    cv2.imwrite(str(d / "coffee.jpg"), np.ascontiguousarray(skdata.coffee()[..., ::-1]))
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = redirect.main([str(tiny_trained_run), str(d / "astronaut.jpg"), str(d / "coffee.jpg"), str(d / "out"),
                              "--gazes", GAZES, "--fit-steps", "2", "--paste-back"])
    assert code == 0
    return d, d / "out", err.getvalue()


def test_outputs_and_their_sizes(redirected):
    from apps.photo.images import load_photo
    from train.data.dataset import GazeDataset

    d, out, err = redirected
    assert "skipped" in err and "coffee.jpg" in err  # the other photo went on
    names = {"redirected.h5", "astronaut_face1_grid.png", *(f"astronaut_face1_{t}.png" for t in TAGS)}
    assert {p.name for p in out.iterdir()} == names
    photo = load_photo(d / "astronaut.jpg").bgr
    for t in TAGS:
        assert cv2.imread(str(out / f"astronaut_face1_{t}.png")).shape == photo.shape  # the original resolution
    side = grid_tile_side(64)  # the tiny run's crops are 64²
    assert cv2.imread(str(out / "astronaut_face1_grid.png")).shape == (side + LABEL_PX, (1 + 4) * side, 3)
    ds = GazeDataset([out / "redirected.h5"], res=64)
    assert len(ds) == 4  # one face × 4 gazes
    want = redirect.parse_gazes(GAZES)
    for i in range(4):
        assert np.allclose(ds[i]["pitchyaw_head"].numpy(), want[i], atol=1e-6)
    with h5py.File(out / "redirected.h5") as h:
        assert (h["source_row"][:] == 0).all() and h["warp"].shape == (4, 3, 3)
        assert (h["source_size"][:] == [512, 512]).all()


def _photo_regions(photo_shape, warp, head_mask):
    """Photo pixels whose crop sample lies where the feathered alpha is 1 (inside) and where the alpha, dilated by
    a crop pixel, is 0 or beyond the crop (outside)."""
    from apps.photo.normalize import to_opencv
    from apps.photo.paste import FEATHER, feathered_alpha

    S = head_mask.shape[0]
    alpha = feathered_alpha(head_mask, FEATHER * S)
    H, W = photo_shape[:2]
    samp = lambda m: cv2.warpPerspective(m, to_opencv(warp.astype(np.float64)), (W, H),  # noqa: E731
                                         flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    inside = samp(cv2.erode((alpha >= 0.999).astype(np.uint8), np.ones((3, 3), np.uint8)))
    outside = samp(1 - cv2.dilate((alpha > 0).astype(np.uint8), np.ones((3, 3), np.uint8)))
    return inside, outside | ~samp(np.ones((S, S), np.uint8))


def test_pasted_photos_change_the_head_only(redirected):
    from apps.photo.images import load_photo

    d, out, _ = redirected
    photo = load_photo(d / "astronaut.jpg").bgr  # the decoded JPEG
    with h5py.File(out / "redirected.h5") as h:
        warp, masks = h["warp"][:], h["head_mask"][:]
    pasted = [cv2.imread(str(out / f"astronaut_face1_{t}.png")) for t in TAGS]
    for j, p in enumerate(pasted):
        inside, outside = _photo_regions(photo.shape, warp[j], masks[j])
        assert inside.sum() > 2000 and outside.sum() > 0.8 * outside.size
        assert np.array_equal(p[outside], photo[outside])  # bit for bit
        assert (p != photo).any(-1)[inside].mean() > 0.5
    assert not np.array_equal(pasted[0], pasted[1])  # another gaze, another face


def test_the_eyes_turn_with_the_target_gaze(redirected):
    """The tiny run's renders are a blur and its evaluation estimator reads nonsense on them (60° pitch, 160° yaw
    whatever the gaze), so: turning the gaze from yaw -20° to +20° changes the renders around the eyes (the eye
    masks grown by 3 px) about twice as much as the rest of the head (1.9-2.4 with 2-3 fit steps, seeds 0-2 and
    --natural-eyes; about 0.8 around the mouth)."""
    _, out, _ = redirected
    with h5py.File(out / "redirected.h5") as h:
        img = h["face_patch"][:].astype(np.float64)
        eyes = (h["left_eye_mask"][0] > 0) | (h["right_eye_mask"][0] > 0)
        head = h["head_mask"][0] > 0
    near = cv2.dilate(eyes.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    for a, b in ((0, 1), (2, 3)):  # yaw -20 -> +20 at pitch -20, then at +20
        diff = np.abs(img[b] - img[a]).mean(-1)
        assert diff[near & head].mean() > 1.5 * diff[head & ~near].mean()


def test_a_photo_without_a_face_is_one_line(tiny_trained_run, tmp_path):
    pytest.importorskip("mediapipe")
    skdata = pytest.importorskip("skimage.data")
    coffee = tmp_path / "coffee.jpg"
    cv2.imwrite(str(coffee), np.ascontiguousarray(skdata.coffee()[..., ::-1]))
    assert_refused("apps.redirect", [tiny_trained_run, coffee, tmp_path / "out", "--paste-back"],
                   r"^error: \S*coffee\.jpg: no face found", inputs=[coffee, tiny_trained_run], out_dir=tmp_path)


@pytest.mark.parametrize("args, match", [
    (["{h5}", "{tmp}/out.h5", "--paste-back"], r"--paste-back pastes .*: it needs photo input"),
    (["{h5}", "{tmp}/out.h5", "--largest-face"], r"--largest-face .*: it needs photo input"),
    (["{jpg}", "{tmp}/out.h5"], r"photo input writes a folder"),
    (["{jpg}", "{h5}", "{tmp}/out"], r"cannot be mixed with an HDF5 file"),
    (["{jpg}", "{tmp}/out", "--fit-steps", "0"], r"photo input \(fitted before it is rendered\) needs --fit-steps >= 1, got 0"),
], ids=["paste-back-h5", "largest-face-h5", "photo-to-h5", "mixed", "no-fit"])
def test_photo_flags_refused(tiny_trained_run, tmp_path, args, match):
    h5 = sorted((tiny_trained_run / "data").glob("*.h5"))[-1]
    jpg = tmp_path / "me.jpg"
    jpg.write_bytes(b"not read: refused before")
    argv = [a.format(h5=h5, tmp=tmp_path, jpg=jpg) for a in args]
    assert_refused("apps.redirect", [tiny_trained_run, *argv], match, inputs=[h5, jpg], out_dir=tmp_path)
