"""Procedural subjects: watertight meshes, exact and mutually consistent labels, iris position from gaze."""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest
import torch
from scipy import ndimage

from tests.train.data.conftest import needs_gl
from toolkit.errors import ToolkitError
from toolkit.rotations import angular_error_deg, so3_exp, vector_to_pitchyaw
from train.data import subject_params as sp
from train.data import synthetic as syn


def _rows(path):
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f.keys()}


def test_head_mesh_is_watertight_and_outward(subject):
    import trimesh

    m = trimesh.Trimesh(subject.neutral_vertices(), subject.head_faces, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0  # outward winding
    # Extreme identities and expressions keep a valid closed surface.
    for sign in (-1.0, 1.0):
        params = sp.SubjectParams(tuple(sign for _ in sp.IDENTITY_NAMES))
        s = syn.build_subject(params, subdivisions=3)
        for e in ([0, 0, 0, 0], [1, 1, 1, 1], [1, -1, -1, 0]):
            v = s.head_vertices(e)
            assert np.isfinite(v).all()
            mm = trimesh.Trimesh(v, s.head_faces, process=False)
            assert mm.is_watertight and mm.volume > 0
        assert np.isfinite(s.head_colors([1, 1, 1, 1])).all() and np.isfinite(s.landmarks([1, -1, 1, 1])).all()


def test_eyeballs_are_spheres_rotating_about_their_centres(subject):
    for g in ([0.0, 0.0], [0.4, -0.6], [-0.7, 0.7]):
        ev = subject.eyeball_vertices(g)
        for k in range(2):
            r = np.linalg.norm(ev[k] - subject.eye_centers[k], axis=1)
            np.testing.assert_allclose(r, subject.eye_radius, rtol=1e-5)
        # The pupil pole (vertex 0, theta = 0) points along the gaze direction.
        d = ev[0, 0] - subject.eye_centers[0]
        py = vector_to_pitchyaw(torch.tensor(d, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(py, g, atol=1e-5)
    assert subject.eye_centers[0, 0] < 0 < subject.eye_centers[1, 0]  # left = image-left (x < 0)


def test_landmark_layout_matches_ibug(subject):
    lm = subject.landmarks()
    assert lm[36:42, 0].max() < 0 < lm[42:48, 0].min()  # left eye on the image left
    assert lm[36, 0] < lm[39, 0] and lm[42, 0] < lm[45, 0]  # 36 outer-left, 45 outer-right
    assert lm[37:39, 1].max() < lm[40:42, 1].min()  # upper lids above lower lids (y down)
    assert lm[48, 0] < lm[54, 0] and lm[51, 1] < lm[57, 1]
    assert lm[8, 1] > lm[57, 1] > lm[33, 1] > lm[27, 1]  # chin below mouth below nose below bridge
    # Landmarks lie on the analytic surface; the eye ones on the outer skin just outside the opening.
    from scipy.spatial import cKDTree

    d, _ = cKDTree(subject.neutral_vertices()).query(lm)
    assert d.max() < 4e-3


def test_latent_code_is_a_fixed_invertible_embedding(subject_params):
    e = np.array([0.3, -0.5, 0.2, 0.1], np.float32)
    code = sp.latent_code(subject_params.vector(), e)
    assert code.shape == (144,)
    ident, expr = sp.params_from_code(code)
    np.testing.assert_allclose(ident, subject_params.vector(), atol=1e-5)
    np.testing.assert_allclose(expr, e, atol=1e-6)
    np.testing.assert_array_equal(code, sp.latent_code(subject_params.vector(), e))


@needs_gl
def test_file_labels_are_consistent(subject_file, subject):
    r = _rows(subject_file)
    n = len(r["face_patch"])
    assert r["cam_index"].shape == r["frame_index"].shape == (n, 1)  # [N, 1], as the peers index them
    assert n == 36 and set(r["cam_index"][:, 0]) == set(range(18)) and set(r["frame_index"][:, 0]) == {0, 1}
    # 3D landmarks projected with K and the extrinsics land on the 2D landmarks.
    pc = np.einsum("nij,nkj->nki", r["w2c_Rmat"], r["facial_landmarks_3d"]) + r["w2c_Tvec"][:, None]
    uv = np.einsum("nij,nkj->nki", r["inmat"], pc)
    np.testing.assert_allclose(uv[..., :2] / uv[..., 2:], r["facial_landmarks"], atol=2e-3)
    for i in (0, 17, 20):
        R = so3_exp(torch.from_numpy(r["pose"][i, :3].astype(np.float64))).numpy()
        s, t = float(r["scale"][i, 0]), r["pose"][i, 3:]
        e = r["expression_params"][i]
        # World landmarks / vertices = pose applied to the head-frame ones.
        np.testing.assert_allclose(r["facial_landmarks_3d"][i], s * subject.landmarks(e) @ R.T + t, atol=1e-5)
        np.testing.assert_allclose(r["vertice"][i], s * subject.head_vertices(e) @ R.T + t, atol=1e-5)
        # Camera-frame gaze = w2c ∘ pose applied to the head-frame gaze.
        g_head = syn._pitchyaw_vec(r["pitchyaw_head"][i])
        g_cam = r["w2c_Rmat"][i] @ R @ g_head
        np.testing.assert_allclose(vector_to_pitchyaw(torch.from_numpy(g_cam)).numpy(), r["pitchyaw_cam"][i], atol=1e-5)
    # The normalized camera leaves no head roll: the camera-frame gaze is the head-frame gaze turned by the
    # rotation that the camera-frame head pose alone fixes (what the gaze estimator composes).
    from toolkit.rotations import head_to_camera_gaze

    composed = head_to_camera_gaze(torch.from_numpy(r["pitchyaw_head"]).double(),
                                   torch.from_numpy(r["face_head_pose"]).double())
    assert float(angular_error_deg(composed, torch.from_numpy(r["pitchyaw_cam"]).double()).max()) < 1e-3
    assert (np.abs(np.degrees(r["pitchyaw_head"])) <= 40 + 1e-4).all()
    ident, expr = sp.params_from_code(r["latent_codes"])
    np.testing.assert_allclose(expr, r["expression_params"], atol=1e-5)
    np.testing.assert_allclose(r["neutral_vertice"], subject.neutral_vertices(), atol=1e-6)
    np.testing.assert_allclose(r["eyeball_centers"], subject.eye_centers, atol=1e-6)


@needs_gl
def test_landmarks_lie_on_the_rendered_surface(subject_file):
    r = _rows(subject_file)
    hits = 0
    for i in range(len(r["face_patch"])):
        if r["cam_index"][i] not in (8, 9):  # the near-frontal cameras (±12° yaw): these landmarks are visible
            continue
        pc = r["facial_landmarks_3d"][i] @ r["w2c_Rmat"][i].T + r["w2c_Tvec"][i]
        cams = syn_cameras_from_rows(r, [i], res=4 * r["face_patch"].shape[1])  # 4x finer than stored
        out = syn.render_views(_SUBJECT[0], r["pitchyaw_head"][i], r["pose"][i], r["expression_params"][i], cams,
                               light_dirs=r["light_dir"][i])
        for k in (30, 33, 36, 39, 42, 45):  # nose tip and base, eye corners
            u, v = 4 * r["facial_landmarks"][i, k]
            j, ii = int(u), int(v)
            # Eye corners sit on the lid rim, a fraction of a pixel from the socket: take the 3x3 best.
            depth = out["depth"][0, ii - 1:ii + 2, j - 1:j + 2]
            assert out["head_mask"][0, ii, j]
            assert np.abs(depth - pc[k, 2]).min() < 2e-3, (i, k, depth, pc[k, 2])
            hits += 1
    assert hits >= 24


_SUBJECT: list = []


@pytest.fixture(autouse=True)
def _keep_subject(subject):
    _SUBJECT[:] = [subject]


def syn_cameras_from_rows(r, rows, res=None):
    from toolkit.cameras import Camera

    cams = []
    for i in rows:
        V = np.eye(4, dtype=np.float32)
        V[:3, :3], V[:3, 3] = r["w2c_Rmat"][i], r["w2c_Tvec"][i]
        H, W = r["face_patch"].shape[1:3]
        c = Camera(torch.from_numpy(r["inmat"][i]), torch.from_numpy(V), W, H)
        cams.append(c if res is None else c.resized(res, res))
    return cams


@needs_gl
def test_masks_match_the_silhouette(subject_file, subject):
    import cv2

    r = _rows(subject_file)
    for i in (3, 8, 26):
        # Independent silhouette: fill every projected triangle of the posed head + eyeballs with OpenCV.
        R = so3_exp(torch.from_numpy(r["pose"][i, :3].astype(np.float64))).numpy()
        mesh = subject.scene_mesh(r["expression_params"][i], r["pitchyaw_head"][i])
        w = mesh["verts"] @ R.T + r["pose"][i, 3:]
        pc = w @ r["w2c_Rmat"][i].T + r["w2c_Tvec"][i]
        uv = (pc @ r["inmat"][i].T)[:, :2] / pc[:, 2:]
        H, W = r["head_mask"].shape[1:]
        sil = np.zeros((H * 8, W * 8), np.uint8)
        tris = np.round(uv[mesh["faces"]] * 8 - 0.5).astype(np.int32)  # pixel centres at (j + 0.5) / 8
        for tri in tris:  # one call per triangle: a multi-polygon fillPoly would cancel overlaps
            cv2.fillConvexPoly(sil, tri, 1)
        sil = cv2.resize(sil.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA) > 0.5
        m = r["head_mask"][i] > 0
        iou = (m & sil).sum() / (m | sil).sum()
        assert iou > 0.985, iou
        assert set(np.unique(r["head_mask"][i])) <= {0, 255}
        for key in ("left_eye_mask", "right_eye_mask"):
            assert not (r[key][i] & ~r["head_mask"][i]).any()
        assert not (r["left_eye_mask"][i] & r["right_eye_mask"][i]).any()
        # Eye masks sit between their eye corners.
        seen = 0
        for key, lo in (("left_eye_mask", 36), ("right_eye_mask", 42)):
            ys, xs = np.nonzero(r[key][i])
            if len(xs) > 3:  # a side view may hide one eye, never both
                seen += 1
                c = r["facial_landmarks"][i, lo:lo + 6].mean(0)
                assert np.hypot(xs.mean() + 0.5 - c[0], ys.mean() + 0.5 - c[1]) < 0.03 * W + 2
        assert seen >= 1, i
    # The images are white outside the head mask (rendered on white; anti-aliasing only touches pixels next to
    # the silhouette) and not white inside.
    img = r["face_patch"][8].astype(float)
    near = ndimage.binary_dilation(r["head_mask"][8] > 0)
    assert (img[~near] == 255).all()
    assert (img[near & (r["head_mask"][8] == 0)] < 255).any()
    assert img[r["head_mask"][8] > 0].mean() < 230


@needs_gl
@pytest.mark.parametrize("gaze_deg", [(0, 0), (6, -30), (-12, 25), (0, 38)])  # pupil clear of the lids
def test_rendered_iris_matches_labelled_gaze(subject, gaze_deg):
    """Back-project the rendered pupil's centroid onto the eyeball sphere: its direction is the gaze."""
    from toolkit.cameras import eth_xgaze_rig
    from train.data.generate import frame_cameras

    pose = np.array([0.05, -0.1, 0.02, 0.01, -0.005, 0.01])
    cams = frame_cameras(subject, pose, eth_xgaze_rig(), 512)
    cams = [cams[8], cams[9]]
    g = np.radians(gaze_deg)
    out = syn.render_views(subject, g, pose, [0, 0, 0, 0], cams)
    R = so3_exp(torch.from_numpy(pose[:3].copy())).numpy()
    for c, cam in enumerate(cams):
        V, K = cam.viewmat.numpy().astype(np.float64), cam.K.numpy().astype(np.float64)
        for k, key in enumerate(("left_eye_mask", "right_eye_mask")):
            pupil = out[key][c] & (out["eye_region"][c] == syn.EYE_PUPIL)
            assert pupil.sum() > 20
            ys, xs = np.nonzero(pupil)
            uv = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
            ray = np.linalg.solve(K, [uv[0], uv[1], 1.0])
            ray /= np.linalg.norm(ray)
            centre = V[:3, :3] @ (R @ subject.eye_centers[k] + pose[3:]) + V[:3, 3]
            # Nearest ray-sphere intersection (sphere radius shrunk to the pupil cap's mean depth).
            r_eff = subject.eye_radius
            b = ray @ centre
            disc = b * b - (centre @ centre - r_eff**2)
            hit = (b - math.sqrt(max(disc, 0.0))) * ray
            d_cam = hit - centre
            expect = V[:3, :3] @ R @ syn._pitchyaw_vec(g)
            ang = math.degrees(math.acos(np.clip(d_cam @ expect / np.linalg.norm(d_cam), -1, 1)))
            assert ang < 2.5, (gaze_deg, c, key, ang)
            np.testing.assert_allclose(out["pitchyaw_cam"][c],
                                       vector_to_pitchyaw(torch.from_numpy(expect)).numpy(), atol=1e-5)


@needs_gl
def test_generation_is_deterministic(subject_params, subject):
    from train.data.generate import generate_subject

    a, _, _ = generate_subject(subject_params, n_frames=1, res=32, seed=3, subject=subject)
    b, _, _ = generate_subject(subject_params, n_frames=1, res=32, seed=3, subject=subject)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_bad_parameters_are_rejected(subject):
    with pytest.raises(ToolkitError, match="identity"):
        sp.SubjectParams((0.0,) * 3)
    with pytest.raises(ToolkitError, match="identity"):
        sp.SubjectParams((2.0,) * len(sp.IDENTITY_NAMES))
    with pytest.raises(ToolkitError, match="mouth_open must lie in"):
        subject.head_vertices([1.5, 0, 0, 0])
    with pytest.raises(ToolkitError, match="expression"):
        subject.head_vertices([float("nan"), 0, 0, 0])
    with pytest.raises(ToolkitError, match="SubjectParams JSON"):
        sp.SubjectParams.from_json("{}")
    from toolkit.cameras import Camera, intrinsics

    cam = Camera(intrinsics(100, 100, 16, 16), torch.eye(4), 32, 32)
    with pytest.raises(ToolkitError, match="gaze"):
        syn.render_views(subject, [2.0, 0.0], np.zeros(6), [0, 0, 0, 0], [cam])
    with pytest.raises(ToolkitError, match="pose"):
        syn.render_views(subject, [0.0, 0.0], np.zeros(5), [0, 0, 0, 0], [cam])
    with pytest.raises(ToolkitError, match="no cameras"):
        syn.render_views(subject, [0.0, 0.0], np.zeros(6), [0, 0, 0, 0], [])
    with pytest.raises(ToolkitError, match="scale"):
        syn.render_views(subject, [0.0, 0.0], np.zeros(6), [0, 0, 0, 0], [cam], scale=0.0)


@needs_gl
def test_estimator_images_many_gazes_few_cameras_deterministic():
    from train.data.generate import estimator_images

    imgs, labels, lms = estimator_images([3, 4], n_frames=3, cameras_per_frame=2, res=32, seed=1)
    assert imgs.shape == (12, 3, 32, 32) and imgs.dtype == torch.uint8 and labels.shape == (12, 4)
    assert lms.shape == (12, 68, 2) and float(lms.min()) > 0 and float(lms.max()) < 32
    assert torch.isfinite(labels).all() and float(labels.abs().max()) <= math.pi
    # Each frame's two cameras see one gaze from two directions: different camera-frame labels.
    assert not torch.allclose(labels[0], labels[1])
    # Two processes, one subject each: the same images in the same order.
    again, labels2, lms2, iris = estimator_images([3, 4], n_frames=3, cameras_per_frame=2, res=32, seed=1,
                                                  iris_pixels=True, workers=2)
    assert torch.equal(imgs, again) and torch.equal(labels, labels2) and torch.equal(lms, lms2)
    # Visible iris pixels per eye: counts, some eye seen somewhere, never more than a small eye area.
    assert iris.shape == (12, 2) and iris.dtype == torch.int64
    assert int(iris.min()) >= 0 and 0 < int(iris.max()) < 32 * 32 // 20
    other, _, _ = estimator_images([3, 4], n_frames=3, cameras_per_frame=2, res=32, seed=2)
    assert not torch.equal(imgs, other)
    with pytest.raises(ToolkitError, match="cameras_per_frame"):
        estimator_images([3], n_frames=1, cameras_per_frame=19)
    with pytest.raises(ToolkitError, match="res must be"):
        estimator_images([3], n_frames=1, res=8)
    with pytest.raises(ToolkitError, match="no subject seeds"):
        estimator_images(range(5, 5), n_frames=1)
    with pytest.raises(ToolkitError, match="workers"):
        estimator_images([3], n_frames=1, workers=0)


def test_light_jitter_zero_is_one_frontal_light():
    from train.data.generate import sample_frames

    fixed = sample_frames(5, 8, light_jitter=0.0)["light"]
    np.testing.assert_allclose(fixed, np.tile([0.0, 0.0, -1.0], (8, 1)))
    varied = sample_frames(5, 8, light_jitter=0.6)["light"]
    np.testing.assert_allclose(np.linalg.norm(varied, axis=1), 1.0, atol=1e-6)
    assert np.abs(varied[:, :2]).max() > 0.05 and np.abs(varied[:, :2] / -varied[:, 2:]).max() <= 0.6 + 1e-6
    # Other draws are unchanged by the light spread (same seed, same gazes and poses).
    np.testing.assert_array_equal(sample_frames(5, 8, 0.0)["gaze"], sample_frames(5, 8, 0.6)["gaze"])
    with pytest.raises(ToolkitError, match="light_jitter"):
        sample_frames(5, 2, light_jitter=-1)


@needs_gl
def test_held_out_subjects_get_their_own_frame_count(tmp_path):
    from train.data.generate import synth_dataset

    paths = synth_dataset(tmp_path, n_subjects=2, n_frames=1, res=32, test_fraction=0.5, test_frames=2,
                          log=lambda *a: None)
    rows = []
    for p in paths:
        with h5py.File(p) as f:
            rows.append(len(f["pitchyaw_head"]))
            gazes = np.unique(np.asarray(f["pitchyaw_head"]), axis=0)
        assert len(gazes) == rows[-1] // 18  # one gaze per frame, each seen by the 18 rig cameras
    assert rows == [18, 36]
    assert json.loads((tmp_path / "split.json").read_text()) == {"train": ["subject0000.h5"], "test": ["subject0001.h5"]}
    with pytest.raises(ToolkitError, match=r"test_frames: expected frames per subject in \[1, 100000\], got 0"):
        synth_dataset(tmp_path / "bad", n_subjects=2, n_frames=1, res=32, test_frames=0, log=lambda *a: None)


def test_generator_counts_are_bounded_before_any_work(tmp_path, monkeypatch):
    from train.data.generate import estimator_images, generate_subject, synth_dataset
    from train.data.subject_params import SubjectParams
    from train.data.synthetic import build_subject

    monkeypatch.setenv("DITGAZE_MEMORY_GB", "2")
    params = SubjectParams.sample(1)
    with pytest.raises(ToolkitError, match=r"subdivisions: expected icosphere subdivisions in \[0, 7\], got 12"):
        build_subject(params, subdivisions=12)
    with pytest.raises(ToolkitError, match=r"n_frames: expected frames per subject in \[1, 100000\]"):
        generate_subject(params, n_frames=10**12)
    with pytest.raises(ToolkitError, match=r"seed: expected a seed"):
        generate_subject(params, n_frames=1, seed=-1)
    with pytest.raises(ToolkitError, match=r"generate_subject: 3000 frames x 18 cameras at 512 pixels would allocate"):
        generate_subject(params, n_frames=3000, res=512)
    with pytest.raises(ToolkitError, match=r"n_subjects: expected a number of subject files in \[1, 10000\]"):
        synth_dataset(tmp_path / "s", n_subjects=10**12, n_frames=1, log=None)
    with pytest.raises(ToolkitError, match=r"seed: expected a seed in \[0, 4294967295\], got -1"):
        synth_dataset(tmp_path / "s", n_subjects=1, n_frames=1, seed=-1, log=None)
    with pytest.raises(ToolkitError, match=r"estimator_images: 4000000 images at 256 pixels would allocate"):
        estimator_images(range(1000), n_frames=2000, res=256)
    assert not (tmp_path / "s").exists()


def test_kappa_turns_each_eye_temporally_and_leaves_default_subjects_as_they_were():
    """SubjectParams.kappa: the optical axis = the gaze label + (kappa pitch, ± kappa yaw), yaw temporal per eye;
    a subject sampled without it is the same subject, written the same way."""
    import json

    import numpy as np

    from train.data.subject_params import SubjectParams
    from train.data.synthetic import build_subject

    plain, turned = SubjectParams.sample(3), SubjectParams.sample(3, kappa_deg=5.0)
    assert plain.identity == turned.identity and plain.kappa == (0.0, 0.0) and "kappa" not in json.loads(plain.to_json())
    assert SubjectParams.from_json(turned.to_json()) == turned and 0.02 < turned.kappa[1] < 0.16
    a, b = build_subject(plain, subdivisions=1), build_subject(turned, subdivisions=1)
    ea, eb = a.eyeball_vertices([0.0, 0.0]), b.eyeball_vertices([0.0, 0.0])

    def front(subject, eyes):  # each eyeball's axis: the rotation taking its template (looking along -z) to it
        out = []
        for e, c in zip(eyes, subject.eye_centers):
            Rt = np.linalg.lstsq(subject.eye_local, (e - c) / subject.eye_radius, rcond=None)[0]
            out.append(Rt.T @ np.array([0.0, 0.0, -1.0]))
        return out

    yaw = lambda g: np.degrees(np.arctan2(-g[0], -g[2]))  # noqa: E731  (ETH-XGaze: + yaw towards -x)
    fa, fb = front(a, ea), front(b, eb)
    assert abs(yaw(fa[0])) < 1e-3 and abs(yaw(fa[1])) < 1e-3
    k = np.degrees(turned.kappa[1])
    assert abs(yaw(fb[0]) - k) < 1e-3 and abs(yaw(fb[1]) + k) < 1e-3  # image-left eye (x < 0) turns to -x
