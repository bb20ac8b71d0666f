"""Generate synthetic subject files: random frames (gaze, head pose, expression, light) × an 18-camera rig.

Row order is frame-major: row = frame · n_cameras + camera. Every image of a frame shares one mesh upload.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from toolkit.cameras import Camera, eth_xgaze_rig
from toolkit.errors import ToolkitError
from toolkit.limits import check_allocation, check_count
from train.data.dataset import held_out_count
from train.data.format import write_subject_h5
from train.data.poses import normalized_camera, pose_matrix, sample_head_pose
from train.data.subject_params import (
    EXPRESSION_NAMES,
    IDENTITY_NAMES,
    SubjectParams,
    latent_code,
    sample_expression,
)
from train.data.synthetic import Subject, build_subject, render_views

GAZE_RANGE_DEG = 40.0
NORM_DISTANCE, NORM_CROP = 0.6, 0.26  # metres: normalized camera distance and face-crop width
RIG_RADIUS = 1.0
LIGHT_JITTER = 0.6  # default spread of the per-frame light direction (see sample_frames)


def rgb_to_u8(rgb: np.ndarray) -> np.ndarray:
    """Rendered float RGB in [0, 1] -> uint8, rounded: how every stored or estimator image is quantized."""
    return np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8)


RES_RANGE = (16, 2048)
"""The image sizes the generator renders, pixels (inclusive)."""

MAX_SUBJECTS = 10_000
"""Subjects of one dataset: files are named subject0000 ... subject9999, more would not sort in order."""

MAX_FRAMES = 100_000
"""Frames of one subject (each seen by the 18 rig cameras; memory bounds most counts well below this)."""

SEED_RANGE = (0, 2**32 - 1)
"""Dataset seeds, as the run configuration's."""

SCALE_RANGE = (0.5, 2.0)
"""Head scales the generator renders (inclusive; x_world = scale · R x_head + t, docs/data.md): real fits lie near 1,
and at 2 a head (~0.15 m wide) overflows the normalized crop's 0.26 m."""


def subject_bytes(n_frames: int, res: int, n_cameras: int = 18) -> int:
    """Bytes generating one subject holds before its file is written: ~290 KB + 64 res² per image were measured
    (float RGB, masks, the posed 10242-vertex mesh and their copies), plus the file's image built in memory."""
    return n_frames * n_cameras * (420_000 + 72 * res * res)


def check_subject_memory(n_frames: int, res: int, what: str, hint: str = "lower the frames or the resolution",
                         n_cameras: int = 18) -> None:
    check_allocation(subject_bytes(n_frames, res, n_cameras), what, hint)


def _check_res(res: int) -> None:
    if not RES_RANGE[0] <= res <= RES_RANGE[1]:
        raise ToolkitError(f"res must be in [{RES_RANGE[0]}, {RES_RANGE[1]}], got {res}")


def check_scale(scale) -> float:
    """``scale`` as a float in :data:`SCALE_RANGE` (a real number; NaN and bools are refused)."""
    ok = isinstance(scale, (int, float, np.integer, np.floating)) and not isinstance(scale, (bool, np.bool_))
    if not ok or not SCALE_RANGE[0] <= float(scale) <= SCALE_RANGE[1]:
        raise ToolkitError(f"scale must be a number in [{SCALE_RANGE[0]}, {SCALE_RANGE[1]}], got {scale!r}")
    return float(scale)


@contextlib.contextmanager
def _torch_threads(n: int):
    # Per-vertex shape maths is tiny; torch's thread pool only adds contention (10x slower under load).
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def sample_frames(seed: int, n_frames: int, light_jitter: float = LIGHT_JITTER) -> dict[str, np.ndarray]:
    """Per-frame random gaze [n, 2] (±40° head frame), pose [n, 6], expression [n, 4], light [n, 3].

    The light direction is (x, y, -1) normalized with x, y uniform in ±``light_jitter`` (0: one frontal light
    for every frame, like the full-lighting frames of ETH-XGaze that GazeNeRF and GazeGaussian train on).
    """
    if not 0.0 <= light_jitter <= 2.0:
        raise ToolkitError(f"light_jitter must be in [0, 2], got {light_jitter}")
    rng = np.random.default_rng([seed, 11])
    gaze = rng.uniform(-1, 1, (n_frames, 2)) * math.radians(GAZE_RANGE_DEG)
    pose = sample_head_pose(rng, n_frames)
    expr = sample_expression(rng, n_frames)
    light = np.concatenate([rng.uniform(-1, 1, (n_frames, 2)) * light_jitter, -np.ones((n_frames, 1))], 1)
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    return {"gaze": gaze.astype(np.float32), "pose": pose, "expression": expr, "light": light.astype(np.float32)}


def frame_cameras(subject: Subject, pose, rig: list[Camera], res: int, scale: float = 1.0) -> list[Camera]:
    """The normalized cameras of one frame: each rig camera aimed at the posed face centre."""
    R, t = pose_matrix(pose)
    face_w = scale * R @ subject.face_center + t
    return [normalized_camera(c, face_w, R, res, distance=NORM_DISTANCE, crop=NORM_CROP) for c in rig]


def generate_subject(params: SubjectParams, *, n_frames: int, res: int = 128, seed: int | None = None,
                     rig: list[Camera] | None = None, subject: Subject | None = None,
                     light_jitter: float = LIGHT_JITTER, scale: float = 1.0):
    """Render one subject: returns (rows, subject_arrays, attrs) ready for ``write_subject_h5``.

    ``scale`` (:data:`SCALE_RANGE`): the head scale of every row (x_world = scale · R x_head + t), stored in the
    rows' ``scale`` [N, 1]; each camera is aimed at the scaled face. The head frame (``neutral_vertice``,
    ``eyeball_centers``) and the gaze labels do not depend on it."""
    check_count(n_frames, "n_frames", 1, MAX_FRAMES, "frames per subject")
    _check_res(res)
    scale = check_scale(scale)
    seed = params.seed if seed is None else check_count(seed, "seed", 0, 2**64 - 1, "a seed")
    rig = rig or eth_xgaze_rig(radius=RIG_RADIUS)
    check_subject_memory(n_frames, res, f"generate_subject: {n_frames} frames x {len(rig)} cameras at {res} pixels",
                         n_cameras=len(rig))
    with _torch_threads(1):
        subject = subject or build_subject(params)
        fr = sample_frames(seed, n_frames, light_jitter)
        chunks = []
        for i in range(n_frames):
            cams = frame_cameras(subject, fr["pose"][i], rig, res, scale=scale)
            out = render_views(subject, fr["gaze"][i], fr["pose"][i], fr["expression"][i], cams, scale=scale,
                               light_dirs=fr["light"][i])
            out["light_dir"] = np.tile(fr["light"][i], (len(cams), 1))
            out["cam_index"] = np.arange(len(cams), dtype=np.int32)
            out["frame_index"] = np.full(len(cams), i, dtype=np.int32)
            chunks.append(out)
        out = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    u8 = lambda m: (m.astype(np.uint8) * 255)  # noqa: E731
    rgb8 = rgb_to_u8(out["rgb"])
    n = len(rgb8)
    rows = {
        "face_patch": np.ascontiguousarray(rgb8[..., ::-1]),  # BGR, as the ETH-XGaze files
        "head_mask": u8(out["head_mask"]),
        "left_eye_mask": u8(out["left_eye_mask"]),
        "right_eye_mask": u8(out["right_eye_mask"]),
        "facial_landmarks": out["landmarks_2d"],
        "facial_landmarks_3d": out["landmarks_3d"],
        "latent_codes": latent_code(np.tile(params.vector(), (n, 1)), out["expression"]).astype(np.float32),
        "pose": out["pose"],
        "scale": out["scale"],
        "w2c_Rmat": out["w2c_R"],
        "w2c_Tvec": out["w2c_T"],
        "inmat": out["K"],
        "pitchyaw_head": out["pitchyaw_head"],
        "face_head_pose": out["face_head_pose"],
        # [N, 1], as the peers' files store and index them (cam_index[idx, :]: docs/data.md, Layouts)
        "cam_index": out["cam_index"].reshape(-1, 1),
        "frame_index": out["frame_index"].reshape(-1, 1),
        "vertice": out["vertice"],
        "pitchyaw_cam": out["pitchyaw_cam"],
        "expression_params": out["expression"],
        "light_dir": out["light_dir"].astype(np.float32),
    }
    subj = {
        "neutral_vertice": subject.neutral_vertices(),
        "mesh_faces": subject.head_faces.astype(np.int32),
        "eyeball_centers": subject.eye_centers.astype(np.float32),
        "eyeball_radii": np.full(2, subject.eye_radius, np.float32),
        "identity_params": params.vector(),
    }
    attrs = {
        "source": "train.data.synthetic",
        "subject_params": params.to_json(),
        "frame_seed": int(seed),
        "n_cameras": len(rig),
        "rig": json.dumps({"kind": "eth_xgaze_rig", "radius": RIG_RADIUS}),
        "normalization": json.dumps({"distance": NORM_DISTANCE, "crop": NORM_CROP}),
        "identity_names": json.dumps(list(IDENTITY_NAMES)),
        "expression_names": json.dumps(list(EXPRESSION_NAMES)),
        "ambient": 0.45,
    }
    return rows, subj, attrs


def synth_dataset(out_dir: str | os.PathLike, *, n_subjects: int, n_frames: int, res: int = 128, seed: int = 0,
                  test_fraction: float = 0.25, light_jitter: float = LIGHT_JITTER, log=print,
                  test_frames: int | None = None, scale: float = 1.0, kappa_deg: float = 0.0) -> list[Path]:
    """Write ``subject0000.h5`` ... plus ``split.json`` into ``out_dir``; returns the subject files.

    Every subject is rendered at head scale ``scale`` (:func:`generate_subject`); with ``kappa_deg`` > 0 each
    has eyes whose optical axes differ from the gaze label by a κ of its own (``SubjectParams.sample``).

    The held-out subjects (the last ``test_fraction``) get ``test_frames`` frames each (default ``n_frames``).
    Evaluation pairs take their input from the first half of a subject's rows and their target from the second
    half (``train.data.pairing.synthetic_pairs``), so ``test_frames`` sets how many distinct redirections the
    gaze error averages over."""
    check_count(n_subjects, "n_subjects", 1, MAX_SUBJECTS, "a number of subject files")
    check_count(seed, "seed", *SEED_RANGE, "a seed")
    scale = check_scale(scale)
    if not (isinstance(kappa_deg, (int, float)) and 0 <= kappa_deg <= 15):
        raise ToolkitError(f"kappa_deg must be a number of degrees in [0, 15], got {kappa_deg!r}")
    for name, frames in (("n_frames", n_frames), ("test_frames", test_frames)):
        if frames is not None:
            check_count(frames, name, 1, MAX_FRAMES, "frames per subject")
            check_subject_memory(frames, res, f"synth_dataset: one subject of {frames} frames at {res} pixels")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ToolkitError(f"{out_dir}: exists and is not a directory")
    paths, n_images = [], 0
    t0 = time.perf_counter()
    rig = eth_xgaze_rig(radius=RIG_RADIUS)
    n_test = held_out_count(n_subjects, test_fraction)
    for s in range(n_subjects):
        params = SubjectParams.sample(seed * 100003 + s, kappa_deg)
        frames = test_frames if test_frames is not None and s >= n_subjects - n_test else n_frames
        rows, subj, attrs = generate_subject(params, n_frames=frames, res=res, rig=rig, light_jitter=light_jitter,
                                             scale=scale)
        p = write_subject_h5(out_dir / f"subject{s:04d}.h5", rows, subject=subj, attrs=attrs)
        paths.append(p)
        n_images += len(rows["face_patch"])
        log(f"{p}: {len(rows['face_patch'])} images ({n_images / (time.perf_counter() - t0):.1f} images/s)")
    split = {"train": [p.name for p in paths[: n_subjects - n_test]], "test": [p.name for p in paths[n_subjects - n_test:]]}
    from toolkit.io import atomic_write_json

    atomic_write_json(out_dir / "split.json", split)
    return paths


def estimator_images(subject_seeds, *, n_frames: int, cameras_per_frame: int = 2, res: int = 128,
                     seed: int = 0, log=None, iris_pixels: bool = False, workers: int = 1) -> tuple[torch.Tensor, ...]:
    """Training images for a gaze estimator: many gazes per subject, few rig cameras per gaze.

    The subject files of :func:`synth_dataset` show each (gaze, pose, expression) frame to all 18 cameras,
    which is what multi-view fitting wants but starves an estimator of distinct eye states: it then
    learns to recognise the frame instead of reading the eyes. Here every subject gets ``n_frames``
    random frames, each seen by ``cameras_per_frame`` distinct rig cameras drawn at random.

    Args:
        subject_seeds: seeds for :meth:`SubjectParams.sample` (keep them disjoint from any evaluation subjects).
        workers: processes rendering contiguous runs of subjects at once (the renderer is single-threaded;
            the images and their order do not depend on it).
    Returns:
        images [N, 3, res, res] uint8 RGB, labels [N, 4] float32 radians: camera-frame gaze (pitch, yaw)
        then camera-frame head pose (pitch, yaw), landmarks [N, 68, 2] float32 pixels;
        N = len(subject_seeds) · n_frames · cameras_per_frame; with ``iris_pixels`` also [N, 2] int64, the
        visible iris + pupil pixels of the image-left and image-right eye (how readable each eye is: 0 when
        the lids, the nose or the view hide it).
    """
    n_cams = len(eth_xgaze_rig(radius=RIG_RADIUS))
    if not 1 <= cameras_per_frame <= n_cams:
        raise ToolkitError(f"cameras_per_frame must be in [1, {n_cams}], got {cameras_per_frame}")
    check_count(n_frames, "n_frames", 1, MAX_FRAMES, "frames per subject")
    subject_seeds = [int(s) for s in subject_seeds]
    if not subject_seeds:
        raise ToolkitError("estimator_images: no subject seeds given (expected at least one)")
    _check_res(res)
    n = len(subject_seeds) * n_frames * cameras_per_frame
    # the uint8 images twice (the per-subject parts, then their concatenation) and a float RGB render a frame
    check_allocation(n * (6 * res * res + 512) + cameras_per_frame * 16 * res * res,
                     f"estimator_images: {n} images at {res} pixels", "lower the subjects, frames or resolution")
    if workers < 1:
        raise ToolkitError(f"estimator_images: workers must be >= 1, got {workers}")
    args = dict(n_frames=n_frames, cameras_per_frame=cameras_per_frame, res=res, seed=seed, iris_pixels=iris_pixels)
    t0 = time.perf_counter()
    workers = min(workers, len(subject_seeds))
    if workers == 1:
        parts = [_estimator_subjects(subject_seeds, log=log, **args)]
    else:
        import concurrent.futures as cf
        import multiprocessing as mp

        runs = [r.tolist() for r in np.array_split(np.asarray(subject_seeds), workers)]
        with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
            futures = [ex.submit(_estimator_subjects, r, **args) for r in runs]
            parts, done = [], 0
            for r, f in zip(runs, futures):
                parts.append(f.result())
                done += len(r)
                if log is not None:
                    n = done * n_frames * cameras_per_frame
                    log(f"estimator images: subject {done}/{len(subject_seeds)}, {n / (time.perf_counter() - t0):.0f} images/s "
                        f"({workers} processes)")
    cat = [np.concatenate([p[k] for p in parts]) for k in range(len(parts[0]))]
    img = torch.from_numpy(cat[0]).permute(0, 3, 1, 2).contiguous()
    out = (img, torch.from_numpy(cat[1].astype(np.float32)), torch.from_numpy(cat[2].astype(np.float32)))
    return out + (torch.from_numpy(cat[3].astype(np.int64)),) if iris_pixels else out


def _estimator_subjects(subject_seeds: list[int], *, n_frames: int, cameras_per_frame: int, res: int, seed: int,
                        iris_pixels: bool, log=None) -> list[np.ndarray]:
    """:func:`estimator_images` for a run of subjects, in one process: [images u8 NHWC, labels, landmarks(, iris)]."""
    rig = eth_xgaze_rig(radius=RIG_RADIUS)
    images, labels, landmarks, iris = [], [], [], []
    t0 = time.perf_counter()
    with _torch_threads(1):
        for k, s in enumerate(subject_seeds):
            subject = build_subject(SubjectParams.sample(s))
            fr = sample_frames(s + seed * 7919, n_frames)
            rng = np.random.default_rng([s, seed, 23])
            for i in range(n_frames):
                sel = rng.choice(len(rig), cameras_per_frame, replace=False)
                cams = frame_cameras(subject, fr["pose"][i], [rig[j] for j in sel], res)
                out = render_views(subject, fr["gaze"][i], fr["pose"][i], fr["expression"][i], cams,
                                   light_dirs=fr["light"][i])
                images.append(rgb_to_u8(out["rgb"]))
                labels.append(np.concatenate([out["pitchyaw_cam"], out["face_head_pose"]], 1))
                landmarks.append(out["landmarks_2d"])
                if iris_pixels:
                    seen = out["eye_region"] >= 1  # iris or pupil
                    iris.append(np.stack([(seen & out["left_eye_mask"]).sum((1, 2)),
                                          (seen & out["right_eye_mask"]).sum((1, 2))], 1))
            if log is not None:
                done = (k + 1) * n_frames * cameras_per_frame
                log(f"estimator images: subject {k + 1}/{len(subject_seeds)}, {done / (time.perf_counter() - t0):.0f} images/s")
    arrays = [np.concatenate(images), np.concatenate(labels), np.concatenate(landmarks)]
    return arrays + [np.concatenate(iris)] if iris_pixels else arrays
