"""``make demo``: the project's main job on its embedded default data (no downloads).

Step 1: builds the procedural Gaussian demo head (face Gaussians on an analytic head surface plus two
eyeballs, with part labels and RGB features), saves it as ``.safetensors`` and as a graphdeco 3DGS
``.ply`` under ``--out``, reloads both to check them, and prints a summary.
Step 2: renders a gaze sweep of the demo head through the headless preview splatter (each eye turned
rigidly about its own eyeball centre) as an .mp4 and a .png contact sheet.
Step 3 (unless ``--skip-training``): the whole DiT-Gaze pipeline (``train/run.py``, ``demo`` preset) on
synthetic data generated on the fly: geometry, codec (none: the demo's DiT renders in pixel space), gaze
estimators, the two-stream Gaussian model with the DiT renderer, evaluation on held-out subjects against exact
ground truth (``report.md``), a gaze-sweep video of a held-out subject rendered by the trained model, and a
redirected mini-dataset (HDF5). The held-out face is fitted first, as the evaluation fits one, for the sweep,
and for the mini-dataset (``apps.redirect --fit-weights --natural-eyes``: eyes, not specks repainted for the
loss estimator; the demo preset's own fit, so both are fitted alike).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from apps.preview import DEMO_MAX, DEMO_MIN, check_demo_gaussians
from toolkit.errors import CliParser, ToolkitError, run_cli
from toolkit.io import check_output_folder
from toolkit.limits import check_count
from toolkit.procedural import demo_head_scene
from toolkit.scene import GaussianScene

DEFAULT_PRESET = "demo"
SEED_RANGE = (-(2**63), 2**64 - 1)
"""--seed seeds torch's generators alone (the pipeline's own seed is the config key ``seed``): what they take;
past 2^64 they overflow with a traceback."""


def main(argv: Sequence[str] | None = None) -> int:
    ap = CliParser(prog="python -m apps.demo", description="Run the DiT-Gaze demo pipeline.")
    ap.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    ap.add_argument("--gaussians", type=int, default=20000,
                    help=f"Gaussians in the demo head, {DEMO_MIN} to {DEMO_MAX} (default: 20000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the demo head, in [-2^63, 2^64) (default: 0)")
    ap.add_argument("--skip-training", action="store_true",
                    help="only the procedural head and its preview sweep (takes no --preset or overrides: "
                         "they configure the training)")
    ap.add_argument("--preset", default=None, help=f"train/run.py preset for the pipeline (default: {DEFAULT_PRESET})")
    ap.add_argument("overrides", nargs="*", help="train/run.py config overrides, e.g. gaussian.steps=100")
    args = ap.parse_args(argv)
    # Every flag is checked before the head is built or any file written: the pipeline's config included,
    # so a typo in an override is not found only after the head and both sweeps.
    check_demo_gaussians(args.gaussians, "--gaussians", sized=f"--gaussians {args.gaussians}")
    check_count(args.seed, "--seed", *SEED_RANGE, "a seed")
    if not args.out.strip():  # an empty path is the current folder: the demo's files would land among the user's
        raise ToolkitError("--out: expected an output folder, got an empty path")
    out = check_output_folder(args.out, "--out")
    if args.skip_training:
        if args.preset is not None or args.overrides:
            given = " ".join(([f"--preset {args.preset}"] if args.preset is not None else []) + args.overrides)
            raise ToolkitError(f"--skip-training runs no training, so {given} would be ignored: drop "
                               f"--skip-training, or drop --preset and the overrides")
    else:
        check_pipeline_config(args.preset or DEFAULT_PRESET, args.overrides)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)

    t0 = time.perf_counter()
    scene = demo_head_scene(args.gaussians, seed=args.seed)
    st_path, ply_path = out / "demo_head.safetensors", out / "demo_head.ply"
    scene.save(st_path)
    scene.to_ply(ply_path)
    for path, loaded in ((st_path, GaussianScene.load(st_path)), (ply_path, GaussianScene.from_ply(ply_path))):
        if not torch.equal(loaded.means, scene.means) or not torch.equal(loaded.features, scene.features):
            raise ToolkitError(f"{path}: round trip changed the scene")
    print("== procedural demo head ==")
    print(scene.summary())
    print(f"wrote {st_path} ({st_path.stat().st_size / 1e6:.1f} MB)")
    print(f"wrote {ply_path} ({ply_path.stat().st_size / 1e6:.1f} MB)")

    from apps.preview_sweep import render_gaze_sweep

    print("== gaze sweep of the demo head (preview splatter) ==")
    pitches, yaws = [20, 0, -20], [-30, -15, 0, 15, 30]
    for name in ("gaze_sweep.mp4", "gaze_sweep.png"):
        info = render_gaze_sweep(scene, out / name, pitches, yaws, 256, 256)
        print(f"wrote {info['path']} ({len(info['gazes'])} gazes: pitch {pitches} x yaw {yaws} degrees)")
    if not args.skip_training:
        run_pipeline(out, args.preset or DEFAULT_PRESET, args.overrides)
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


def check_pipeline_config(preset_name: str, overrides: list[str]) -> None:
    """The run config the pipeline will train with, checked as ``train.run`` checks it (the same preset, the
    same overrides, the same checks), so a bad preset or override is one line before the demo writes anything."""
    from train.config import apply_overrides
    from train.presets import PRESETS, preset
    from train.stages.artifacts import resolve_device
    from train.stages.checks import check_config

    if preset_name not in PRESETS:  # named here: train.run would print its own usage first
        raise ToolkitError(f"--preset: expected one of {sorted(PRESETS)}, got {preset_name!r}")
    cfg = apply_overrides(preset(preset_name), overrides)  # train.run's resolution when given a --preset
    check_config(cfg)
    resolve_device(cfg)


def most_frontal(head_poses) -> int:
    """Index of the smallest head rotation, |pitch| + |yaw|, in ``head_poses`` [N, 2] (the camera-frame head
    pose of each row): the sweep's view. Row 0 of a synthetic subject is a rig camera far below the chin,
    where no eye shows."""
    poses = np.asarray(head_poses, dtype=np.float32)
    if poses.size == 0:
        raise ToolkitError("demo: the held-out subject has no rows to sweep")
    return int(np.abs(poses).sum(-1).argmin())


def publish_report(run_dir: Path, dest: Path) -> None:
    """The run's ``report.md`` at ``dest`` (beside the run directory), its figure links pointing into the run."""
    import re

    from toolkit.io import atomic_write_text

    rel = Path(os.path.relpath(run_dir, dest.parent)).as_posix()
    text = (run_dir / "report.md").read_text(encoding="utf-8")
    atomic_write_text(dest, re.sub(r"\]\(([\w.-]+\.png)\)", lambda m: f"]({rel}/{m.group(1)})", text))


def run_pipeline(out: Path, preset: str, overrides: list[str]) -> None:
    """Train and evaluate on synthetic data, then sweep and redirect a held-out subject."""
    import h5py

    from apps import redirect
    from apps.preview_sweep import write_contact_sheet, write_video
    from train import run
    from train.data.dataset import GazeDataset
    from train.evaluation.figures import model_gaze_sweep, sweep_gazes
    from train.evaluation.fitting import restored_weights
    from train.run_config import eval_sampling_steps
    from train.trained_run import TrainedRun

    run_dir = out / "run"
    print(f"== DiT-Gaze pipeline ({preset} preset) -> {run_dir} ==", flush=True)
    code = run.main(["--preset", preset, "--run-dir", str(run_dir), *overrides])
    if code:
        raise ToolkitError(f"the training pipeline stopped (exit {code})")
    trained = TrainedRun.open(run_dir)
    cfg = trained.config
    test_file = trained.split("test")[0]
    model, renderer = trained.load_model("cpu")
    with h5py.File(test_file, "r") as f:  # the labels alone: no image needs decoding to choose the view
        row = most_frontal(f["face_head_pose"][:])
    item = GazeDataset([test_file], res=cfg.data.res)[row]
    n = cfg.eval.sweep_frames
    gazes = sweep_gazes(n)  # a circle of ±20° pitch, ±26° yaw
    # A held-out face: fitted first, as the evaluation fits one (at the sweep's gazes), then swept.
    fit_steps = cfg.eval.tta_steps
    with restored_weights(model, renderer):
        if fit_steps > 0:
            fit = trained.row_fitter(model, renderer, torch.device("cpu"), fit_steps)
            item = {**item, "latent_code": fit(item, gazes)[0]}
        frames = model_gaze_sweep(model, renderer, item, gazes, cfg.data.res, eval_sampling_steps(cfg))
    rgb = (frames.clamp(0, 1).permute(0, 2, 3, 1).numpy() * 255).round().astype("uint8")
    write_video(out / "heldout_gaze_sweep.mp4", rgb, fps=6)
    cols = min(n, 8)
    write_contact_sheet(out / "heldout_gaze_sweep.png", rgb, rows=-(-n // cols), cols=cols)
    redirected = out / "redirected_mini.h5"
    # Eyes turned, not repainted for the loss estimator (docs/redirect.md, "Natural eyes").
    redirect.main([str(run_dir), str(test_file), str(redirected), "--gazes", "grid:3x3:25", "--rows", "4"]
                  + (["--fit-weights", "--natural-eyes"] if fit_steps > 0 else []))
    report = out / "report.md"
    publish_report(run_dir, report)
    print("== outputs ==")
    for name, path in (("evaluation report", report), ("metrics", run_dir / "metrics.json"),
                       ("qualitative grid", run_dir / "qualitative.png"),
                       ("worst pairs' eyes", run_dir / "eyes.png"),
                       ("held-out gaze sweep (video)", out / "heldout_gaze_sweep.mp4"),
                       ("held-out gaze sweep (sheet)", out / "heldout_gaze_sweep.png"),
                       ("redirected mini-dataset", redirected), ("run config", run_dir / "config.yaml"),
                       ("training metrics", run_dir / "metrics.jsonl")):
        print(f"{name:>28}: {path}")


if __name__ == "__main__":
    sys.exit(run_cli(main))
