"""Stage ``geometry``: fit the SDF to one training subject's views, extract its DMTet mesh and place the
Gaussians on it (the two-stream model's initialization)."""

from __future__ import annotations

from train.config import component
from train.stages.artifacts import RunArtifacts
from train.stages.pipeline import RunContext


def stage_geometry(ctx: RunContext) -> dict[str, str]:
    """The training subject ``geometry.subject`` -> ``geometry/`` (the SDF, the neutral mesh, the fit's summary
    and the Gaussian scene, with the subject's 3D landmarks in its metadata)."""
    from geometry.fit import FitConfig
    from geometry.fit_dataset import fit_dataset, read_subject
    from geometry.init_gaussians import InitConfig, init_gaussians
    from geometry.mesh_stats import load_mesh
    from geometry.sdf import SDFNet

    g = ctx.config.geometry
    train_files = RunArtifacts(ctx).split("train")
    src = train_files[min(g.subject, len(train_files) - 1)]
    out = ctx.run_dir / "geometry"
    summary = fit_dataset(src, out, component(FitConfig, g, seed=ctx.config.seed), init_scene=False, log=None)
    ctx.log(f"[geometry] held-out silhouette IoU {summary.get('heldout_iou_mean', float('nan')):.3f}, "
            f"Chamfer/diag {summary.get('chamfer_rel_diag', float('nan')):.4f}, {summary['fit_seconds']:.0f} s")
    data = read_subject(src)
    verts, faces = load_mesh(out / "neutral_mesh.ply")
    net = SDFNet.load(out / "sdf.safetensors")
    scene = init_gaussians(verts, faces, data["landmarks"], net, component(InitConfig, g, seed=ctx.config.seed))
    scene.metadata["landmarks"] = data["landmarks"].tolist()
    scene.save(out / "gaussians.safetensors")
    return {"scene": "geometry/gaussians.safetensors", "mesh": "geometry/neutral_mesh.ply", "fit": "geometry/fit.json"}
