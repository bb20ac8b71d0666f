"""``python -m geometry``: inspect, compare, clean, extract, fit and render meshes.

Every subcommand validates its input; a bad file prints one line ``error: ...`` and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

from geometry.fit import FitConfig
from toolkit.errors import CliParser, ToolkitError, run_cli
from toolkit.io import check_not_an_input
from toolkit.limits import check_allocation, check_count


def number(text: str) -> int | float:
    """A count flag's value: an int, or a float that the command's range check refuses unless integral (so
    ``--samples 2e4`` is 20000 and ``--views 1e8`` is refused by its range, not read as a typo)."""
    try:
        return int(text)
    except ValueError:
        return float(text)  # argparse turns its ValueError into "invalid number value"


def _check_res(res, flag: str, low: int, kind: str, feature_dim: int) -> int:
    """A grid resolution in [low, MAX_RES] whose grid and extraction fit the memory budget."""
    from geometry.dmtet import grid_bytes
    from geometry.tets import MAX_RES

    what = "a grid resolution (cubes per axis" + ("; 0: the checkpoint's)" if flag == "--res" and low == 2 else ")")
    res = check_count(res, flag, low, MAX_RES, what)
    check_allocation(grid_bytes(kind, res, feature_dim), f"{flag} {res}: a {kind} tet grid and its mesh",
                     f"lower {flag}")
    return res


def _cmd_inspect(a) -> int:
    from geometry.mesh_files import load_mesh
    from geometry.mesh_stats import format_stats, inspect_mesh

    stats = inspect_mesh(*load_mesh(a.mesh))
    print(json.dumps(stats, indent=2) if a.json else format_stats(stats))
    return 0


def _cmd_compare(a) -> int:
    from geometry.mesh_files import load_mesh
    from geometry.mesh_stats import BYTES_PER_SAMPLE, MAX_SAMPLES, compare_meshes

    n = check_count(a.samples, "--samples", 1, MAX_SAMPLES, "a number of surface samples per mesh")
    check_allocation(2 * n * BYTES_PER_SAMPLE, f"--samples {n}", "lower --samples")
    res = compare_meshes(*load_mesh(a.a), *load_mesh(a.b), n_samples=n, names=(a.a, a.b))
    if a.json:
        print(json.dumps(res, indent=2))
    else:
        print(f"chamfer            {res['chamfer']:.6g}  ({100 * res['chamfer_rel_diag']:.3f} % of A's bbox diagonal)")
        print(f"hausdorff          {res['hausdorff']:.6g}  ({100 * res['hausdorff_rel_diag']:.3f} %)")
        print(f"normal consistency {res['normal_consistency']:.4f}")
        print(f"mean A->B {res['mean_a_to_b']:.6g}   mean B->A {res['mean_b_to_a']:.6g}")
    return 0


CLEAN_FLAGS = {"weld_tolerance": "--weld-tolerance", "min_component_fraction": "--min-component-fraction",
               "max_hole_edges": "--max-hole-edges", "remesh_edge_fraction": "--remesh-edge",
               "taubin_steps": "--taubin-steps", "target_faces": "--target-faces"}


def _cmd_clean(a) -> int:
    from geometry.cleanup import CleanupConfig, check_config, check_remesh_size, clean_mesh
    from geometry.mesh_files import check_mesh_extension, load_mesh, save_mesh

    check_mesh_extension(a.output)  # before the pipeline runs, not after
    check_not_an_input(a.output, [a.input])
    cfg = CleanupConfig(weld_tolerance=a.weld_tolerance, min_component_fraction=a.min_component_fraction,
                        repair_non_manifold=not a.no_repair, max_hole_edges=a.max_hole_edges,
                        remesh_edge_fraction=a.remesh_edge, taubin_steps=a.taubin_steps, target_faces=a.target_faces)
    cfg = check_config(cfg, CLEAN_FLAGS)
    v, f = load_mesh(a.input)
    check_remesh_size(v, f, cfg.remesh_edge_fraction, "--remesh-edge")  # depends on the mesh's area
    v2, f2, _ = clean_mesh(v, f, cfg, log=print)
    save_mesh(a.output, v2, f2)
    print(f"wrote {a.output}: {v2.shape[0]} vertices, {f2.shape[0]} faces")
    return 0


def _cmd_extract(a) -> int:
    from geometry.mesh_files import check_mesh_extension, save_mesh
    from geometry.sdf import SDFNet, extract_mesh

    check_mesh_extension(a.output)
    check_not_an_input(a.output, [a.ckpt])
    if a.res != 0:  # with no features: the grid alone must fit before the checkpoint is read
        _check_res(a.res, "--res", 2, a.kind, 0)
    net = SDFNet.load(a.ckpt)
    res = _check_res(a.res or net.config.grid_res, "--res" if a.res else f"{a.ckpt}: grid_res (--res 0)", 2,
                     a.kind, net.config.feature_dim)
    v, f, _ = extract_mesh(net, res, a.kind, use_offsets=not a.no_offsets)
    save_mesh(a.output, v, f)
    print(f"wrote {a.output}: {v.shape[0]} vertices, {f.shape[0]} faces")
    return 0


def _fit_flags(a) -> list[int]:
    """Check ``fit``'s flags before the dataset is read -> the held-out camera indices."""
    from geometry.fit import MAX_SEED, MAX_STEPS

    if a.threads < 0:
        raise ToolkitError(f"--threads must be >= 0 (0: torch's default), got {a.threads}")
    check_count(a.threads, "--threads", 0, 1024, "a number of threads (0: torch's default)")
    check_count(a.steps, "--steps", 1, MAX_STEPS, "a number of optimiser steps")
    _check_res(a.res, "--res", 4, FitConfig.grid_kind, FitConfig().net.feature_dim)
    check_count(a.seed, "--seed", 0, MAX_SEED, "a seed")
    if a.holdout is None:
        return None  # the default cameras the file has
    try:
        holdout = [int(c) for c in a.holdout.split(",") if c.strip()]
    except ValueError:
        raise ToolkitError(f"--holdout: expected comma-separated camera indices, got {a.holdout!r}") from None
    for c in holdout:
        check_count(c, "--holdout", 0, 2**31 - 1, "camera indices")
    return holdout


def _cmd_fit(a) -> int:
    from geometry.fit_dataset import fit_dataset

    holdout = _fit_flags(a)
    if a.threads:
        import torch

        torch.set_num_threads(int(a.threads))
    cfg = FitConfig(steps=int(a.steps), extract_res=int(a.res), seed=int(a.seed))
    summary = fit_dataset(a.dataset, a.output, cfg, holdout_cams=holdout, log=print)
    summary.pop("history", None)
    summary.pop("config", None)
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_render(a) -> int:
    from geometry.mesh_files import load_mesh
    from geometry.render_sheet import check_sheet, contact_sheet

    if not a.output.lower().endswith(".png"):
        raise ToolkitError(f"{a.output}: the contact sheet is a PNG; expected a file name ending in .png")
    if a.views < 1 or a.size < 8:
        raise ToolkitError(f"--views must be >= 1 and --size >= 8, got {a.views} and {a.size}")
    views, size = check_sheet(a.views, a.size, ("--views", "--size"))
    check_not_an_input(a.output, [a.mesh])
    v, f = load_mesh(a.mesh)
    contact_sheet(v, f, a.output, n_views=views, size=size)
    print(f"wrote {a.output}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="python -m geometry", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("inspect", help="topology and geometry statistics of a mesh")
    s.add_argument("mesh")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=_cmd_inspect)
    s = sub.add_parser("compare", help="Chamfer / Hausdorff / normal consistency between two meshes")
    s.add_argument("a")
    s.add_argument("b")
    s.add_argument("--samples", type=number, default=20000)
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=_cmd_compare)
    s = sub.add_parser("clean", help="pymeshlab cleanup pipeline")
    s.add_argument("input")
    s.add_argument("output")
    s.add_argument("--target-faces", type=number, default=None)
    s.add_argument("--taubin-steps", type=number, default=10)
    s.add_argument("--max-hole-edges", type=number, default=30)
    s.add_argument("--min-component-fraction", type=float, default=0.01)
    s.add_argument("--weld-tolerance", type=float, default=1e-6)
    s.add_argument("--remesh-edge", type=float, default=0.0, help="isotropic remeshing edge / bbox diagonal (0: off)")
    s.add_argument("--no-repair", action="store_true", help="skip the non-manifold repairs")
    s.set_defaults(fn=_cmd_clean)
    s = sub.add_parser("extract", help="mesh the zero set of an SDF checkpoint with DMTet")
    s.add_argument("ckpt")
    s.add_argument("output")
    s.add_argument("--res", type=number, default=0,
                   help="tet grid resolution (0: the grid the checkpoint's offsets were trained for; finer grids "
                        "clamp the offsets to half a cell)")
    s.add_argument("--kind", choices=("kuhn", "bcc"), default="kuhn")
    s.add_argument("--no-offsets", action="store_true", help="ignore the network's tet-vertex offsets")
    s.set_defaults(fn=_cmd_extract)
    s = sub.add_parser("fit", help="fit the neutral head SDF to a synthetic multi-view dataset (HDF5)")
    s.add_argument("dataset")
    s.add_argument("output", help="output folder (mesh, SDF checkpoint, Gaussians, fit.json)")
    s.add_argument("--steps", type=number, default=FitConfig.steps)
    s.add_argument("--res", type=number, default=FitConfig.extract_res, help="extraction grid resolution")
    s.add_argument("--holdout", default=None, help="rig cameras held out of the fit for the IoU check, each one the "
                   "file has ('': none; default: those of 2,7,10,15 the file has)")
    s.add_argument("--seed", type=number, default=0)
    s.add_argument("--threads", type=number, default=0, help="torch CPU threads for the fit (0: torch's default)")
    s.set_defaults(fn=_cmd_fit)
    s = sub.add_parser("render", help="multi-view contact sheet of a mesh (render/mesh_gl.py)")
    s.add_argument("mesh")
    s.add_argument("output")
    s.add_argument("--views", type=number, default=6)
    s.add_argument("--size", type=number, default=256)
    s.set_defaults(fn=_cmd_render)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.fn(args) or 0)
    except ToolkitError as e:
        # The promise is one line: a message quoting a library's multi-line text (torch's state-dict mismatch
        # lists every tensor on its own line) is folded onto it.
        raise ToolkitError(" ".join(str(e).split())) from None


if __name__ == "__main__":
    sys.exit(run_cli(main))
