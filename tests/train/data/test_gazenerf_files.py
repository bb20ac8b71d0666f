"""GazeNeRF's preprocessed ETH-XGaze files read by every stage (train.data.layouts, GAZENERF), and a model whose
code is as wide as the data's.

The fixture is a native subject written the way GazeNeRF's pipeline writes it (tests/train/data/peer_fixtures.py,
citing AlessandroRuzzi/GazeNeRF eb0a5f1): w2c composed with the head pose, so that each row's head frame is its
world (surface_fitting/nl3dmm/fitting_nl3dmm.py L276-279); the pitch sign flipped (utils/gaze_estimation_utils.py
L45-51); codes padded to NL3DMM's 100 identity + 79 expression + 100 texture + 27 illumination
(configs/gazenerf_options.py L11-14); uint8 (N, 1) indices (dataset_pre_processing.py L258-271); detector-noisy 2D
landmarks; no pose, scale or 3D keys. Reading it must give back the native labels.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from tests.train.data import peer_fixtures as pf
from toolkit.errors import ToolkitError
from train.data.dataset import GazeDataset
from train.data.layouts import GAZENERF

RES, NOISE_PX = 256, 0.25  # at 256² (focal 591 px at 0.6 m), 0.25 px of landmark noise is ~0.25 mm


@pytest.fixture(scope="module")
def truth():
    return pf.native_truth(n_frames=3, n_cams=4, seed=7, res=RES, noise_px=NOISE_PX)


@pytest.fixture(scope="module")
def nerf_file(tmp_path_factory, truth):
    path = tmp_path_factory.mktemp("gazenerf") / "xgaze_subject0007.h5"
    pf.write_gazenerf(path, truth, native_codes=True, optional=False)
    return path


def _camera(R, t, points):
    return np.einsum("nij,nkj->nki", np.asarray(R, np.float64), np.asarray(points, np.float64)) + \
        np.asarray(t, np.float64)[:, None]


def _rows(ds: GazeDataset) -> dict[str, np.ndarray]:
    rows = [ds.read_row(0, i) for i in range(len(ds))]
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]}


def test_the_fixture_is_what_gazenerf_writes(nerf_file):
    with h5py.File(nerf_file, "r") as f:
        assert set(f) == set(GAZENERF.required)
        assert f["cam_index"].dtype == f["frame_index"].dtype == np.uint8 and f["cam_index"].shape == (12, 1)
        assert f["latent_codes"].shape == (12, 306)


@pytest.mark.parametrize("layout", ["auto", "gazenerf"])
def test_gazenerf_file_reads_as_native(nerf_file, truth, layout):
    ds = GazeDataset([nerf_file], layout=layout)
    assert ds.layouts == ["gazenerf"] and len(ds) == 12 and ds.code_widths() == (100, 79)
    got, want = _rows(ds), truth.rows
    # the world is each row's head frame: pose 0, scale 1, and the camera is GazeNeRF's w2c (head -> camera)
    assert (got["pose"] == 0).all() and (got["scale"] == 1).all()
    # the triangulated landmarks are the native ones, seen from the camera, to ~1 mm ...
    cam = _camera(got["w2c_Rmat"], got["w2c_Tvec"], got["facial_landmarks_3d"])
    np.testing.assert_allclose(cam, _camera(want["w2c_Rmat"], want["w2c_Tvec"], want["facial_landmarks_3d"]),
                               atol=1e-3, rtol=0)
    # ... and land on the detected 2D landmarks, within the detector's noise
    uvw = np.einsum("nij,nkj->nki", got["inmat"].astype(np.float64), cam)
    assert np.linalg.norm(uvw[..., :2] / uvw[..., 2:] - want["facial_landmarks"], axis=-1).max() < 0.5
    for key in ("pitchyaw_head", "face_head_pose"):  # the pitch sign restored
        np.testing.assert_allclose(got[key], want[key], atol=1e-5, rtol=0, err_msg=key)
    np.testing.assert_array_equal(got["cam_index"], want["cam_index"])
    np.testing.assert_array_equal(got["frame_index"], want["frame_index"])
    s = ds[5]
    # the camera-frame gaze, derived from the head-frame one through w2c and the zero pose, is the native one
    np.testing.assert_allclose(s["pitchyaw_cam"].numpy(), want["pitchyaw_cam"][5], atol=1e-5, rtol=0)
    # the model's code: identity (the native 80 dims padded to 100) ++ expression (64 padded to 79)
    code = want["latent_codes"][5]
    assert s["latent_code"].shape == (179,)
    np.testing.assert_allclose(s["latent_code"].numpy(), np.concatenate([code[:80], np.zeros(20), code[80:],
                                                                         np.zeros(15)]), atol=1e-6, rtol=0)
    assert s["latent_texture"].shape == (100,) and s["latent_illumination"].shape == (27,)


def test_the_evaluations_pairing_check_reads_the_file_in_its_layout(nerf_file):
    from train.data.pairing import check_pairing_rows

    check_pairing_rows([nerf_file], None)  # validated as a GazeNeRF file, not as a native one missing 'pose'
    check_pairing_rows([nerf_file], None, layout="gazenerf")
    with pytest.raises(ToolkitError, match=r"pair 0 of the pairing \(input row 0, target row 12\) is out of range"):
        check_pairing_rows([nerf_file], {"*": np.array([[0, 12]])})


def test_a_model_of_the_datas_widths_renders_a_sample(nerf_file):
    from tests.train.helpers import rasterizer_for_tests
    from toolkit.procedural import demo_head_scene
    from train.model.gaussian_model import GaussianModel, GaussianModelConfig
    from train.model.renderer import make_renderer

    ds = GazeDataset([nerf_file], res=32)
    s = ds[3]
    torch.manual_seed(0)
    cfg = GaussianModelConfig(hidden=16, identity_dim=100, expression_dim=79)
    model = GaussianModel.from_scene(demo_head_scene(300), cfg, rasterizer=rasterizer_for_tests())
    b = lambda k: s[k][None]  # noqa: E731
    with torch.no_grad():
        maps = model(b("latent_code"), b("pose"), b("pitchyaw_head"), b("viewmat"), b("K"), 32, 32, renders=("head",))
        image = make_renderer("baseline", shape_dim=cfg.code_dim).render(maps["head"], b("latent_code"))
    assert image.shape == (1, 3, 32, 32) and bool(torch.isfinite(image).all())
    assert [t.shape for t in cfg.code_parts(b("latent_code"))] == [(1, 100), (1, 79)]
    native = GaussianModel.from_scene(demo_head_scene(300), GaussianModelConfig(hidden=16))
    with pytest.raises(ToolkitError, match=r"code: expected \[B, 144\] \(80 identity \+ 64 expression.*got \[1, 179\]"):
        native(b("latent_code"), b("pose"), b("pitchyaw_head"), b("viewmat"), b("K"), 32, 32)


def test_a_frame_seen_by_one_camera_is_one_line(tmp_path, truth):
    path = tmp_path / "xgaze_subject0008.h5"
    keep = np.ones(12, bool)
    keep[[5, 6, 7]] = False  # frame 1 keeps its camera 0 alone
    pf.write_gazenerf(path, pf.subset(truth, keep))
    with pytest.raises(ToolkitError) as e:
        GazeDataset([path])
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{path}: key 'facial_landmarks_3d': frame_index 1 (rows 4-4) is seen "
                                              "by 1 camera")


def test_a_one_camera_dataset_is_read_without_3d_landmarks(tmp_path, truth):
    """GazeNeRF's MPIIFaceGaze files: one webcam image per frame (dataset_pre_processing.py L559-612, written as
    mpii_subjectNNNN.h5, L496). Nothing can triangulate them: the samples carry no 3D landmarks, the evaluation
    reads them, and the geometry stage names the key it lacks."""
    from train.data.pairing import redirection_pairs
    from train.stages.geometry import subject_views_in_layout

    path = tmp_path / "mpii_subject0000.h5"
    pf.write_gazenerf(path, pf.subset(truth, np.arange(12) % 4 == 0))  # camera 0 of each of the 3 frames
    ds = GazeDataset([path], res=32)
    assert len(ds) == 3 and "landmarks_3d" not in ds[0] and ds[0]["latent_code"].shape == (179,)
    pairs = redirection_pairs(path, np.array([[0, 2], [1, 2]]), res=32)
    assert pairs.protocol == "stored" and pairs[1]["target"]["image"].shape == (3, 32, 32)
    with pytest.raises(ToolkitError, match=r"mpii_subject0000\.h5: no 3D landmarks \(key 'facial_landmarks_3d'\)"):
        subject_views_in_layout(path)


def test_a_degenerate_triangulation_is_one_line(tmp_path, truth):
    path = tmp_path / "xgaze_subject0009.h5"
    pf.write_gazenerf(path, truth)
    with h5py.File(path, "r+") as f:  # frame 2's cameras all at the first one's place: rays with no baseline
        R, t = f["w2c_Rmat"][()], f["w2c_Tvec"][()]
        R[8:], t[8:] = R[8], t[8]
        f["w2c_Rmat"][...], f["w2c_Tvec"][...] = R, t
    ds = GazeDataset([path])
    with pytest.raises(ToolkitError, match=rf"^{path}: key 'facial_landmarks_3d': frame_index 2 \(rows 8-11\): the "
                                           r"triangulation from its 4 cameras' 'facial_landmarks' is degenerate"):
        ds[0]


def test_frames_past_255_are_told_apart_by_their_rows():
    """GazeNeRF stores frame_index as uint8 (dataset_pre_processing.py L260-265): frames 256 apart share a value,
    but a frame is a run of consecutive rows (L383-445)."""
    from train.data.triangulation import frame_rows

    # frames 255, 256 and 512 (both stored as 0: a camera repeating starts the next), then 513 (stored as 1)
    frames = np.array([255, 255, 0, 0, 0, 0, 0, 1, 1], np.uint8)
    cams = np.array([0, 1, 0, 1, 2, 0, 1, 0, 1])
    assert [r.tolist() for r in frame_rows(frames, cams)] == [[0, 1], [2, 3, 4], [5, 6], [7, 8]]


# ------------------------------------------------------------------------------------------------------------
# The Gaussian stage's model takes its widths from the run's training files
# ------------------------------------------------------------------------------------------------------------

def _artifacts(tmp_path, root, *overrides: str):
    from toolkit.procedural import demo_head_scene
    from train.config import apply_overrides
    from train.presets import preset
    from train.stages.artifacts import RunArtifacts
    from train.stages.pipeline import RunContext

    demo_head_scene(300).save(tmp_path / "scene.safetensors")
    cfg = apply_overrides(preset("tiny"), [f"data.root={root}", "codec.kind=pixel", *overrides])
    return RunArtifacts(RunContext(tmp_path, cfg, {"geometry": {"scene": "scene.safetensors"}}, log=lambda m: None))


def test_the_gaussian_stage_builds_its_model_at_the_training_files_widths(tmp_path, truth):
    from train.stages.artifacts import checkpoint_code_widths
    from train.trained_run import TrainedRun
    from train.training.checkpoint import save_training_checkpoint

    nerf, native = tmp_path / "nerf", tmp_path / "native"
    nerf.mkdir()
    native.mkdir()
    small = pf.native_truth(n_frames=1, n_cams=2, seed=3)
    for i in range(2):
        pf.write_gazenerf(nerf / f"xgaze_subject000{i}.h5", small)
        pf.write_ditgaze(native / f"subject000{i}.h5", small)
    run = _artifacts(tmp_path / "a", nerf)
    model, renderer = run.build_model("cpu")
    assert (model.config.identity_dim, model.config.expression_dim, model.config.code_dim) == (100, 79, 179)
    assert renderer.dit.config.shape_dim == 179
    # the stage records the widths with the weights; a finished run reloads at them without its data
    ckpt = tmp_path / "a" / "final.safetensors"
    save_training_checkpoint(ckpt, step=1, modules={"model": model, "renderer": renderer},
                             extra={"code_widths": [100, 79]})
    run.context.outputs["gaussian"] = {"checkpoint": "final.safetensors"}
    for p in nerf.iterdir():
        p.unlink()
    assert checkpoint_code_widths(ckpt) == (100, 79) and TrainedRun(run.context).code_widths() == (100, 79)
    loaded, _ = run.load_model("cpu")
    assert loaded.config.code_dim == 179 and torch.equal(loaded.face_features, model.face_features)
    # a native run keeps 80 + 64, and its checkpoints from before the widths were stored read as native
    model, renderer = _artifacts(tmp_path / "b", native).build_model("cpu")
    assert (model.config.identity_dim, model.config.expression_dim, renderer.dit.config.shape_dim) == (80, 64, 144)
    save_training_checkpoint(tmp_path / "b" / "old.safetensors", step=1, modules={"model": model})
    assert checkpoint_code_widths(tmp_path / "b" / "old.safetensors") == (80, 64)


def test_training_files_of_other_widths_are_one_line(tmp_path):
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    small = pf.native_truth(n_frames=1, n_cams=2, seed=3)
    pf.write_ditgaze(mixed / "subject0000.h5", small)
    pf.write_gazenerf(mixed / "subject0001.h5", small)
    pf.write_ditgaze(mixed / "subject0002.h5", small)
    run = _artifacts(tmp_path / "run", mixed, "data.test_fraction=0.25")  # 0000 and 0001 train
    with pytest.raises(ToolkitError) as e:
        run.build_model("cpu")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{mixed / 'subject0001.h5'}: codes of 100 identity + 79 expression "
                                              f"dims, but {mixed / 'subject0000.h5'} has 80 + 64")


def test_the_redirect_apps_codes_are_as_wide_as_the_runs(tmp_path):
    """apps.redirect checks a labels CSV's codes against the trained run's widths (TrainedRun.code_widths)."""
    import cv2

    from apps.labels_table import read_labels

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((64, 64, 3), np.uint8))
    np.save(tmp_path / "code.npy", np.zeros(179, np.float32))
    (tmp_path / "labels.csv").write_text("image,head_pitch,head_yaw,code\na.png,0,0,code.npy\n")
    rows, _ = read_labels(tmp_path / "labels.csv", code_widths=(100, 79))
    assert rows[0].code.shape == (179,)
    with pytest.raises(ToolkitError, match=r"code.npy: expected 144 numbers \(identity 80 \+ expression 64\)"):
        read_labels(tmp_path / "labels.csv")
