"""Stage ``geometry``: fit the SDF to one training subject's views, extract its DMTet mesh and place the
Gaussians on it (the two-stream model's initialization); optionally pre-train the model's fields."""

from __future__ import annotations

from pathlib import Path

from toolkit.errors import ToolkitError
from train.config import component
from train.stages.artifacts import RunArtifacts
from train.stages.pipeline import RunContext


def stage_geometry(ctx: RunContext) -> dict[str, str]:
    """The training subject ``geometry.subject`` -> ``geometry/`` (the SDF, the neutral mesh, the fit's summary
    and the Gaussian scene, with the subject's 3D landmarks in its metadata); with ``geometry.pretrain_fields``,
    the model's fields pre-trained on the training split (``geometry/fields.safetensors``,
    :mod:`train.stages.field_pretrain`)."""
    from geometry.fit import FitConfig
    from geometry.fit_dataset import fit_dataset
    from geometry.init_gaussians import InitConfig, init_gaussians
    from geometry.mesh_files import load_mesh
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
    outputs = {"scene": "geometry/gaussians.safetensors", "mesh": "geometry/neutral_mesh.ply", "fit": "geometry/fit.json"}
    if g.pretrain_fields > 0:
        from train.stages.field_pretrain import pretrain_run_fields

        outputs["fields"] = pretrain_run_fields(ctx, out / "gaussians.safetensors")
    return outputs


def geometry_section(cfg):
    """The part of the config the geometry stage's fingerprint hashes: the seed and the ``geometry`` section, and
    with ``geometry.pretrain_fields`` on, what the pre-trained fields depend on too: the ``gaussian`` fields that
    set the two-stream model (``maps_to`` GaussianModelConfig), ``feature_upscale`` and ``rgb_init``, as a
    ``gaussian`` section whose other fields are at their defaults, so that a switch added later with a
    :data:`train.config.NEUTRAL` default leaves the fingerprint as it was."""
    if cfg.geometry.pretrain_fields <= 0:
        return cfg.seed, cfg.geometry
    from dataclasses import fields, replace

    from train.run_config import GaussianStageConfig

    keys = [f.name for f in fields(cfg.gaussian) if f.metadata.get("maps_to", ("",))[0] == "GaussianModelConfig"]
    model_part = {k: getattr(cfg.gaussian, k) for k in (*keys, "feature_upscale", "rgb_init")}
    return cfg.seed, cfg.geometry, replace(GaussianStageConfig(), **model_part)


def subject_views_in_layout(path: Path, layout: str = "auto") -> dict:
    """``geometry.fit_dataset.subject_views`` of a subject file in any layout the rows can be read from: a
    native file read directly (with the generator's ground-truth mesh), another validated as ``GazeDataset``
    validates it and its label keys and masks converted whole to the native conventions
    (``train.data.layout_conversion.to_native``): no face image is read."""
    from geometry.fit_dataset import SUBJECT_KEYS, read_subject, subject_views
    from toolkit.h5 import has_key, open_h5, read_array
    from train.data.layout_conversion import to_native
    from train.data.layout_files import row_layout, validate_file
    from train.data.layouts import DITGAZE

    lay = row_layout(path, layout)
    if lay is DITGAZE:
        return read_subject(path)
    validate_file(path, lay)
    with open_h5(path) as f:  # the 2D landmarks: what a GazeNeRF file's 3D ones are triangulated from
        stored = {k: read_array(path, f, k) for k in (*SUBJECT_KEYS, "facial_landmarks") if has_key(path, f, k)}
    arrays = to_native(lay, stored, str(path))
    if "facial_landmarks_3d" not in arrays:
        raise ToolkitError(f"{path}: no 3D landmarks (key 'facial_landmarks_3d'): every frame of this {lay.name} "
                           "file is seen by one camera, so none can be triangulated; the geometry stage needs a "
                           "multi-camera subject (geometry.subject)")
    return subject_views({k: arrays[k] for k in SUBJECT_KEYS if k in arrays}, path)
