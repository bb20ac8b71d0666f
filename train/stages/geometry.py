"""Stage ``geometry``: fit the SDF to one training subject's views, extract its DMTet mesh and place the
Gaussians on it (the two-stream model's initialization)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError
from train.config import component
from train.stages.artifacts import RunArtifacts
from train.stages.pipeline import RunContext


def stage_geometry(ctx: RunContext) -> dict[str, str]:
    """The training subject ``geometry.subject`` -> ``geometry/`` (the SDF, the neutral mesh, the fit's summary
    and the Gaussian scene, with the subject's 3D landmarks in its metadata)."""
    from geometry.fit import FitConfig
    from geometry.fit_dataset import fit_dataset
    from geometry.init_gaussians import InitConfig, init_gaussians
    from geometry.mesh_stats import load_mesh
    from geometry.sdf import SDFNet

    g = ctx.config.geometry
    train_files = RunArtifacts(ctx).split("train")
    src = train_files[min(g.subject, len(train_files) - 1)]
    out = ctx.run_dir / "geometry"
    data = subject_views_in_layout(src, ctx.config.data.layout)
    summary = fit_dataset(src, out, component(FitConfig, g, seed=ctx.config.seed), init_scene=False, log=None,
                          views=data)
    ctx.log(f"[geometry] held-out silhouette IoU {summary.get('heldout_iou_mean', float('nan')):.3f}, "
            f"Chamfer/diag {summary.get('chamfer_rel_diag', float('nan')):.4f}, {summary['fit_seconds']:.0f} s")
    verts, faces = load_mesh(out / "neutral_mesh.ply")
    net = SDFNet.load(out / "sdf.safetensors")
    scene = init_gaussians(verts, faces, data["landmarks"], net, component(InitConfig, g, seed=ctx.config.seed))
    scene.metadata["landmarks"] = data["landmarks"].tolist()
    scene.save(out / "gaussians.safetensors")
    return {"scene": "geometry/gaussians.safetensors", "mesh": "geometry/neutral_mesh.ply", "fit": "geometry/fit.json"}


def subject_views_in_layout(path: Path, layout: str = "auto") -> dict:
    """``geometry.fit_dataset.subject_views`` of a subject file in any layout the rows can be read from: a
    native file read directly (with the generator's ground-truth mesh), another converted row by row to the
    native conventions by ``GazeDataset`` (``train.data.layouts``)."""
    from geometry.fit_dataset import SUBJECT_KEYS, read_subject, subject_views
    from train.data.dataset import GazeDataset
    from train.data.layout_files import row_layout
    from train.data.layouts import DITGAZE

    if row_layout(path, layout) is DITGAZE:
        return read_subject(path)
    ds = GazeDataset([path], layout=layout)
    rows = [ds.read_row(0, i) for i in range(len(ds))]
    ds.close()
    if "facial_landmarks_3d" not in rows[0]:
        raise ToolkitError(f"{path}: no 3D landmarks (key 'facial_landmarks_3d'): every frame of this {layout} file "
                           "is seen by one camera, so none can be triangulated; the geometry stage needs a "
                           "multi-camera subject (geometry.subject)")
    arrays = {k: np.stack([np.asarray(r[k]) for r in rows]) for k in SUBJECT_KEYS if k in rows[0]}
    return subject_views(arrays, path)
