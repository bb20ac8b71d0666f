"""``geometry fit DATASET OUT``: the neutral head from a multi-view HDF5 subject file (docs/data.md).

The keys are read through ``toolkit.h5``'s bounded reader: links, external
storage and forged sizes are refused there, before any row is read. Every row's camera is
moved into the **head** frame (camera-from-head = w2c o pose, with the pose's scale), so silhouettes from
all frames and all rig cameras constrain one neutral head; the 3D landmarks are moved into the head frame
the same way and their per-landmark median over the frames (robust to the expressions) is used.
Rows of the ``holdout_cams`` rig cameras are kept out of the fit and score it (silhouette IoU).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from geometry.fit import FitConfig, fit_silhouettes
from geometry.silhouettes import Views, silhouette_iou
from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_json, check_output_folder, check_readable_file
from toolkit.rotations import so3_exp

DEFAULT_HOLDOUT = (2, 7, 10, 15)


def _read(f, path, key, shape_tail=None, *, copies: int = 1):
    from toolkit.h5 import has_key, read_array

    if not has_key(path, f, key):
        raise ToolkitError(f"{path}: missing dataset {key!r} (expected the keys of docs/data.md)")
    a = read_array(path, f, key, copies=copies)
    if a.dtype.kind not in "biuf":
        raise ToolkitError(f"{path}: key '{key}' has dtype {a.dtype}, expected numbers")
    if shape_tail is not None and (a.ndim == 0 or tuple(a.shape[1:]) != shape_tail):
        raise ToolkitError(f"{path}: {key} has shape {list(a.shape)}, expected [N, {', '.join(map(str, shape_tail))}]")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ToolkitError(f"{path}: {key} contains NaN/inf")
    return a


def _read_rows(f, path, key, n: int, width: int = 1, default=None):
    """``key`` as [n] (width 1) or [n, width] rows -- [n, width] or [n, 1, width] in the file -- or ``default``
    when the file has no ``key`` (required when ``default`` is None)."""
    from toolkit.h5 import has_key

    if default is not None and not has_key(path, f, key):
        return default
    a = _read(f, path, key)
    if a.ndim == 0 or a.size != n * width or a.shape[0] != n:
        want = f"[{n}]" if width == 1 else f"[{n}, {width}]"
        raise ToolkitError(f"{path}: {key} has shape {list(a.shape)}, expected {want} (one row per head_mask image)")
    return a.reshape(n) if width == 1 else a.reshape(n, width)


def _ground_truth_mesh(f, path) -> dict[str, torch.Tensor]:
    """The generator's neutral mesh of a synthetic subject file (``neutral_vertice`` [V, 3], ``mesh_faces``
    [F, 3]), checked: finite vertices, integer faces indexing them."""
    verts, faces = _read(f, path, "neutral_vertice", (3,)), _read(f, path, "mesh_faces", (3,))
    if faces.dtype.kind not in "iu" or not len(verts) or (faces < 0).any() or (faces >= len(verts)).any():
        raise ToolkitError(f"{path}: mesh_faces must be integer indices into neutral_vertice's {len(verts)} rows")
    return {"gt_verts": torch.from_numpy(verts.astype(np.float32)), "gt_faces": torch.from_numpy(faces.astype(np.int64))}


SUBJECT_KEYS = ("head_mask", "inmat", "w2c_Rmat", "w2c_Tvec", "pose", "scale", "facial_landmarks_3d", "cam_index",
                "frame_index")
"""The per-row keys :func:`subject_views` reads (``scale``, ``cam_index``, ``frame_index`` optional)."""


def read_subject(path: str | os.PathLike) -> dict:
    """Head-frame views and landmarks of one subject file in the native layout (docs/data.md):
    :func:`subject_views` of its keys, read through ``toolkit.h5``."""
    from toolkit.h5 import has_key, open_h5

    path = check_readable_file(path, "HDF5 subject file")
    with open_h5(path) as f:
        masks = _read(f, path, "head_mask", copies=3)  # + the boolean masks and their tensor views
        if masks.ndim != 3 or masks.shape[0] < 1 or min(masks.shape[1:]) < 8:
            raise ToolkitError(f"{path}: head_mask must be [N, H, W] with N >= 1 and H, W >= 8 pixels, "
                               f"got {list(masks.shape)}")
        n = masks.shape[0]
        rows = {"head_mask": masks, "inmat": _read(f, path, "inmat", (3, 3)),
                "w2c_Rmat": _read(f, path, "w2c_Rmat", (3, 3)), "w2c_Tvec": _read_rows(f, path, "w2c_Tvec", n, 3),
                "pose": _read(f, path, "pose", (6,)), "scale": _read_rows(f, path, "scale", n, default=np.ones(n)),
                "facial_landmarks_3d": _read(f, path, "facial_landmarks_3d", (68, 3)),
                "cam_index": _read_rows(f, path, "cam_index", n, default=np.arange(n)),
                "frame_index": _read_rows(f, path, "frame_index", n, default=np.arange(n))}
        if has_key(path, f, "neutral_vertice") and has_key(path, f, "mesh_faces"):
            rows.update(_ground_truth_mesh(f, path))
    return subject_views(rows, path)


def subject_views(rows: dict, where: str | os.PathLike = "") -> dict:
    """Head-frame views and landmarks from a subject's native arrays (:data:`SUBJECT_KEYS`: ``head_mask``
    [N, H, W] uint8, ``inmat``, ``w2c_Rmat`` [N, 3, 3], ``w2c_Tvec`` [N, 3], ``pose`` [N, 6], ``scale`` [N],
    ``facial_landmarks_3d`` [N, 68, 3] world; optional ``cam_index``, ``frame_index`` [N], ``gt_verts``,
    ``gt_faces``). Every row's camera is moved into the head frame, so all frames constrain one neutral head.

    Returns dict: masks [N, H, W] bool, Ks [N, 3, 3], viewmats [N, 4, 4] (head -> camera, scale folded
    in), landmarks [68, 3] (head frame, median over frames), cam_index [N], and when given gt_verts [V, 3]
    (head frame), gt_faces [F, 3].
    """
    masks, n = rows["head_mask"], len(rows["head_mask"])
    K, Rc, tc, pose, lmk_w = (rows[k] for k in ("inmat", "w2c_Rmat", "w2c_Tvec", "pose", "facial_landmarks_3d"))
    scale = np.reshape(rows.get("scale", np.ones(n)), n)
    cam = np.reshape(rows.get("cam_index", np.arange(n)), n)
    frame = np.reshape(rows.get("frame_index", np.arange(n)), n)
    for k, a in (("inmat", K), ("w2c_Rmat", Rc), ("w2c_Tvec", tc), ("pose", pose), ("facial_landmarks_3d", lmk_w)):
        if a.shape[0] != n:
            raise ToolkitError(f"{where}: {k} has {a.shape[0]} rows, head_mask has {n}")
    if not (scale > 0).all():
        raise ToolkitError(f"{where}: scale must be > 0")
    R = so3_exp(torch.from_numpy(pose[:, :3].astype(np.float64))).numpy()  # head -> world rotation
    t = pose[:, 3:6].astype(np.float64)
    view = np.zeros((n, 4, 4))
    view[:, :3, :3] = Rc.astype(np.float64) @ (scale[:, None, None] * R)
    view[:, :3, 3] = np.einsum("nij,nj->ni", Rc.astype(np.float64), t) + tc
    view[:, 3, 3] = 1
    lmk_h = np.einsum("nji,nkj->nki", R, lmk_w.astype(np.float64) - t[:, None, :]) / scale[:, None, None]
    # Landmarks are the same for all cameras of a frame: one per frame, then the median over frames.
    _, first = np.unique(frame, return_index=True)
    landmarks = np.median(lmk_h[first], axis=0)
    gt = {k: rows[k] for k in ("gt_verts", "gt_faces") if k in rows}
    return {"masks": torch.from_numpy(masks > 127), "Ks": torch.from_numpy(K.astype(np.float32)),
            "viewmats": torch.from_numpy(view.astype(np.float32)),
            "landmarks": torch.from_numpy(landmarks.astype(np.float32)), "cam_index": torch.from_numpy(cam.astype(np.int64)),
            **gt}


def split_views(data: dict, holdout_cams=None) -> tuple[Views, Views | None]:
    """(training views, held-out views or None) by rig camera index: ``holdout_cams`` each one the file has (a
    camera it lacks would hold nothing out, and the fit would go unscored unseen), None those of
    :data:`DEFAULT_HOLDOUT` it has."""
    present = sorted(set(data["cam_index"].tolist()))
    if holdout_cams is None:
        holdout_cams = [c for c in DEFAULT_HOLDOUT if c in present]
    absent = [int(c) for c in holdout_cams if int(c) not in present]
    if absent:
        raise ToolkitError(f"fit: --holdout camera(s) {absent} not in the file, whose cameras are {present}")
    hold = torch.zeros(data["masks"].shape[0], dtype=torch.bool)
    for c in holdout_cams:
        hold |= data["cam_index"] == int(c)
    if bool(hold.all()):
        raise ToolkitError("fit: every row is held out; pass fewer --holdout cameras")
    train = Views(data["masks"][~hold], data["Ks"][~hold], data["viewmats"][~hold])
    test = Views(data["masks"][hold], data["Ks"][hold], data["viewmats"][hold]) if bool(hold.any()) else None
    return train, test


def fit_dataset(dataset: str | os.PathLike, out_dir: str | os.PathLike, cfg: FitConfig | None = None, *,
                holdout_cams=None, max_eval_views: int = 24, init_scene: bool = True, log=None,
                views: dict | None = None) -> dict:
    """Fit, then write ``neutral_mesh.ply``, ``sdf.safetensors``, ``gaussians.safetensors`` and ``fit.json``.

    ``views``: the subject's :func:`subject_views`, when the caller read them (a file in another layout);
    otherwise ``dataset`` is read as a native file. Returns the summary written to fit.json (timing, held-out
    IoU, Chamfer to the ground truth if present).
    """
    from geometry.mesh_files import save_mesh
    from geometry.mesh_stats import compare_meshes

    cfg = cfg or FitConfig()
    out = Path(out_dir)
    check_output_folder(out, f"output folder {out}")
    t0 = time.perf_counter()
    data = views if views is not None else read_subject(dataset)
    train, test = split_views(data, holdout_cams)
    res = fit_silhouettes(train, cfg, landmarks=data["landmarks"], log=log)
    summary: dict = {"dataset": str(dataset), "train_views": len(train), "fit_seconds": res.seconds,
                     "skipped_steps": res.skipped_steps, "vertices": int(res.verts.shape[0]),
                     "faces": int(res.faces.shape[0]), "config": json.loads(json.dumps(asdict(cfg), default=list))}
    if test is not None:
        idx = torch.linspace(0, len(test) - 1, min(len(test), max_eval_views)).round().long().unique()
        ious = silhouette_iou(res.verts, res.faces, test.subset(idx))
        summary.update(heldout_views=len(idx), heldout_iou_mean=float(np.mean(ious)), heldout_iou_min=float(np.min(ious)))
    if "gt_verts" in data:
        cmp = compare_meshes(data["gt_verts"], data["gt_faces"], res.verts, res.faces)
        summary.update(chamfer=cmp["chamfer"], chamfer_rel_diag=cmp["chamfer_rel_diag"],
                       hausdorff_rel_diag=cmp["hausdorff_rel_diag"], normal_consistency=cmp["normal_consistency"])
    out.mkdir(parents=True, exist_ok=True)
    save_mesh(out / "neutral_mesh.ply", res.verts, res.faces)
    res.net.save(out / "sdf.safetensors", {"dataset": str(dataset)})
    if init_scene:
        from geometry.init_gaussians import init_gaussians

        scene = init_gaussians(res.verts, res.faces, data["landmarks"], res.net)
        scene.save(out / "gaussians.safetensors")
        summary["gaussians"] = scene.num_gaussians
    summary["total_seconds"] = time.perf_counter() - t0
    summary["history"] = res.history
    atomic_write_json(out / "fit.json", summary)
    return summary
