"""``python -m geometry``: inspect, compare, clean, extract, fit and render meshes.

Every subcommand validates its input; a bad file prints one line ``error: ...`` and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

from geometry.fit import FitConfig
from toolkit.errors import ToolkitError, run_cli
from toolkit.io import check_not_an_input


def _cmd_inspect(a) -> int:
    from geometry.mesh_stats import format_stats, inspect_mesh, load_mesh

    stats = inspect_mesh(*load_mesh(a.mesh))
    print(json.dumps(stats, indent=2) if a.json else format_stats(stats))
    return 0


def _cmd_compare(a) -> int:
    from geometry.mesh_stats import compare_meshes, load_mesh

    if a.samples < 1:
        raise ToolkitError(f"--samples must be >= 1, got {a.samples}")
    res = compare_meshes(*load_mesh(a.a), *load_mesh(a.b), n_samples=a.samples)
    if a.json:
        print(json.dumps(res, indent=2))
    else:
        print(f"chamfer            {res['chamfer']:.6g}  ({100 * res['chamfer_rel_diag']:.3f} % of A's bbox diagonal)")
        print(f"hausdorff          {res['hausdorff']:.6g}  ({100 * res['hausdorff_rel_diag']:.3f} %)")
        print(f"normal consistency {res['normal_consistency']:.4f}")
        print(f"mean A->B {res['mean_a_to_b']:.6g}   mean B->A {res['mean_b_to_a']:.6g}")
    return 0


def _cmd_clean(a) -> int:
    from geometry.cleanup import CleanupConfig, clean_mesh
    from geometry.mesh_stats import check_mesh_extension, load_mesh, save_mesh

    check_mesh_extension(a.output)  # before the pipeline runs, not after
    check_not_an_input(a.output, [a.input])
    if a.target_faces is not None and a.target_faces < 4:
        raise ToolkitError(f"--target-faces must be >= 4, got {a.target_faces}")
    cfg = CleanupConfig(weld_tolerance=a.weld_tolerance, min_component_fraction=a.min_component_fraction,
                        repair_non_manifold=not a.no_repair, max_hole_edges=a.max_hole_edges,
                        remesh_edge_fraction=a.remesh_edge, taubin_steps=a.taubin_steps, target_faces=a.target_faces)
    v, f = load_mesh(a.input)
    v2, f2, _ = clean_mesh(v, f, cfg, log=print)
    save_mesh(a.output, v2, f2)
    print(f"wrote {a.output}: {v2.shape[0]} vertices, {f2.shape[0]} faces")
    return 0


def _cmd_extract(a) -> int:
    from geometry.mesh_stats import check_mesh_extension, save_mesh
    from geometry.sdf import SDFNet, extract_mesh

    check_mesh_extension(a.output)
    check_not_an_input(a.output, [a.ckpt])
    if a.res != 0 and a.res < 2:
        raise ToolkitError(f"--res must be 0 (the checkpoint's grid) or >= 2, got {a.res}")
    net = SDFNet.load(a.ckpt)
    v, f, _ = extract_mesh(net, a.res or net.config.grid_res, a.kind, use_offsets=not a.no_offsets)
    save_mesh(a.output, v, f)
    print(f"wrote {a.output}: {v.shape[0]} vertices, {f.shape[0]} faces")
    return 0


def _cmd_fit(a) -> int:
    from geometry.fit_dataset import fit_dataset

    if a.steps < 1 or a.res < 4:
        raise ToolkitError(f"--steps must be >= 1 and --res >= 4, got {a.steps} and {a.res}")
    if a.threads < 0:
        raise ToolkitError(f"--threads must be >= 0 (0: torch's default), got {a.threads}")
    try:
        holdout = [int(c) for c in a.holdout.split(",") if c.strip()]
    except ValueError:
        raise ToolkitError(f"--holdout: expected comma-separated camera indices, got {a.holdout!r}") from None
    if a.threads:
        import torch

        torch.set_num_threads(a.threads)
    cfg = FitConfig(steps=a.steps, extract_res=a.res, seed=a.seed)
    summary = fit_dataset(a.dataset, a.output, cfg, holdout_cams=holdout, log=print)
    summary.pop("history", None)
    summary.pop("config", None)
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_render(a) -> int:
    from geometry.mesh_stats import load_mesh
    from geometry.render_sheet import contact_sheet

    if not a.output.lower().endswith(".png"):
        raise ToolkitError(f"{a.output}: the contact sheet is a PNG; expected a file name ending in .png")
    if a.views < 1 or a.size < 8:
        raise ToolkitError(f"--views must be >= 1 and --size >= 8, got {a.views} and {a.size}")
    v, f = load_mesh(a.mesh)
    contact_sheet(v, f, a.output, n_views=a.views, size=a.size)
    print(f"wrote {a.output}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m geometry", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("inspect", help="topology and geometry statistics of a mesh")
    s.add_argument("mesh")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=_cmd_inspect)
    s = sub.add_parser("compare", help="Chamfer / Hausdorff / normal consistency between two meshes")
    s.add_argument("a")
    s.add_argument("b")
    s.add_argument("--samples", type=int, default=20000)
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=_cmd_compare)
    s = sub.add_parser("clean", help="pymeshlab cleanup pipeline")
    s.add_argument("input")
    s.add_argument("output")
    s.add_argument("--target-faces", type=int, default=None)
    s.add_argument("--taubin-steps", type=int, default=10)
    s.add_argument("--max-hole-edges", type=int, default=30)
    s.add_argument("--min-component-fraction", type=float, default=0.01)
    s.add_argument("--weld-tolerance", type=float, default=1e-6)
    s.add_argument("--remesh-edge", type=float, default=0.0, help="isotropic remeshing edge / bbox diagonal (0: off)")
    s.add_argument("--no-repair", action="store_true", help="skip the non-manifold repairs")
    s.set_defaults(fn=_cmd_clean)
    s = sub.add_parser("extract", help="mesh the zero set of an SDF checkpoint with DMTet")
    s.add_argument("ckpt")
    s.add_argument("output")
    s.add_argument("--res", type=int, default=0,
                   help="tet grid resolution (0: the grid the checkpoint's offsets were trained for; finer grids "
                        "clamp the offsets to half a cell)")
    s.add_argument("--kind", choices=("kuhn", "bcc"), default="kuhn")
    s.add_argument("--no-offsets", action="store_true", help="ignore the network's tet-vertex offsets")
    s.set_defaults(fn=_cmd_extract)
    s = sub.add_parser("fit", help="fit the neutral head SDF to a synthetic multi-view dataset (HDF5)")
    s.add_argument("dataset")
    s.add_argument("output", help="output folder (mesh, SDF checkpoint, Gaussians, fit.json)")
    s.add_argument("--steps", type=int, default=FitConfig.steps)
    s.add_argument("--res", type=int, default=FitConfig.extract_res, help="extraction grid resolution")
    s.add_argument("--holdout", default="2,7,10,15", help="rig cameras held out of the fit for the IoU check")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--threads", type=int, default=0, help="torch CPU threads for the fit (0: torch's default)")
    s.set_defaults(fn=_cmd_fit)
    s = sub.add_parser("render", help="multi-view contact sheet of a mesh (render/mesh_gl.py)")
    s.add_argument("mesh")
    s.add_argument("output")
    s.add_argument("--views", type=int, default=6)
    s.add_argument("--size", type=int, default=256)
    s.set_defaults(fn=_cmd_render)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.fn(args) or 0)


if __name__ == "__main__":
    sys.exit(run_cli(main))
