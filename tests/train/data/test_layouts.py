"""train.data.layouts against files written as the peers write them (tests/train/data/peer_fixtures.py)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from tests.train.data import peer_fixtures as pf
from toolkit.errors import ToolkitError
from train.data import layouts as L
from train.data.format import REQUIRED, validate_subject_file, write_subject_h5
from train.data.layout_conversion import from_native, native_row, to_native
from train.data.layout_files import read_split_file


@pytest.fixture(scope="module")
def truth():
    return pf.native_truth(n_frames=2, n_cams=3, seed=0)


@pytest.fixture(scope="module")
def files(tmp_path_factory, truth):
    d = tmp_path_factory.mktemp("peers")
    pf.write_ditgaze(d / "subject0000.h5", truth)
    pf.write_gazegaussian(d / "xgaze_subject0000.h5", truth)
    pf.write_gazegaussian(d / "gg_minimal.h5", truth, gazenerf_keys=False)
    codes = pf.write_gazenerf(d / "gn_subject0000.h5", truth)
    pf.write_xgaze(d / "subject0001.h5", truth)
    pf.write_xgaze(d / "subject0002.h5", truth, labels=False, landmarks=True)
    return {"ditgaze": d / "subject0000.h5", "gazegaussian": d / "xgaze_subject0000.h5",
            "gazegaussian_minimal": d / "gg_minimal.h5", "gazenerf": d / "gn_subject0000.h5",
            "xgaze": d / "subject0001.h5", "xgaze_test": d / "subject0002.h5", "gazenerf_codes": codes}


def _one_line(e: pytest.ExceptionInfo) -> str:
    msg = str(e.value)
    assert "\n" not in msg and len(msg) < 400, msg
    return msg


def _angle_diff(a, b):
    return np.abs(np.angle(np.exp(1j * (np.asarray(a, np.float64) - np.asarray(b, np.float64))))).max()


# ------------------------------------------------------------------------------------------------------------
# Detection
# ------------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("which, expected", [
    ("ditgaze", "ditgaze"), ("gazegaussian", "gazegaussian"), ("gazegaussian_minimal", "gazegaussian"),
    ("gazenerf", "gazenerf"), ("xgaze", "xgaze"), ("xgaze_test", "xgaze"),
])
def test_detects_each_layout(files, which, expected):
    keys, shapes = L.describe_file(files[which])
    assert L.detect_layout(keys, shapes, where=str(files[which])).name == expected


def test_native_file_without_optional_keys_is_told_by_its_1d_indices(truth):
    keys = set(REQUIRED)  # the peers index cam_index[idx, :] (GazeGaussian eth_xgaze.py L442), never 1-D
    shapes = {k: np.asarray(v).shape for k, v in truth.rows.items() if k in REQUIRED}
    assert L.detect_layout(keys, shapes) is L.DITGAZE


def test_ambiguous_keys_ask_for_data_layout(files, tmp_path):
    path = tmp_path / "xgaze_subject0009.h5"
    path.write_bytes(files["gazegaussian_minimal"].read_bytes())
    with h5py.File(path, "a") as f:  # the native keys exactly, indices (N, 1): either frame could be meant
        f["frame_index"] = f["cam_index"][()]
    keys, shapes = L.describe_file(path)
    with pytest.raises(ToolkitError) as e:
        L.detect_layout(keys, shapes, where=str(path))
    msg = _one_line(e)
    assert str(path) in msg and "data.layout=ditgaze" in msg and "data.layout=gazegaussian" in msg


def test_unknown_keys_name_what_was_found():
    with pytest.raises(ToolkitError) as e:
        L.detect_layout({"face_patch", "images"}, {"face_patch": (2, 16, 16, 3)}, where="a.h5")
    msg = _one_line(e)
    assert msg.startswith("a.h5: ") and "['face_patch']" in msg and "data.layout=" in msg
    assert all(name in msg for name in L.LAYOUTS)


def test_contradicting_shape_rules_a_layout_out(files):
    keys, shapes = L.describe_file(files["gazenerf"])
    shapes["latent_codes"] = (6, 144)  # GazeNeRF writes 306-d codes (dataset_pre_processing.py L306-312)
    with pytest.raises(ToolkitError):
        L.detect_layout(keys, shapes)
    with pytest.raises(ToolkitError) as e:
        L.check_layout("gazenerf", keys, shapes, where="f.h5")
    assert "'latent_codes' [6, 144] (expected N,306)" in _one_line(e)


def test_user_named_layout_contradicting_the_file(files):
    keys, _ = L.describe_file(files["gazenerf"])
    with pytest.raises(ToolkitError) as e:
        L.check_layout("gazegaussian", keys, where=str(files["gazenerf"]))
    msg = _one_line(e)
    assert "data.layout=gazegaussian requires keys" in msg
    assert all(k in msg for k in ("'facial_landmarks_3d'", "'pose'", "'scale'", "'vertice'"))
    assert L.check_layout("gazenerf", keys) is L.GAZENERF


def test_unknown_layout_name():
    with pytest.raises(ToolkitError) as e:
        L.get_layout("gazenerff")
    assert "'gazenerff'" in _one_line(e) and "ditgaze, gazegaussian, gazenerf, xgaze" in str(e.value)


# ------------------------------------------------------------------------------------------------------------
# Conversion
# ------------------------------------------------------------------------------------------------------------

def _native(files, which):
    keys, shapes, rows = pf.read_rows(files[which])
    return to_native(L.detect_layout(keys, shapes), rows)


@pytest.mark.parametrize("which", ["ditgaze", "gazegaussian", "gazegaussian_minimal"])
def test_to_native_recovers_the_truth(files, truth, which):
    got, want = _native(files, which), truth.rows
    assert _angle_diff(got["pitchyaw_head"], want["pitchyaw_head"]) < 1e-6
    assert _angle_diff(got["face_head_pose"], want["face_head_pose"]) < 1e-6
    for k in ("facial_landmarks_3d", "vertice"):
        assert np.abs(got[k] - want[k]).max() < 1e-5, k
    for k in ("cam_index", "scale", "pose", "latent_codes", "facial_landmarks", "w2c_Rmat", "face_patch"):
        assert got[k].shape == want[k].shape and got[k].dtype == want[k].dtype, k
        np.testing.assert_allclose(got[k], want[k], atol=1e-6, err_msg=k)
    assert got["cam_index"].ndim == 1 and got["scale"].shape == (6, 1) and (got["scale"] != 1).all()
    assert ("frame_index" in got) == (which != "gazegaussian_minimal")  # nothing the file lacks is invented


def test_gazegaussian_native_file_validates(files, tmp_path):
    path = write_subject_h5(tmp_path / "converted.h5", _native(files, "gazegaussian"))
    assert validate_subject_file(path)["n"] == 6


def test_gazegaussian_pose_and_scale_give_back_the_head_landmarks(files, truth):
    """GazeGaussian's canonical landmarks, (q - T) @ R / S (dataloader/eth_xgaze.py L314-319), are the
    head-frame landmarks once its 3D keys are read in its frame."""
    got = _native(files, "gazegaussian")
    R = pf.rodrigues(got["pose"][:, :3].astype(np.float64))
    q = got["facial_landmarks_3d"].astype(np.float64)
    head = np.einsum("nki,nij->nkj", q - got["pose"][:, None, 3:], R) / got["scale"][:, :, None]
    assert np.abs(head - truth.landmarks_head).max() < 1e-5


def _reprojection_px(rows, points):
    R, t, K = (rows[k].astype(np.float64) for k in ("w2c_Rmat", "w2c_Tvec", "inmat"))
    cam = np.einsum("nij,nkj->nki", R, points.astype(np.float64)) + t[:, None]
    uv = np.einsum("nij,nkj->nki", K, cam)
    return np.linalg.norm(uv[..., :2] / uv[..., 2:] - rows["facial_landmarks"], axis=-1).max()


def test_gazegaussian_3d_landmarks_reproject_onto_the_2d_ones(files):
    """Its renderer puts world points through w2c_Rmat/w2c_Tvec (eth_xgaze.py L464-472) and inmat, in pixels
    of face_patch (L452-462): the converted landmarks land within 1.5 px of the detected ones, the stored
    ones do not."""
    _, _, stored = pf.read_rows(files["gazegaussian"])
    assert _reprojection_px(_native(files, "gazegaussian"), _native(files, "gazegaussian")["facial_landmarks_3d"]) < 1.5
    assert _reprojection_px(stored, stored["facial_landmarks_3d"]) > 5


def test_gazenerf_gaze_sign_and_codes(files, truth):
    got = _native(files, "gazenerf")
    assert _angle_diff(got["pitchyaw_head"], truth.rows["pitchyaw_head"]) < 1e-6
    assert _angle_diff(got["face_head_pose"], truth.rows["face_head_pose"]) < 1e-6
    # the model's code: NL3DMM identity (100) then expression (79), configs/gazenerf_options.py L11-14
    codes = files["gazenerf_codes"]
    assert got["latent_codes"].shape == (6, 179) and got["latent_codes"].dtype == np.float32
    np.testing.assert_allclose(got["latent_codes"], np.concatenate([codes[:, :100], codes[:, 100:179]], 1), atol=1e-6)
    assert got["latent_texture"].shape == (6, 100) and got["latent_illumination"].shape == (6, 27)
    np.testing.assert_allclose(got["latent_illumination"], codes[:, 279:], atol=1e-6)
    assert not any(k.startswith("latent_codes_") for k in got)
    assert not {"c2w_Rmat", "pitchyaw_3d", "pitchyaw", "vertice"} & set(got)
    assert got["frame_index"].dtype == np.int32 and got["cam_index"].shape == (6,)


def test_gazenerf_rows_are_posed_in_their_head_frame(files):
    """w2c maps the NL3DMM head frame (fitting_nl3dmm.py L276-279): the world is the row's head frame, so pose 0
    and scale 1; the 3D landmarks are triangulated per frame (accuracy: tests/train/data/test_gazenerf_files.py)."""
    got = _native(files, "gazenerf")
    assert (got["pose"] == 0).all() and got["pose"].shape == (6, 6) and (got["scale"] == 1).all()
    assert got["facial_landmarks_3d"].shape == (6, 68, 3) and got["facial_landmarks_3d"].dtype == np.float32
    frame = got["frame_index"]
    assert (got["facial_landmarks_3d"][frame == 0] == got["facial_landmarks_3d"][frame == 0][0]).all()
    # the gaze alone (train.data inspect) converts without the cameras, and makes no pose
    assert set(to_native("gazenerf", {"pitchyaw_head": np.zeros((6, 2))})) == {"pitchyaw_head"}
    with pytest.raises(ToolkitError, match="convert the file's arrays whole"):
        native_row("gazenerf", {"pitchyaw_head": np.zeros(2)}, 0)


def test_code_widths_per_layout():
    assert L.code_widths("ditgaze") == L.code_widths("gazegaussian") == (80, 64)
    assert L.code_widths("gazenerf") == (100, 79)
    with pytest.raises(ToolkitError, match="data.layout=xgaze: its files carry no identity and expression codes"):
        L.code_widths("xgaze")
    assert L.agreed_code_widths([("a.h5", "ditgaze"), ("b.h5", "gazegaussian")]) == (80, 64)
    with pytest.raises(ToolkitError) as e:
        L.agreed_code_widths([("a.h5", "ditgaze"), ("xgaze_b.h5", "gazenerf")])
    assert _one_line(e).startswith("xgaze_b.h5: codes of 100 identity + 79 expression dims, but a.h5 has 80 + 64")


def test_xgaze_gaze_in_camera_and_head_frames(files, truth):
    got = _native(files, "xgaze")
    assert _angle_diff(got["pitchyaw_cam"], truth.rows["pitchyaw_cam"]) < 1e-6
    assert _angle_diff(got["pitchyaw_head"], truth.rows["pitchyaw_head"]) < 1e-6
    assert _angle_diff(got["face_head_pose"], truth.rows["face_head_pose"]) < 1e-6
    assert "face_mat_norm" not in got and got["cam_index"].shape == (6,)
    unlabelled = _native(files, "xgaze_test")
    assert "pitchyaw_head" not in unlabelled and unlabelled["facial_landmarks"].shape == (6, 68, 2)


def test_gazegaussian_export_reads_back(truth):
    exported = from_native("gazegaussian", truth.rows)
    assert exported["cam_index"].shape == (6, 1) and "pitchyaw_cam" not in exported
    keys = set(exported)
    assert L.detect_layout(keys, {k: v.shape for k, v in exported.items()}) is L.GAZEGAUSSIAN
    back = to_native("gazegaussian", exported)
    for k in REQUIRED:
        assert back[k].shape == truth.rows[k].shape and back[k].dtype == truth.rows[k].dtype, k
        tol = 1e-6 if k in ("pitchyaw_head", "face_head_pose") else 1e-5
        np.testing.assert_allclose(back[k], truth.rows[k], atol=tol, rtol=0, err_msg=k)


def test_export_to_gazenerf_is_refused(truth):
    with pytest.raises(ToolkitError) as e:
        from_native("gazenerf", truth.rows)
    assert "gazenerf" in _one_line(e)


def test_codes_of_the_wrong_width(truth):
    with pytest.raises(ToolkitError) as e:
        to_native("gazenerf", {"latent_codes": np.zeros((6, 144), np.float32)})
    assert "[6, 144]" in _one_line(e) and "306" in str(e.value)


# ------------------------------------------------------------------------------------------------------------
# Split files
# ------------------------------------------------------------------------------------------------------------

def test_split_files_of_both_forms(tmp_path):
    peer = pf.write_peer_split(tmp_path / "train_test_split.json", ["subject0000", "subject0003"], ["subject0012"])
    assert read_split_file(peer, "gazegaussian") == (["xgaze_subject0000", "xgaze_subject0003"],
                                                       ["xgaze_subject0012"])
    assert read_split_file(peer, "gazenerf")[1] == ["xgaze_subject0012"]
    native = tmp_path / "split.json"
    native.write_text(json.dumps({"train": ["subject0000.h5", "subject0001"], "test": ["subject0002"]}))
    assert read_split_file(native, "ditgaze") == (["subject0000", "subject0001"], ["subject0002"])
    xgaze = tmp_path / "xgaze_split.json"
    xgaze.write_text(json.dumps({"train": ["subject0000.h5"], "test": ["subject0001.h5"], "test_specific": []}))
    assert read_split_file(xgaze, "xgaze") == (["subject0000"], ["subject0001"])


@pytest.mark.parametrize("text, layout, expected", [
    ("{not json", "ditgaze", "not valid JSON"),
    ("[1, 2]", "ditgaze", "not a JSON object"),
    ('{"train": [], "test": ["a"]}', "gazegaussian", "no key 'val'"),
    ('{"train": "subject0000.h5", "val": []}', "gazenerf", "'train' is a JSON str"),
    ('{"train": [3], "val": []}', "gazenerf", "the entry 3"),
    ('{"train": ["../x.h5"], "val": []}', "gazenerf", "the entry '../x.h5'"),
    ('{"train": ["s1.h5"], "val": ["s1"]}', "gazenerf", "xgaze_s1 is both"),
    ('{"train": [], "test": []}', "ditgaze", "both empty"),
])
def test_malformed_split_files(tmp_path, text, layout, expected):
    path = tmp_path / "split.json"
    path.write_text(text)
    with pytest.raises(ToolkitError) as e:
        read_split_file(path, layout)
    msg = _one_line(e)
    assert str(path) in msg and expected in msg


def test_a_native_split_file_named_for_a_peer_layout_says_which_form_it_is(tmp_path):
    path = tmp_path / "split.json"
    path.write_text(json.dumps({"train": ["a"], "test": ["b"]}))
    with pytest.raises(ToolkitError) as e:
        read_split_file(path, "gazegaussian")
    assert "pass data.layout=ditgaze" in _one_line(e)


def test_inspect_shows_no_mesh_as_a_dash(files):
    """A GazeNeRF file stores no mesh: its row of the inspect table says '-', not None."""
    from train.data.__main__ import summarize
    from train.data.dataset import GazeDataset

    ds = GazeDataset([files["gazenerf"]], res=None)
    assert summarize(files["gazenerf"], ds.info[0], ds.layouts[0])["vertices"] == "-"
    ds = GazeDataset([files["ditgaze"]], res=None)
    assert summarize(files["ditgaze"], ds.info[0], ds.layouts[0])["vertices"] == ds.info[0]["n_vertices"] > 0
