"""Scaled heads end to end: the generator renders a subject at head scale s != 1 (x_world = s · R x_head + t, as
real fits store), and every stage reads it as the unit head it is once ``fold_head_scale`` has divided the world
lengths by s (docs/data.md).

The same subject, frame seed and parameters are rendered at s = 0.9, 1.0 and 1.1 (one frame, 18 cameras, 48²);
the end-to-end test runs the ``tiny`` preset on a training subject at 0.9 and a held-out one at 1.1.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from tests.train.data.conftest import EGL
from toolkit.errors import ToolkitError

RES = 48
SCALES = (0.9, 1.0, 1.1)
SCALED = (0.9, 1.1)
FRAME_SEED = 7


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------


def _pixels(x_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """[..., n, 3] camera-frame points and [..., 3, 3] intrinsics -> [..., n, 2] pixels (u = 0: left edge)."""
    p = np.einsum("...ij,...nj->...ni", np.asarray(K, np.float64), np.asarray(x_cam, np.float64))
    return p[..., :2] / p[..., 2:]


def _head_to_world(pose: np.ndarray, x_head: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """[n, 3] head-frame points posed by ``pose`` [6] at ``scale``: s · R(pose[:3]) x + pose[3:], float64."""
    from train.data.poses import pose_matrix

    R, t = pose_matrix(np.asarray(pose, np.float64))
    return scale * np.asarray(x_head, np.float64) @ R.T + t


def _to_camera(x_world: np.ndarray, R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """[n, 3] world points -> camera frame of w2c rotation ``R`` [3, 3], translation ``T`` [3], float64."""
    return np.asarray(x_world, np.float64) @ np.asarray(R, np.float64).T + np.asarray(T, np.float64)


def _rows(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f.keys()}


def _extent(points) -> np.ndarray:
    """[3] the axis-aligned extent of [n, 3] points."""
    p = np.asarray(points, np.float64)
    return p.max(0) - p.min(0)


@pytest.fixture(scope="module")
def scaled_files(tmp_path_factory, subject_params, subject) -> dict[float, Path]:
    """{scale: subject file} of one subject rendered at each of :data:`SCALES` (same frame seed)."""
    if not EGL:
        from tests.gl import skip_without_gl

        skip_without_gl("no headless EGL OpenGL 3.3 context on this machine")
    from train.data.format import write_subject_h5
    from train.data.generate import generate_subject

    d = tmp_path_factory.mktemp("scaled")
    files = {}
    for s in SCALES:
        rows, subj, attrs = generate_subject(subject_params, n_frames=1, res=RES, seed=FRAME_SEED, subject=subject,
                                             scale=s)
        files[s] = write_subject_h5(d / f"scale{s}" / "subject0000.h5", rows, subject=subj, attrs=attrs)
    return files


# ----------------------------------------------------------------------------------------------
# The generator
# ----------------------------------------------------------------------------------------------


def test_generator_stores_the_scale_and_scale_one_is_the_default(scaled_files, subject_params, subject):
    """The rows' ``scale`` holds the rendered scale; the head frame and the attributes do not change with it; an
    explicit scale 1 writes what the default writes."""
    from train.data.generate import generate_subject

    files = {s: _rows(p) for s, p in scaled_files.items()}
    attrs = {}
    for s, p in scaled_files.items():
        assert files[s]["scale"].shape == (18, 1)
        np.testing.assert_array_equal(files[s]["scale"], np.float32(s))
        with h5py.File(p, "r") as f:
            attrs[s] = dict(f.attrs)
    for s in SCALED:
        assert attrs[s] == attrs[1.0]  # no attribute for the scale: the rows hold it
        for key in ("neutral_vertice", "eyeball_centers", "eyeball_radii", "mesh_faces", "pitchyaw_head"):
            np.testing.assert_array_equal(files[s][key], files[1.0][key])
        assert not np.allclose(files[s]["facial_landmarks_3d"], files[1.0]["facial_landmarks_3d"], atol=1e-3)
    default = generate_subject(subject_params, n_frames=1, res=RES, seed=FRAME_SEED, subject=subject)
    explicit = generate_subject(subject_params, n_frames=1, res=RES, seed=FRAME_SEED, subject=subject, scale=1.0)
    for a, b in zip(default, explicit):
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.parametrize("bad", [0.49, 2.01, 0.0, -1.0, float("nan"), float("inf"), True, "1.1", None])
def test_generator_refuses_a_scale_out_of_range(subject_params, bad):
    from train.data.generate import generate_subject, synth_dataset

    with pytest.raises(ToolkitError, match=r"^scale must be a number in \[0\.5, 2\.0\], got [^\n]+$"):
        generate_subject(subject_params, n_frames=1, res=16, scale=bad)
    with pytest.raises(ToolkitError, match=r"^scale must be"):
        synth_dataset("/nonexistent/never/written", n_subjects=1, n_frames=1, res=16, scale=bad)


def test_synth_cli_takes_a_scale(tmp_path, capsys):
    """``python -m train.data synth --scale`` writes that scale; a scale out of range is refused, naming the flag,
    before anything is written."""
    from toolkit.errors import run_cli
    from train.data.__main__ import main

    for bad in ("0.4", "2.5", "nan"):
        out = tmp_path / f"bad{bad}"
        assert run_cli(main, ["synth", "--subjects", "1", "--frames", "1", "--res", "16", "--scale", bad,
                              "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: --scale: expected a head scale in [0.5, 2.0]") and err.count("\n") == 1, err
        assert not out.exists()
    if not EGL:
        return
    out = tmp_path / "synth"
    assert run_cli(main, ["synth", "--subjects", "1", "--frames", "1", "--res", "16", "--scale", "1.2",
                          "--out", str(out)]) == 0
    np.testing.assert_array_equal(_rows(out / "subject0000.h5")["scale"], np.float32(1.2))


# ----------------------------------------------------------------------------------------------
# GazeDataset: the folded samples
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("s", SCALES)
def test_folded_sample_projects_onto_its_landmarks(scaled_files, s):
    """After folding, ``scale`` is 1 and ``landmarks_3d`` seen by ``K``, ``w2c_R``, ``w2c_T`` lands on the 2D
    landmarks; the stored (unfolded) 3D landmarks seen by the folded camera miss them by pixels."""
    from train.data.dataset import GazeDataset

    ds = GazeDataset([scaled_files[s]])
    worst, unfolded_worst = 0.0, 0.0
    for i in range(len(ds)):
        x, raw = ds[i], ds.read_row(0, i)
        assert float(x["scale"]) == 1.0
        cam = _to_camera(x["landmarks_3d"].numpy(), x["w2c_R"].numpy(), x["w2c_T"].numpy())
        worst = max(worst, np.abs(_pixels(cam, x["K"].numpy()) - x["landmarks"].numpy()).max())
        cam_raw = _to_camera(raw["facial_landmarks_3d"], x["w2c_R"].numpy(), x["w2c_T"].numpy())
        unfolded_worst = max(unfolded_worst, np.abs(_pixels(cam_raw, x["K"].numpy()) - x["landmarks"].numpy()).max())
    assert worst < 0.01  # pixels of a 48² image
    if s != 1.0:
        assert unfolded_worst > 0.5


@pytest.mark.parametrize("s", SCALED)
def test_head_to_camera_sees_the_unit_head(scaled_files, subject, s):
    """w2c ∘ pose of the folded sample, applied to the subject's head-frame landmarks, gives the folded camera-frame
    landmarks, which are the stored camera-frame landmarks divided by s: the camera sees the unit head at 1 / s
    its distance (the face centre at NORM_DISTANCE / s). Without the scale, the stored pose misses the stored
    landmarks by ~1 cm."""
    from train.data.dataset import GazeDataset
    from train.data.generate import NORM_DISTANCE

    ds = GazeDataset([scaled_files[s]])
    for i in range(len(ds)):
        x, raw = ds[i], ds.read_row(0, i)
        head = subject.landmarks(raw["expression_params"])
        folded = _to_camera(x["landmarks_3d"].numpy(), x["w2c_R"].numpy(), x["w2c_T"].numpy())
        seen = _to_camera(_head_to_world(x["pose"].numpy(), head), x["w2c_R"].numpy(), x["w2c_T"].numpy())
        stored = _to_camera(raw["facial_landmarks_3d"], raw["w2c_Rmat"], raw["w2c_Tvec"])
        np.testing.assert_allclose(seen, folded, atol=2e-6)  # metres
        np.testing.assert_allclose(stored / s, folded, atol=2e-6)
        stored_pose = _to_camera(_head_to_world(raw["pose"], head, s), raw["w2c_Rmat"], raw["w2c_Tvec"])
        np.testing.assert_allclose(stored_pose, stored, atol=2e-6)
        unit_pose = _to_camera(_head_to_world(raw["pose"], head), raw["w2c_Rmat"], raw["w2c_Tvec"])
        assert np.abs(unit_pose - stored).max() > 0.004  # ~10 % of the landmarks' distances to the head origin
        centre = _to_camera(_head_to_world(x["pose"].numpy(), subject.face_center[None]), x["w2c_R"].numpy(),
                            x["w2c_T"].numpy())[0]
        assert np.linalg.norm(centre) == pytest.approx(NORM_DISTANCE / s, rel=1e-5)


def test_gaze_labels_do_not_depend_on_scale(scaled_files):
    """Same subject, same frame seed: the head-frame gaze is the same at every scale, and so is the gaze in the rig
    frame. The camera-frame gaze is that gaze seen by each row's own camera, aimed at the (scaled) face centre, so
    it moves by the small turn of the camera alone; each row's is the head-frame gaze turned by w2c ∘ pose."""
    from toolkit.rotations import angular_error_deg, pitchyaw_to_vector
    from train.data.dataset import GazeDataset
    from train.losses import gaze_to_camera, head_to_camera_rotation

    world, batches = {}, {}
    for s, path in scaled_files.items():
        ds = GazeDataset([path])
        b = {k: torch.stack([ds[i][k] for i in range(len(ds))]).double()
             for k in ("pitchyaw_head", "pitchyaw_cam", "viewmat", "pose")}
        turned = gaze_to_camera(b["pitchyaw_head"], head_to_camera_rotation(b["viewmat"], b["pose"]))
        np.testing.assert_allclose(turned.numpy(), b["pitchyaw_cam"].numpy(), atol=2e-6)
        world[s] = torch.einsum("bji,bj->bi", b["viewmat"][:, :3, :3], pitchyaw_to_vector(b["pitchyaw_cam"]))
        batches[s] = b
        np.testing.assert_array_equal(_rows(path)["pitchyaw_head"], _rows(scaled_files[1.0])["pitchyaw_head"])
    for s in SCALED:
        np.testing.assert_allclose(world[s].numpy(), world[1.0].numpy(), atol=2e-6)  # w2c_Rᵀ g_cam
        a, b = batches[s], batches[1.0]
        gaze_turn = angular_error_deg(pitchyaw_to_vector(a["pitchyaw_cam"]), pitchyaw_to_vector(b["pitchyaw_cam"]))
        aim = a["viewmat"][:, :3, :3] @ b["viewmat"][:, :3, :3].transpose(1, 2)
        aim_turn = torch.rad2deg(torch.arccos(((aim.diagonal(dim1=1, dim2=2).sum(1) - 1) / 2).clamp(-1, 1)))
        assert (gaze_turn <= aim_turn + 1e-3).all() and 0 < float(aim_turn.max()) < 3.0


# ----------------------------------------------------------------------------------------------
# The stages' readers
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("s", SCALED)
def test_geometry_reader_takes_the_views_into_the_head_frame(scaled_files, subject, tmp_path, s):
    """``geometry.fit_dataset.read_subject`` (the geometry stage's reader) applies the file's scale: its
    head-frame landmarks are the subject's, and each view's head -> camera matrix puts them on the 2D landmarks.
    The same file with its ``scale`` set to 1 does not."""
    from geometry.fit_dataset import read_subject

    rows = _rows(scaled_files[s])
    head = subject.landmarks(rows["expression_params"][0])

    def misses(path) -> tuple[float, float]:
        data = read_subject(path)
        np.testing.assert_allclose(data["gt_verts"].numpy(), subject.neutral_vertices(), atol=1e-6)
        V = data["viewmats"].numpy().astype(np.float64)
        uv = _pixels(np.einsum("nij,kj->nki", V[:, :3, :3], head) + V[:, None, :3, 3], data["Ks"].numpy())
        return (float(np.abs(data["landmarks"].numpy() - head).max()),
                float(np.abs(uv - rows["facial_landmarks"]).max()))

    landmarks_off, pixels_off = misses(scaled_files[s])
    assert landmarks_off < 1e-5 and pixels_off < 0.01

    def unit_scale(f):
        f["scale"][...] = 1.0

    from tests.train.data.tiny_subject import edited_copy

    landmarks_off, pixels_off = misses(edited_copy(scaled_files[s], tmp_path / "unscaled.h5", unit_scale))
    assert landmarks_off > 2e-3 and pixels_off > 0.5


@pytest.mark.parametrize("s", SCALED)
def test_training_rows_pose_the_unit_head(scaled_files, subject, s):
    """The Gaussian stage's rows (``open_split`` -> ``TrainRows``) place the unit head: the subject's head-frame
    landmarks posed by ``pose``, seen by ``viewmat`` and ``K``, land on the rows' 2D landmarks, and the head-frame
    gaze turned by ``head_to_camera`` is the camera-frame label."""
    from toolkit.rotations import pitchyaw_to_vector, vector_to_pitchyaw
    from train.training.trainer import open_split

    rows = open_split([scaled_files[s]], "all", RES, cache_bytes=0, workers=0)
    try:
        b = rows.take(torch.arange(len(rows)), "cpu")
        g = vector_to_pitchyaw(torch.einsum("bij,bj->bi", rows.head_to_camera(b).double(),
                                            pitchyaw_to_vector(b["gaze_head"].double())))
    finally:
        rows.close()
    assert len(b["image"]) == 18
    np.testing.assert_allclose(g.numpy(), b["gaze_cam"].numpy(), atol=2e-6)
    stored = _rows(scaled_files[s])
    head = subject.landmarks(stored["expression_params"][0])
    unfolded_worst = 0.0
    for i in range(18):
        V = b["viewmat"][i].numpy()
        uv = _pixels(_to_camera(_head_to_world(b["pose"][i].numpy(), head), V[:3, :3], V[:3, 3]), b["K"][i].numpy())
        assert np.abs(uv - b["landmarks"][i].numpy()).max() < 0.01
        # the stored row's pose and camera, read as a unit head (the scale dropped), miss the landmarks
        cam = _to_camera(_head_to_world(stored["pose"][i], head), stored["w2c_Rmat"][i], stored["w2c_Tvec"][i])
        unfolded_worst = max(unfolded_worst, np.abs(_pixels(cam, b["K"][i].numpy()) - b["landmarks"][i].numpy()).max())
    assert unfolded_worst > 0.5


@pytest.mark.parametrize("s", SCALED)
def test_estimator_crops_find_the_eyes(scaled_files, s):
    """The estimator's rows of a scaled head: its labels are the file's camera-frame gaze and head pose, and its eye
    crops (``eye_patches`` at the rows' landmarks) hold the eyes: wherever an eye is visible, its mask covers part
    of its own patch and none of the other eye's."""
    from train.data.dataset import GazeDataset
    from train.estimator.crops import eye_patches
    from train.training.trainer import train_row

    ds = GazeDataset([scaled_files[s]], res=RES)
    items = [ds[i] for i in range(len(ds))]
    rows = _rows(scaled_files[s])
    for i, it in enumerate(items):
        row = train_row(it)
        np.testing.assert_array_equal(torch.cat([row["gaze_cam"], row["head_pose_cam"]]).numpy(),
                                      np.concatenate([rows["pitchyaw_cam"][i], rows["face_head_pose"][i]]))
    masks = torch.stack([torch.cat([it["left_eye_mask"], it["right_eye_mask"]]) for it in items])
    landmarks = torch.stack([it["landmarks"] for it in items])
    cover = eye_patches(masks, landmarks).mean((2, 3)).reshape(-1, 2, 2)  # [N, patch (left, right), mask (...)]
    visible = masks.sum((2, 3)) >= 2  # [N, eye]: at 48² an open eye shows a few pixels
    assert visible.all(1).sum() >= 8  # the frontal cameras see both eyes
    for eye in (0, 1):
        assert (cover[visible[:, eye], eye, eye] > 0.02).all()
        assert (cover[:, 1 - eye, eye] < 0.005).all()


@pytest.mark.parametrize("s", SCALED)
def test_evaluation_targets_render_the_scaled_row(scaled_files, subject, s):
    """The evaluation's generator targets (``SyntheticRedirectionPairs.render_target``) of a row turned to its own
    gaze reproduce the stored row; a render of the same row at scale 1 does not."""
    from train.data.pairing import SyntheticRedirectionPairs
    from train.data.synthetic import render_views

    pairs = SyntheticRedirectionPairs(scaled_files[s], res=RES)
    row = 8  # a frontal rig camera
    x = pairs.data[row]
    target = pairs.render_target(row, x["pitchyaw_head"].numpy())
    assert (target["head_mask"] != x["head_mask"]).float().mean() < 0.002
    assert (target["image"] - x["image"]).abs().max() < 2 / 255
    np.testing.assert_allclose(target["pitchyaw_cam"].numpy(), x["pitchyaw_cam"].numpy(), atol=1e-6)
    raw = pairs.data.read_row(0, row)
    from toolkit.cameras import Camera

    V = np.eye(4, dtype=np.float32)
    V[:3, :3], V[:3, 3] = raw["w2c_Rmat"], raw["w2c_Tvec"]
    cam = Camera(torch.from_numpy(raw["inmat"]), torch.from_numpy(V), RES, RES)
    unit = render_views(subject, raw["pitchyaw_head"], raw["pose"], raw["expression_params"], [cam],
                        light_dirs=raw["light_dir"], ambient=pairs.ambient)
    assert (torch.from_numpy(unit["head_mask"][0]).float() != x["head_mask"][0]).float().mean() > 0.01


# ----------------------------------------------------------------------------------------------
# A whole tiny run
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scaled_run(tmp_path_factory) -> tuple[Path, Path]:
    """(run directory, data root) of the ``tiny`` preset on a training subject at scale 0.9 (1 frame) and a
    held-out one at 1.1 (2 frames), 64² (the preset's size)."""
    if not EGL:
        from tests.gl import skip_without_gl

        skip_without_gl("no headless EGL OpenGL 3.3 context on this machine")
    from train import run
    from train.data.format import write_subject_h5
    from train.data.generate import generate_subject
    from train.data.subject_params import SubjectParams

    root, run_dir = tmp_path_factory.mktemp("scaled_root"), tmp_path_factory.mktemp("scaled_run")
    for i, (s, frames) in enumerate(((0.9, 1), (1.1, 2))):
        rows, subj, attrs = generate_subject(SubjectParams.sample(100 + i), n_frames=frames, res=64, seed=3 + i,
                                             scale=s)
        write_subject_h5(root / f"subject{i:04d}.h5", rows, subject=subj, attrs=attrs)
    (root / "split.json").write_text(json.dumps({"train": ["subject0000.h5"], "test": ["subject0001.h5"]}))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: threads only add overhead
    try:
        assert run.main(["--preset", "tiny", "--run-dir", str(run_dir), f"data.root={root}"]) == 0
    finally:
        torch.set_num_threads(threads)
    return run_dir, root


def test_tiny_run_fits_the_unit_head_of_a_scaled_subject(scaled_run):
    """Every stage runs on scaled subjects. The geometry stage's neutral mesh of the 0.9 subject has the size of its
    head-frame (unit) mesh, not 0.9 of it, and its Gaussians, posed by the folded rows, fall on the head."""
    from geometry.mesh_files import load_mesh
    from toolkit.scene import GaussianScene
    from train.data.dataset import GazeDataset

    run_dir, root = scaled_run
    for stage in ("data", "geometry", "codec", "estimator", "gaussian", "eval"):
        assert (run_dir / "stages" / f"{stage}.json").is_file(), stage
    fit = json.loads((run_dir / "geometry" / "fit.json").read_text())
    assert fit["chamfer_rel_diag"] < 0.03
    verts, _ = load_mesh(run_dir / "geometry" / "neutral_mesh.ply")
    truth = _rows(root / "subject0000.h5")["neutral_vertice"]
    ratio = _extent(verts) / _extent(truth)
    assert np.abs(ratio - 1).max() < 0.05, ratio  # a fit blind to the scale makes it 0.9
    means = GaussianScene.load(run_dir / "geometry" / "gaussians.safetensors").means.detach().numpy()
    ds = GazeDataset([root / "subject0000.h5"], res=64)
    on_head = []
    for i in range(len(ds)):
        x = ds[i]
        V = x["viewmat"].numpy()
        uv = _pixels(_to_camera(_head_to_world(x["pose"].numpy(), means), V[:3, :3], V[:3, 3]), x["K"].numpy())
        ij = np.floor(uv).astype(int)
        inside = ((ij >= 0) & (ij < 64)).all(1)
        on_head.append(inside.mean() * (x["head_mask"][0].numpy()[ij[inside, 1], ij[inside, 0]] > 0.5).mean())
    assert np.mean(on_head) > 0.9 and np.min(on_head) > 0.8, np.round(on_head, 3)
    metrics = json.loads((run_dir / "metrics.json").read_text())["metrics"]
    assert metrics["pairs"] == 2
    assert np.isfinite(metrics["gaze_error_deg"]) and metrics["psnr"] > 10 and metrics["ssim"] > 0.5


def test_redirect_app_reads_a_scaled_subject(scaled_run, tmp_path):
    """``apps.redirect`` on the held-out 1.1 subject writes unit-scale rows whose 3D landmarks project onto their
    2D ones, with the head where the input row's is."""
    from apps import redirect

    run_dir, root = scaled_run
    out = tmp_path / "redirected.h5"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert redirect.main([str(run_dir), str(root / "subject0001.h5"), str(out), "--rows", "2",
                              "--gazes", "grid:2x2:20"]) == 0
    finally:
        torch.set_num_threads(threads)
    got, src = _rows(out), _rows(root / "subject0001.h5")
    assert len(got["face_patch"]) == 8
    np.testing.assert_array_equal(got["scale"], 1.0)
    cam = np.stack([_to_camera(p, R, T) for p, R, T in zip(got["facial_landmarks_3d"], got["w2c_Rmat"],
                                                            got["w2c_Tvec"])])
    assert np.abs(_pixels(cam, got["inmat"]) - got["facial_landmarks"]).max() < 0.01
    for out_row, src_row in enumerate(got["source_row"]):
        a, b = got["head_mask"][out_row] > 127, src["head_mask"][src_row] > 127
        assert (a & b).sum() / (a | b).sum() > 0.7
