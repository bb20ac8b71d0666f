"""Staged training of DiT-Gaze: ``python train/run.py`` or ``python -m train.run``.

    python -m train.run --preset demo --run-dir out/run --stages all [section.key=value ...] [--resume]

Stages (each writes into the run directory and is skipped when its outputs exist and its inputs, i.e. its
config section and upstream stages, are unchanged; one module each in ``train/stages/``):

    data       generate the synthetic dataset (skipped when data.root points at HDF5 files)
    geometry   fit the SDF to one training subject's views -> DMTet mesh -> Gaussian initialization
    codec      train the small KL autoencoder (or use the SD-VAE / pixel codec)
    estimator  train the loss and the evaluation gaze estimators (independent seeds)
    gaussian   end-to-end training of the two-stream model and the renderer
    eval       the GazeNeRF protocol on held-out subjects -> report.md, metrics.json, qualitative PNG

The resolved config is written to ``config.yaml``; a config with an unknown key or a wrong type fails
before any work. Without ``--preset`` or ``--config`` an existing run directory continues its own
``config.yaml`` (``--run-dir out/run --stages eval eval.tta_steps=20`` re-runs one stage of that run); a run
refused because an unselected upstream stage (direct or read through others) is missing or was made under another
config, a stage record it reads is unreadable, an eval output cannot be written, or the pairing misses a held-out
subject of the run's current data leaves it untouched.
Launch with ``torchrun --nproc_per_node N -m train.run ...`` for DDP in stage gaussian: each process takes 1/N
of ``gaussian.batch`` (the same rows of every random draw) and the gradients are averaged, so the weights equal
one process's on the whole batch up to float sums (tested); rank 0 logs and writes the checkpoints.
A finished run is opened for use with ``train.trained_run.TrainedRun``; ``python -m train.run augment --run-dir
RUN --out OUT`` measures whether its redirected data makes a gaze estimator better (``train.augment``), and
``python -m train.run ablate --preset demo --seeds 3`` trains and tables the paper's Table 3 (``train.ablate``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Sequence

if __package__ in (None, ""):  # `python train/run.py`: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from toolkit.errors import CliParser, ToolkitError, run_cli  # noqa: E402
from toolkit.host import keep_freed_memory  # noqa: E402
from toolkit.io import check_output_folder  # noqa: E402
from train.config import apply_overrides, load_yaml_config, save_yaml_config  # noqa: E402
from train.presets import PRESETS, preset  # noqa: E402
from train.run_config import RunConfig  # noqa: E402
from train.stages import STAGE_NAMES, STAGES  # noqa: E402
from train.stages.artifacts import resolve_device  # noqa: E402
from train.stages.checks import check_config, check_run_pairing  # noqa: E402
from train.stages.pipeline import RunContext, check_run, run_stages  # noqa: E402
from train.training.distributed import is_main_process  # noqa: E402


def resolve_config(args: argparse.Namespace) -> RunConfig:
    """``--config``, else ``--preset``, else the run directory's own ``config.yaml`` (re-running a stage of an
    existing run continues its config), else the demo preset; then the overrides."""
    if args.config:
        cfg = load_yaml_config(RunConfig, args.config)
    elif args.preset is None and (Path(args.run_dir) / "config.yaml").is_file():
        cfg = load_yaml_config(RunConfig, Path(args.run_dir) / "config.yaml")
    else:
        cfg = preset(args.preset or "demo")
    return apply_overrides(cfg, args.overrides)


def build_parser() -> argparse.ArgumentParser:
    ap = CliParser(prog="python -m train.run", description="Staged DiT-Gaze training.",
                   formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--preset", default=None, choices=sorted(PRESETS),
                    help="start from this preset (default: the run directory's config.yaml when it has one, else demo)")
    ap.add_argument("--config", help="a config.yaml to start from instead of a preset")
    ap.add_argument("--run-dir", default="out/run", help="the run directory (default: out/run)")
    ap.add_argument("--stages", default="all", help=f"comma-separated subset of {','.join(STAGE_NAMES)} or 'all'")
    ap.add_argument("--force", default="", help="comma-separated stages to re-run even when up to date")
    ap.add_argument("--resume", action="store_true", help="continue stage gaussian from its newest checkpoint")
    ap.add_argument("overrides", nargs="*", help="section.key=value overrides (e.g. gaussian.steps=100)")
    return ap


def _stage_names(flag: str, text: str) -> list[str]:
    """The comma-separated stage names of ``flag``, each one checked."""
    names = [s.strip() for s in text.split(",") if s.strip()]
    if unknown := [s for s in names if s not in STAGE_NAMES]:
        raise ToolkitError(f"{flag}: unknown stage(s) {unknown}; stages are {list(STAGE_NAMES)} or 'all'")
    return names


def select_stages(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """(the stages to run, the stages to force) from ``--stages`` and ``--force``, checked; under ``torchrun``
    only stage gaussian may run."""
    stages = list(STAGE_NAMES) if args.stages == "all" else _stage_names("--stages", args.stages)
    force = _stage_names("--force", args.force)
    if idle := [s for s in force if s not in stages]:
        raise ToolkitError(f"--force: stage(s) {idle} are not among --stages {args.stages}, so nothing would re-run them")
    from train.training.distributed import world_size

    world = world_size()
    if world > 1 and stages != ["gaussian"]:
        # Every rank would run every other stage in full, writing the same files side by side.
        raise ToolkitError(f"--stages {args.stages}: under torchrun (WORLD_SIZE={world}) only stage gaussian is "
                           "distributed; run the others in one process (python -m train.run ... --stages "
                           "data,geometry,codec,estimator, later --stages eval) and torchrun ... --stages gaussian")
    return stages, force


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["augment"]:  # the augmentation benchmark on a finished run (train.augment)
        from train.augment.cli import main as augment

        return augment(argv[1:])
    if argv[:1] == ["ablate"]:  # the paper's Table 3 over seeds (train.ablate)
        from train.ablate import main as ablate

        return ablate(argv[1:])
    args = build_parser().parse_args(argv)
    check_output_folder(args.run_dir, f"--run-dir {args.run_dir}")  # a file there: said before the config is read
    cfg = resolve_config(args)
    stages, force = select_stages(args)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    keep_freed_memory()
    check_config(cfg)
    resolve_device(cfg)  # fail early on an impossible device
    run_dir = Path(args.run_dir)
    main_process = is_main_process()  # under torchrun rank 0 alone logs: N copies of each line say nothing more
    ctx = RunContext(run_dir, cfg, resume=args.resume, log=lambda m: print(m, flush=True) if main_process else None)
    will_run = check_run(STAGES, stages, ctx, force)  # a refused run leaves the run's config.yaml as it was
    if "eval" in stages:  # its outputs too: not after the stages before it have run (the stage checks again)
        from train.evaluation.report import check_eval_outputs

        check_eval_outputs(run_dir)
    check_run_pairing(ctx, will_run)
    run_dir.mkdir(parents=True, exist_ok=True)
    save_yaml_config(cfg, run_dir / "config.yaml")
    t0 = time.perf_counter()
    from train.training.loop import TrainingInterrupted

    try:
        status = run_stages(STAGES, stages, ctx, force=force)
    except TrainingInterrupted as e:
        print(f"stopped: {e}", file=sys.stderr)
        return 130
    if main_process:
        print(json.dumps({"stages": status, "seconds": round(time.perf_counter() - t0, 1), "run_dir": str(run_dir)}))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
