"""A tiny valid subject file built from numpy alone (no renderer): the base that bad-file tests mutate."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from train.data.format import write_subject_h5

RES, N_VERTS = 24, 5


def tiny_rows(n: int = 4, res: int = RES, seed: int = 0) -> dict[str, np.ndarray]:
    """Every key of REQUIRED and OPTIONAL with ``n`` rows of valid values at ``res`` x ``res``."""
    rng = np.random.default_rng(seed)
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    K = np.tile(f32([[res, 0, res / 2], [0, res, res / 2], [0, 0, 1]]), (n, 1, 1))
    return {
        "face_patch": rng.integers(0, 256, (n, res, res, 3), dtype=np.uint8),
        "head_mask": np.full((n, res, res), 255, np.uint8),
        "left_eye_mask": np.zeros((n, res, res), np.uint8),
        "right_eye_mask": np.zeros((n, res, res), np.uint8),
        "facial_landmarks": f32(rng.uniform(0, res, (n, 68, 2))),
        "facial_landmarks_3d": f32(rng.normal(0, 0.05, (n, 68, 3)) + [0, 0, 0.6]),
        "latent_codes": f32(rng.normal(0, 1, (n, 144))),
        "pose": np.zeros((n, 6), np.float32),
        "scale": np.ones((n, 1), np.float32),
        "w2c_Rmat": np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)),
        "w2c_Tvec": np.tile(f32([0, 0, 0.6]), (n, 1)),
        "inmat": K,
        "pitchyaw_head": f32(rng.uniform(-0.5, 0.5, (n, 2))),
        "face_head_pose": f32(rng.uniform(-0.5, 0.5, (n, 2))),
        "cam_index": np.arange(n, dtype=np.int32),
        "frame_index": np.zeros(n, np.int32),
        "vertice": f32(rng.normal(0, 0.1, (n, N_VERTS, 3))),
        "pitchyaw_cam": f32(rng.uniform(-0.5, 0.5, (n, 2))),
        "expression_params": np.zeros((n, 4), np.float32),
        "light_dir": np.tile(f32([0, 0, -1]), (n, 1)),
    }


def tiny_subject_arrays() -> dict[str, np.ndarray]:
    return {
        "neutral_vertice": np.random.default_rng(1).normal(0, 0.1, (N_VERTS, 3)).astype(np.float32),
        "mesh_faces": np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]], np.int32),
        "eyeball_centers": np.array([[-0.03, 0.03, 0.08], [0.03, 0.03, 0.08]], np.float32),
        "eyeball_radii": np.full(2, 0.012, np.float32),
        "identity_params": np.zeros(22, np.float32),
    }


def tiny_attrs() -> dict:
    return {"source": "tests", "subject_params": json.dumps({"identity": [0.0] * 22, "seed": 3}), "ambient": 0.45,
            "frame_seed": 3, "n_cameras": 18}


def write_tiny_subject(path: str | Path, n: int = 4, **kw) -> Path:
    """A valid subject file (chunked, compressed images as the writer stores them)."""
    return write_subject_h5(path, tiny_rows(n), subject=tiny_subject_arrays(), attrs=tiny_attrs(), **kw)


def edited_copy(base: Path, dst: Path, edit) -> Path:
    """``base`` copied to ``dst``, then ``edit(h5py.File)`` applied to the copy in place."""
    import shutil

    import h5py

    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(base, dst)
    with h5py.File(dst, "r+") as f:
        edit(f)
    return dst


def replace_key(key: str, **create_kw):
    """An edit: ``key`` deleted and created again with ``create_dataset(key, **create_kw)``."""
    def edit(f):
        del f[key]
        f.create_dataset(key, **create_kw)
    return edit


def link_key(key: str, link):
    """An edit: ``key`` replaced by ``link`` (an h5py.SoftLink or h5py.ExternalLink)."""
    def edit(f):
        del f[key]
        f[key] = link
    return edit


def huge_rows(rows: int):
    """An edit: every per-row key declares ``rows`` rows in chunked, compressed storage holding almost nothing
    (a file of a few KB that asks a reader for gigabytes)."""
    def edit(f):
        for k, v in tiny_rows(1).items():
            del f[k]
            f.create_dataset(k, shape=(rows,) + v.shape[1:], dtype=v.dtype, chunks=(1,) + v.shape[1:],
                             compression="gzip")
    return edit
