"""apps.prepare: a user's photos as native subject files. Exactness on synthetic renders (the generator's own
landmarks, pose and camera), a real photo (skimage's astronaut), the files' readers and the redirect app."""

import json
import math

import cv2
import h5py
import numpy as np
import pytest

from apps.photo.face_model import Target, default_face_model, subject_face_model
from apps.photo.normalize import warp_image, warp_points
from apps.photo.rows import FaceObservation, prepare_face
from benchmarks.prepare import generator_view, synthetic_photo
from toolkit.errors import ToolkitError


def _angle_deg(Ra, Rb):
    return math.degrees(math.acos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


def _centroid(mask):
    i, j = np.nonzero(mask)
    return np.array([j.mean() + 0.5, i.mean() + 0.5])


@pytest.fixture(scope="module")
def synthetic_photos():
    from tests.gl import require_gl

    require_gl()
    rot, xy = (0.15, -0.3, 0.08), np.array([0.03, -0.02])
    first = synthetic_photo(3, head_rotation=rot, translation=(*xy, 0.6), gaze=(0.2, -0.3))
    fc = first["R"] @ first["subject"].face_center  # put the face centre at the normalized distance, 0.6 m
    z = math.sqrt(0.6**2 - ((fc[:2] + xy) ** 2).sum()) - fc[2]
    return [synthetic_photo(3, head_rotation=rot, translation=(*xy, z), gaze=(0.2, -0.3), subject=first["subject"]),
            synthetic_photo(5, head_rotation=(-0.2, 0.35, -0.1), translation=(-0.04, 0.03, 0.85), gaze=(-0.1, 0.25),
                            width=800, height=600)]


@pytest.mark.parametrize("k", [0, 1])
def test_exact_landmarks_give_the_generators_pose_crop_and_gaze(synthetic_photos, k):
    """PnP + normalization on the generator's exact landmarks and its own head: the head pose within 1°, the
    crop's eye centres within 1 px of the generator's normalized view (exactly so with the face centre at 0.6 m;
    at 0.85 m the warp's perspective approximation), the iris-geometry gaze within 0.5°."""
    ph = synthetic_photos[k]
    size = 256
    target = Target(subject_face_model(ph["subject"]), 0.6, 0.26, size)
    obs = FaceObservation.from_landmarks(ph["landmarks"], ph["iris"])
    row = prepare_face(ph["bgr"], obs, ph["K"], target, scale=1.0)
    a = row.arrays
    view = generator_view(ph, size)
    # head pose: the stored camera sees the head as the generator's normalized camera does (world = head frame)
    R_gen = view["w2c_R"].astype(np.float64) @ ph["R"]
    assert _angle_deg(a["w2c_Rmat"].astype(np.float64), R_gen) < 1.0
    tol = 0.05 if k == 0 else 1.0
    for eye in (slice(36, 42), slice(42, 48)):
        ours, gen = a["facial_landmarks"][eye].mean(0), view["landmarks_2d"][eye].mean(0)
        assert np.linalg.norm(ours - gen) < tol, (ours, gen)
    # the image itself: the photo's true eye mask warped by the stored warp against the generator's view's
    warped = warp_image(ph["left_eye_mask"].astype(np.uint8) * 255, a["warp"].astype(np.float64), size)
    assert np.linalg.norm(_centroid(warped > 127) - _centroid(view["left_eye_mask"])) < 1.0
    assert np.abs(a["pitchyaw_head"] - ph["gaze"]).max() < math.radians(0.5)
    assert np.abs(a["pitchyaw_cam"] - view["pitchyaw_cam"]).max() < math.radians(0.5)
    assert np.abs(a["face_head_pose"] - view["face_head_pose"]).max() < math.radians(1.0)
    # the stored 3D landmarks project through the stored camera onto the stored 2D ones
    pc = a["facial_landmarks_3d"] @ a["w2c_Rmat"].T + a["w2c_Tvec"]
    uv = pc[:, :2] / pc[:, 2:] * np.diag(a["inmat"])[:2] + a["inmat"][:2, 2]
    assert np.abs(uv - a["facial_landmarks"]).max() < tol


def test_the_average_head_fits_any_subject_within_a_few_degrees(synthetic_photos):
    """With the default head model (not the subject's own) the exact landmarks still give the pose to a few
    degrees: the model mismatch PnP absorbs."""
    ph = synthetic_photos[0]
    target = Target(default_face_model(), 0.6, 0.26, 128)
    row = prepare_face(ph["bgr"], FaceObservation.from_landmarks(ph["landmarks"], ph["iris"]), ph["K"], target)
    view = generator_view(ph, 128)
    assert _angle_deg(row.arrays["w2c_Rmat"].astype(np.float64), view["w2c_R"].astype(np.float64) @ ph["R"]) < 6.0


def test_a_profile_is_refused_naming_the_turn(synthetic_photos):
    ph = synthetic_photo(7, head_rotation=(0.0, 1.45, 0.0), translation=(0.0, 0.0, 0.7),
                         subject=synthetic_photos[0]["subject"])
    target = Target(subject_face_model(ph["subject"]), 0.6, 0.26, 64)
    with pytest.raises(ToolkitError, match=r"turned \d+° from the camera"):
        prepare_face(ph["bgr"], FaceObservation.from_landmarks(ph["landmarks"], ph["iris"]), ph["K"], target)


def test_warp_points_and_image_agree_on_the_pixel_convention():
    """A dot at pixel centre (u, v) lands at warp_points((u, v)) in the warped image (u = 0 the left edge)."""
    img = np.zeros((200, 300), np.uint8)
    img[80, 120] = 255  # centre (120.5, 80.5)
    W = np.array([[1.7, 0.2, -40.0], [-0.1, 1.6, 10.0], [0.0002, 0.0001, 1.0]])
    out = warp_image(cv2.GaussianBlur(img, (0, 0), 2).astype(np.float32), W, 400)
    peak = np.unravel_index(np.argmax(out), out.shape)
    expect = warp_points(np.array([120.5, 80.5]), W)
    assert np.linalg.norm(np.array([peak[1] + 0.5, peak[0] + 0.5]) - expect) < 1.0


# ----------------------------------------------------------------------------------------------------------------
# Real photos (mediapipe)
# ----------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    pytest.importorskip("mediapipe")
    skdata = pytest.importorskip("skimage.data")
    d = tmp_path_factory.mktemp("photos")
    cv2.imwrite(str(d / "astronaut.jpg"), skdata.astronaut()[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    cv2.imwrite(str(d / "coffee.png"), skdata.coffee()[..., ::-1])
    small = cv2.resize(skdata.astronaut(), (256, 256), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(d / "small_face.png"), small[..., ::-1])  # a face ~46 px wide
    raw = (d / "astronaut.jpg").read_bytes()
    (d / "truncated.jpg").write_bytes(raw[: len(raw) // 2])
    (d / "notes.jpg").write_text("not an image")
    return d


@pytest.fixture(scope="module")
def prepared_astronaut(photos, tmp_path_factory):
    from apps import prepare

    out = tmp_path_factory.mktemp("prepared")
    assert prepare.main([str(photos / "astronaut.jpg"), "--out", str(out)]) == 0
    return out / "astronaut.h5"


def test_astronaut_is_found_frontal_centred_and_masked(prepared_astronaut):
    with h5py.File(prepared_astronaut) as f:
        assert f["face_patch"].shape == (1, 512, 512, 3)
        assert f.attrs["gaze_source"] == "iris-geometry"
        assert json.loads(f.attrs["source_files"])[0].endswith("astronaut.jpg")
        lm, hp = f["facial_landmarks"][0], f["face_head_pose"][0]
        head, eyes = f["head_mask"][0], (f["left_eye_mask"][0], f["right_eye_mask"][0])
        iris, warp, size = f["iris_centers"][0], f["warp"][0], f["source_size"][0]
    assert math.degrees(math.hypot(*hp)) < 20  # near frontal
    assert np.linalg.norm(lm[[36, 39, 42, 45, 48, 54]].mean(0) - 256) < 4  # the crop is centred on the face
    assert (size == (512, 512)).all() and abs(np.linalg.det(warp)) > 0
    for m, sl, c in zip(eyes, (slice(36, 42), slice(42, 48)), iris):
        assert 20 < (m > 0).sum() < 3000
        i, j = np.nonzero(m)
        lo, hi = lm[sl].min(0) - 3, lm[sl].max(0) + 3  # inside the eyelid landmarks' box
        assert (j + 0.5 >= lo[0]).all() and (j + 0.5 <= hi[0]).all() and (i + 0.5 >= lo[1]).all() and (i + 0.5 <= hi[1]).all()
        assert m[int(c[1]), int(c[0])] > 0  # the iris centre lies in its eye's mask
        assert head[m > 0].all()
    assert 0.2 < (head > 0).mean() < 0.8


def test_prepared_file_is_read_by_gaze_dataset_and_inspect(prepared_astronaut, capsys):
    from train.data import __main__ as data_cli
    from train.data.dataset import GazeDataset

    ds = GazeDataset([prepared_astronaut], res=64, with_mesh=True)
    s = ds[0]
    assert s["image"].shape == (3, 64, 64) and s["scale"].item() == 1.0  # the head scale folded in
    assert data_cli.main(["inspect", str(prepared_astronaut), "--sheet", str(prepared_astronaut.parent / "i.png")]) == 0


def test_several_inputs_skip_the_bad_ones_with_one_line_each(photos, tmp_path, capsys):
    from apps import prepare
    from toolkit.errors import run_cli

    args = [str(photos / n) for n in ("astronaut.jpg", "coffee.png", "truncated.jpg", "notes.jpg")]
    assert run_cli(prepare.main, args + ["--out", str(tmp_path), "--largest-face"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [ln for ln in err if ln.startswith("skipped")] == err and len(err) == 3
    assert any("coffee.png: no face found" in ln for ln in err)
    assert any("truncated.jpg" in ln and "truncated" in ln.split(":", 2)[-1] for ln in err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["astronaut.h5", "contact_sheet.png"]


@pytest.mark.parametrize("name, match", [
    ("coffee.png", r"coffee\.png: no face found \(expected a face at least 64 px wide, whole in the photo"),
    ("truncated.jpg", r"truncated\.jpg: not a readable image \(truncated"),
    ("notes.jpg", r"notes\.jpg: not a readable image"),
    ("small_face.png", r"small_face\.png: the face found is \d+ px wide, under 64 px: use a larger photo"),
])
def test_a_single_bad_photo_is_one_error_line_and_nothing_written(photos, tmp_path, name, match):
    from tests.fuzz.cli import assert_refused

    out = tmp_path / "out"
    out.mkdir()
    assert_refused("apps.prepare", [photos / name, "--out", out], match, inputs=[photos / name], out_dir=out)


def test_all_bad_photos_are_one_error_line(photos, tmp_path):
    from tests.fuzz.cli import assert_refused

    ins = [photos / "coffee.png", photos / "notes.jpg"]
    assert_refused("apps.prepare", [*ins, "--out", tmp_path], r"none of the 2 photos gave a usable face",
                   inputs=ins, out_dir=tmp_path)


def test_a_face_the_mesh_cannot_fit_is_named(photos, tmp_path, monkeypatch):
    from apps.photo.faces import FaceFinder
    from tests.fuzz.cli import assert_refused

    monkeypatch.setattr(FaceFinder, "mesh", lambda self, rgb, box, roll=0.0: None)
    assert_refused("apps.prepare", [photos / "astronaut.jpg", "--out", tmp_path],
                   r"astronaut\.jpg: a face was detected but the landmarker could not fit it", out_dir=tmp_path)


def test_without_the_extra_the_error_names_it(photos, tmp_path, monkeypatch):
    import sys

    from tests.fuzz.cli import assert_refused

    for name in ("mediapipe", "mediapipe.python"):  # as if never installed, even after an import
        monkeypatch.setitem(sys.modules, name, None)
    assert_refused("apps.prepare", [photos / "astronaut.jpg", "--out", tmp_path],
                   r"^error: reading faces from photos needs the optional extra 'photos'", out_dir=tmp_path)


def test_labels_csv_sets_the_gaze(photos, tmp_path):
    from apps import prepare
    from apps.photo.gaze import pitchyaw_vector

    (tmp_path / "labels.csv").write_text(f"image,gaze_pitch,gaze_yaw\n{photos / 'astronaut.jpg'},-10,5\n")
    assert prepare.main([str(photos / "astronaut.jpg"), "--out", str(tmp_path / "o"), "--labels",
                         str(tmp_path / "labels.csv")]) == 0
    with h5py.File(tmp_path / "o" / "astronaut.h5") as f:
        assert f.attrs["gaze_source"] == "labels-csv"
        W, K_n, R = f["warp"][0].astype(np.float64), f["inmat"][0].astype(np.float64), f["w2c_Rmat"][0]
        g_cam = pitchyaw_vector(f["pitchyaw_cam"][0])
        focal = json.loads(f.attrs["photo_focal"])[0][0]
    # the normalized camera's rotation from the photo's is K_n⁻¹ W K up to a z scale: the labelled photo-frame
    # gaze, turned by it, is the stored camera-frame gaze
    K = np.array([[focal, 0, 256], [0, focal, 256], [0, 0, 1.0]])
    M = np.linalg.inv(K_n) @ W @ K
    Rn = M / np.linalg.norm(M[0])
    Rn[2] = np.cross(Rn[0], Rn[1])
    g = Rn @ pitchyaw_vector(np.radians([-10.0, 5.0]))
    assert np.linalg.norm(g - g_cam) < 1e-3 and R.shape == (3, 3)


def test_the_redirect_app_renders_a_prepared_photo(photos, tiny_trained_run, tmp_path):
    from apps import prepare, redirect

    out = tmp_path / "prepared"
    assert prepare.main([str(photos / "astronaut.jpg"), "--out", str(out), "--like", str(tiny_trained_run)]) == 0
    with h5py.File(out / "astronaut.h5") as f:
        assert f["face_patch"].shape[1:3] == (64, 64)
        assert f["latent_codes"].shape == (1, 144) and not f["latent_codes"][()].any()
    red = tmp_path / "red.h5"
    assert redirect.main([str(tiny_trained_run), str(out / "astronaut.h5"), str(red), "--fit-weights",
                          "--fit-steps", "2", "--gazes", "grid:2x2:20"]) == 0
    with h5py.File(red) as f:
        assert f["face_patch"].shape == (4, 64, 64, 3)
