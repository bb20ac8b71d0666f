"""Tiny subject files written the way each peer's pipeline writes them, from known native ground truth.

:func:`native_truth` draws a few rows in the native conventions (docs/data.md): head poses with scale != 1,
roll-free normalized cameras, gazes, landmarks, vertices. The writers then store them as the peers do; the
citations are to the peers' code (ucwxb/GazeGaussian bb8fac9, AlessandroRuzzi/GazeNeRF eb0a5f1,
xucong-zhang/ETH-XGaze ef9bff0). The writers compute each peer's conventions their own way, without
``train.data.layouts``, so the tests check that module against the peers and not against itself.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

RES, N_VERTS, DISTANCE = 16, 12, 0.6
# focal length: res * DISTANCE / 0.26, so 0.26 m at the face fills the image, as the native generator's cameras
FACE_CENTRE_LANDMARKS = [36, 39, 42, 45, 48, 54]  # docs/data.md: the normalized camera looks at their mean


@dataclass
class Truth:
    rows: dict[str, np.ndarray]  # native rows (train.data.format.REQUIRED + pitchyaw_cam), float32
    landmarks_head: np.ndarray  # [N, 68, 3] float64 head-frame landmarks: what pose and scale place
    head_in_camera: np.ndarray  # [N, 3, 3] float64 w2c_Rmat @ R(pose): the head axes seen from the camera


def rodrigues(v: np.ndarray) -> np.ndarray:
    """[..., 3] axis-angle -> [..., 3, 3] rotation (column vectors)."""
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    k = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def native_vector(py: np.ndarray) -> np.ndarray:
    """docs/data.md: g = (-cos p sin y, -sin p, -cos p cos y), pitch = asin(-g_y), yaw = atan2(-g_x, -g_z)."""
    p, y = py[..., 0], py[..., 1]
    return np.stack([-np.cos(p) * np.sin(y), -np.sin(p), -np.cos(p) * np.cos(y)], -1)


def native_pitchyaw(g: np.ndarray) -> np.ndarray:
    g = g / np.linalg.norm(g, axis=-1, keepdims=True)
    return np.stack([np.arcsin(-g[..., 1]), np.arctan2(-g[..., 0], -g[..., 2])], -1)


def _normalized_camera(face_world: np.ndarray, head_x: np.ndarray, towards: np.ndarray):
    """ETH-XGaze's normalization (normalization_example.py L56-62): forward to the face centre, down =
    forward x head-x, right = down x forward; the camera sits DISTANCE from the face centre along ``towards``."""
    centre = face_world + DISTANCE * towards
    forward = -towards
    down = np.cross(forward, head_x)
    down /= np.linalg.norm(down)
    right = np.cross(down, forward)
    R = np.stack([right / np.linalg.norm(right), down, forward])
    return R, -R @ centre


def native_truth(n_frames: int = 2, n_cams: int = 3, seed: int = 0, *, res: int = RES, noise_px: float = 0.5) -> Truth:
    """``n_frames`` x ``n_cams`` rows at ``res``², frame-major, with exact native labels (2D landmarks carry
    +-``noise_px`` of detector-like noise, as real files' do)."""
    rng = np.random.default_rng(seed)
    focal = res * DISTANCE / 0.26
    n = n_frames * n_cams
    base = rng.normal(0, 0.035, (68, 3)) * [1.0, 1.0, 0.4]
    verts0 = rng.normal(0, 0.06, (N_VERTS, 3))
    out = {k: [] for k in ("lm_head", "q", "v", "R", "t", "pose", "scale", "M", "gaze", "code")}
    for f in range(n_frames):
        pose = np.concatenate([rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.015, 0.015, 3)])
        scale, Rp = 1.07 + 0.02 * f, rodrigues(pose[:3])  # real fits have scale != 1
        lm_head = base + rng.normal(0, 0.002, base.shape)  # this frame's expression
        q = scale * lm_head @ Rp.T + pose[3:]
        v = scale * (verts0 + rng.normal(0, 0.002, verts0.shape)) @ Rp.T + pose[3:]
        gaze, code = rng.uniform(-0.4, 0.4, 2), rng.normal(0, 1, 144)
        for c in range(n_cams):
            yaw, pitch = -0.5 + c * 1.0 / max(n_cams - 1, 1), 0.25 * (-1) ** c
            towards = np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), -np.cos(yaw) * np.cos(pitch)])
            R, t = _normalized_camera(q[FACE_CENTRE_LANDMARKS].mean(0), Rp[:, 0], towards)
            for k, val in zip(out, (lm_head, q, v, R, t, pose, [scale], R @ Rp, gaze, code)):
                out[k].append(val)
    a = {k: np.asarray(v, np.float64) for k, v in out.items()}
    cam = np.einsum("nij,nkj->nki", a["R"], a["q"]) + a["t"][:, None]
    uv = focal * cam[..., :2] / cam[..., 2:] + res / 2 + rng.uniform(-noise_px, noise_px, (n, 68, 2))
    z = a["M"][:, :, 2]  # head +z (into the head) in the camera: the face looks along -z
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    rows = {
        "face_patch": rng.integers(0, 256, (n, res, res, 3), dtype=np.uint8),
        "head_mask": (rng.random((n, res, res)) < 0.6).astype(np.uint8) * 255,
        "left_eye_mask": (rng.random((n, res, res)) < 0.1).astype(np.uint8) * 255,
        "right_eye_mask": (rng.random((n, res, res)) < 0.1).astype(np.uint8) * 255,
        "facial_landmarks": f32(uv), "facial_landmarks_3d": f32(a["q"]), "latent_codes": f32(a["code"]),
        "pose": f32(a["pose"]), "scale": f32(a["scale"]), "w2c_Rmat": f32(a["R"]), "w2c_Tvec": f32(a["t"]),
        "inmat": f32(np.tile([[focal, 0, res / 2], [0, focal, res / 2], [0, 0, 1]], (n, 1, 1))),
        "pitchyaw_head": f32(a["gaze"]),
        "face_head_pose": f32(np.stack([np.arcsin(z[:, 1]), np.arctan2(z[:, 0], z[:, 2])], -1)),
        "cam_index": np.tile(np.arange(n_cams, dtype=np.int32), n_frames),
        "frame_index": np.repeat(np.arange(n_frames, dtype=np.int32), n_cams),
        "vertice": f32(a["v"]),
        "pitchyaw_cam": f32(native_pitchyaw(np.einsum("nij,nj->ni", a["M"], native_vector(a["gaze"])))),
    }
    return Truth(rows, a["lm_head"], a["M"])


# ------------------------------------------------------------------------------------------------------------
# The peers' label conventions, each computed their way
# ------------------------------------------------------------------------------------------------------------

def _gaze_target(truth: Truth) -> tuple[np.ndarray, np.ndarray]:
    """A gaze target 0.5 m from the face centre along the true gaze, in camera coordinates, and that centre
    (the annotation's 3D gaze point, ETH-XGaze normalization_example.py L285)."""
    g = truth.rows["pitchyaw_head"].astype(np.float64)
    fc = np.tile([0.0, 0.0, DISTANCE], (len(g), 1))
    return fc + 0.5 * np.einsum("nij,nj->ni", truth.head_in_camera, native_vector(g)), fc


def gazenerf_head_gaze(truth: Truth) -> np.ndarray:
    """GazeNeRF utils/gaze_estimation_utils.py L35-51: v = inv(hR) @ (gaze point - face centre);
    pitch = arcsin(v[1]), yaw = arctan2(-v[0], -v[2]) (of the normalized v)."""
    gc, fc = _gaze_target(truth)
    v = np.einsum("nji,nj->ni", truth.head_in_camera, gc - fc)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.stack([np.arcsin(v[:, 1]), np.arctan2(-v[:, 0], -v[:, 2])], -1)


def normalized_head_pose(truth: Truth) -> np.ndarray:
    """GazeNeRF dataset_pre_processing.py L50-77 (= ETH-XGaze normalization_example.py L56-69, L327-330):
    R from the face centre and head x-axis, hR_norm = R @ hR, Zv = hR_norm[:, 2], (asin Zv[1], atan2(Zv[0], Zv[2]))."""
    out = []
    for hR in truth.head_in_camera:
        forward = np.array([0.0, 0.0, 1.0])  # the face centre lies on the normalized camera's axis
        down = np.cross(forward, hR[:, 0])
        down /= np.linalg.norm(down)
        right = np.cross(down, forward)
        Zv = (np.stack([right / np.linalg.norm(right), down, forward]) @ hR)[:, 2]
        out.append([np.arcsin(Zv[1]), np.arctan2(Zv[0], Zv[2])])
    return np.asarray(out)


def xgaze_face_gaze(truth: Truth) -> np.ndarray:
    """ETH-XGaze normalization_example.py L73-75, L313-314: g = R @ (gc - face centre), normalized;
    theta = arcsin(-g[1]), phi = arctan2(-g[0], -g[2])."""
    gc, fc = _gaze_target(truth)
    g = (gc - fc) / np.linalg.norm(gc - fc, axis=1, keepdims=True)
    return np.stack([np.arcsin(-g[:, 1]), np.arctan2(-g[:, 0], -g[:, 2])], -1)


def inv_inmat(K: np.ndarray) -> np.ndarray:
    """GazeNeRF surface_fitting/nl3dmm/fitting_nl3dmm.py L324-328."""
    inv = np.tile(np.eye(3), (len(K), 1, 1))
    inv[:, 0, 0], inv[:, 1, 1] = 1 / K[:, 0, 0], 1 / K[:, 1, 1]
    inv[:, 0, 2], inv[:, 1, 2] = -inv[:, 0, 0] * K[:, 0, 2], -inv[:, 1, 1] * K[:, 1, 2]
    return inv


def _create(f, key: str, data, dtype, lzf: bool = True) -> None:
    """GazeNeRF's datasets: one chunk a row, lzf for all but the indices and landmarks (L258-381)."""
    data = np.asarray(data, dtype)
    f.create_dataset(key, data=data, chunks=(1,) + data.shape[1:], compression="lzf" if lzf else None)


def _gazenerf_common(f, truth: Truth, R: np.ndarray, t: np.ndarray) -> None:
    """The keys GazeNeRF's ETH-XGaze branch writes (dataset_pre_processing.py L258-381), float64 (np.float)."""
    r = truth.rows
    n = len(r["face_patch"])
    _create(f, "frame_index", r["frame_index"].reshape(n, 1), np.uint8, lzf=False)  # L260-265
    _create(f, "cam_index", r["cam_index"].reshape(n, 1), np.uint8, lzf=False)  # L266-271
    _create(f, "facial_landmarks", r["facial_landmarks"], np.float64, lzf=False)  # L272-277
    for k in ("face_patch", "left_eye_mask", "right_eye_mask", "head_mask"):  # L278-305, BGR as read by cv2
        _create(f, k, r[k], np.uint8)
    _create(f, "w2c_Rmat", R, np.float64)  # L313-326
    _create(f, "w2c_Tvec", t, np.float64)
    _create(f, "inmat", r["inmat"], np.float64)  # L327-333
    _create(f, "c2w_Rmat", R.transpose(0, 2, 1), np.float64)  # fitting_nl3dmm.py L320-322
    _create(f, "c2w_Tvec", -np.einsum("nji,nj->ni", R, t), np.float64)
    _create(f, "inv_inmat", inv_inmat(r["inmat"].astype(np.float64)), np.float64)
    # L402: columns 2-3 of the annotation row of the frame's first camera; no native meaning, never converted
    _create(f, "pitchyaw", np.zeros((n, 2)), np.float64)
    _create(f, "pitchyaw_head", gazenerf_head_gaze(truth), np.float64)  # L423-430
    _create(f, "pitchyaw_3d", _gaze_target(truth)[0], np.float64)  # L432-436: the 3D gaze point
    _create(f, "face_head_pose", normalized_head_pose(truth), np.float64)  # L438-441


def gazenerf_codes_from_native(codes: np.ndarray, seed: int = 1) -> np.ndarray:
    """[N, 306] GazeNeRF codes holding native ones [N, 144]: the 80 identity dims zero-padded to NL3DMM's 100, the 64
    expression dims to its 79, random texture (100) and illumination (27) dims, the same for a row's frame-mates
    when their native codes are (configs/gazenerf_options.py L11-14; dataset_pre_processing.py L391-395)."""
    codes = np.asarray(codes, np.float64)
    uniq, inverse = np.unique(codes, axis=0, return_inverse=True)
    rest = np.random.default_rng(seed).normal(0, 1, (len(uniq), 127))[inverse.reshape(-1)]
    z = lambda k: np.zeros((len(codes), k))  # noqa: E731
    return np.concatenate([codes[:, :80], z(20), codes[:, 80:144], z(15), rest], 1)


def write_gazenerf(path, truth: Truth, seed: int = 1, *, native_codes: bool = False, optional: bool = True) -> np.ndarray:
    """A GazeNeRF file (dataset_pre_processing.py L80-466); returns the 306-d codes it wrote: random per frame, or
    with ``native_codes`` the truth's (:func:`gazenerf_codes_from_native`). ``optional=False`` leaves out
    ``pitchyaw`` (an annotation column with no native meaning), so the keys are exactly the layout's required."""
    r = truth.rows
    R64, t64 = r["w2c_Rmat"].astype(np.float64), r["w2c_Tvec"].astype(np.float64)
    Rp = rodrigues(r["pose"][:, :3].astype(np.float64))
    # fitting_nl3dmm.py L276-279: the head pose is folded into w2c (w2c @ c2l), unit scale (L170)
    R = R64 @ Rp
    t = np.einsum("nij,nj->ni", R64, r["pose"][:, 3:].astype(np.float64)) + t64
    # L391-395: every row of a frame holds the same code (the mean of its first three views' fits);
    # 100 identity + 79 expression + 100 texture + 27 illumination (configs/gazenerf_options.py L11-14)
    frame = r["frame_index"].reshape(-1)
    if native_codes:
        codes = gazenerf_codes_from_native(r["latent_codes"], seed)
    else:
        codes = np.random.default_rng(seed).normal(0, 1, (frame.max() + 1, 306))[frame]
    with h5py.File(path, "w") as f:
        _gazenerf_common(f, truth, R, t)
        _create(f, "latent_codes", codes, np.float64)  # L306-312
        if not optional:
            del f["pitchyaw"]
    return codes


def write_gazegaussian(path, truth: Truth, gazenerf_keys: bool = True) -> None:
    """A GazeGaussian file as its loader reads it (dataloader/eth_xgaze.py L414-480). Its preprocessing is
    not published: the GazeNeRF keys and dtypes come from GazeNeRF's pipeline, which it "mainly follows"
    (README.md L39); ``gazenerf_keys=False`` keeps only the keys its loader reads."""
    r = truth.rows
    R, t = r["w2c_Rmat"].astype(np.float64), r["w2c_Tvec"].astype(np.float64)
    with h5py.File(path, "w") as f:
        _gazenerf_common(f, truth, R, t)  # w2c: world -> camera, rendered as such (L464-472, graphics_utils.py L36-40)
        if not gazenerf_keys:
            for k in ("frame_index", "c2w_Rmat", "c2w_Tvec", "inv_inmat", "pitchyaw", "pitchyaw_3d"):
                del f[k]
        _create(f, "latent_codes", r["latent_codes"], np.float32)  # [:80] identity, [80:144] expression (L447-448)
        _create(f, "pose", r["pose"], np.float32)  # axis-angle + translation (models/gaussian_model.py L272-278)
        _create(f, "scale", r["scale"].reshape(-1, 1), np.float32)  # scale[idx, :] (L480)
        for k in ("facial_landmarks_3d", "vertice"):
            # L440 reads q = (p - w2c_Tvec) @ w2c_Rmat^T as the world (pose) frame, so p = q @ w2c_Rmat + w2c_Tvec
            q = r[k].astype(np.float64)
            _create(f, k, np.einsum("nki,nij->nkj", q, R) + t[:, None], np.float32)


def write_xgaze(path, truth: Truth, labels: bool = True, landmarks: bool = False) -> None:
    """An ETH-XGaze release file (normalization_example.py L295-331). The release holds no landmarks (its keys:
    TWWinde/ETH--XGAZE h5reader.py L9-14); test subjects hold no gaze labels (data_loader.py L66)."""
    r = truth.rows
    n = len(r["face_patch"])
    raw = rodrigues(np.random.default_rng(2).uniform(-0.4, 0.4, (n, 3)))  # the original camera's rotation
    with h5py.File(path, "w") as f:
        _create(f, "frame_index", r["frame_index"].reshape(n, 1), np.int64, lzf=False)  # L295-296, np.int
        _create(f, "cam_index", r["cam_index"].reshape(n, 1), np.int64, lzf=False)  # L297-298
        if landmarks:
            _create(f, "facial_landmarks", r["facial_landmarks"], np.float64, lzf=False)  # L299-300
        _create(f, "face_patch", r["face_patch"], np.uint8)  # L302-304
        _create(f, "face_mat_norm", r["w2c_Rmat"] @ raw.transpose(0, 2, 1), np.float64, lzf=False)  # L305, L324
        if labels:
            _create(f, "face_gaze", xgaze_face_gaze(truth), np.float64, lzf=False)  # L307, L313-315
        _create(f, "face_head_pose", normalized_head_pose(truth), np.float64, lzf=False)  # L309, L327-331


def subset(truth: Truth, rows) -> Truth:
    """``truth`` with only ``rows`` (indices or a mask), as a file missing some of its views would hold it."""
    return Truth({k: v[rows] for k, v in truth.rows.items()}, truth.landmarks_head[rows], truth.head_in_camera[rows])


def write_ditgaze(path, truth: Truth) -> Path:
    from train.data.format import write_subject_h5

    return write_subject_h5(path, truth.rows)


def write_native_folder(folder: Path, first_seed: int) -> Path:
    """Three native subjects (2 frames x 3 cameras) and their split.json: subjects 0 and 1 train, 2 is held out."""
    for i in range(3):
        write_ditgaze(folder / f"subject{i:04d}.h5", native_truth(n_frames=2, n_cams=3, seed=first_seed + i))
    (folder / "split.json").write_text(json.dumps({"train": ["subject0000", "subject0001"], "test": ["subject0002"]}))
    return folder


def write_peer_split(path, train: list[str], val: list[str]) -> Path:
    """GazeGaussian configs/dataset/eth_xgaze/train_test_split.json (= GazeNeRF data/eth_xgaze/...): entries
    "subject0012.h5" without the "xgaze_" prefix its loaders add (dataloader/eth_xgaze.py L276)."""
    spec = {"train": [f"{s}.h5" for s in train], "val": [f"{s}.h5" for s in val],
            "val_gaze": [f"{s}.h5" for s in val], "test": [], "test_specific": []}
    Path(path).write_text(json.dumps(spec, indent=2))
    return Path(path)


def read_rows(path) -> tuple[set[str], dict[str, tuple], dict[str, np.ndarray]]:
    """A fixture's keys, shapes and arrays."""
    with h5py.File(path, "r") as f:
        rows = {k: f[k][()] for k in f}
    return set(rows), {k: v.shape for k, v in rows.items()}, rows
