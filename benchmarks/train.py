"""Training of the gaussian stage: step time broken down, and held-out quality against wall-clock time.

Part 1, step breakdown: real ``GaussianTrainer.step`` calls (the stage's own step: main pass + weak
supervision pass), the parts timed in place by wrapping them (same inputs, same code path):

- ``fields``: the face deformation field and the eye rotation field (+ the rigid head transform);
- ``splat``: ``render.splat.rasterize`` calls;
- ``renderer``: ``renderer.training_forward`` (DiT: codec encode, noising, DiT, decode; U-Net: forward);
- ``losses``: image loss (L1 + SSIM), gaze loss (frozen estimator), orthogonality loss;
- ``other fwd``: the rest of the forward step (batch gather, RGB loss, gaze sampler, sums);
- ``backward``: ``total.backward()``; ``optim``: gradient clipping + Adam.

At the ``demo`` configuration (the run's geometry scene, codec and loss estimator) and at the ``paper`` one
(DiT-Gaze-paper at 512², codec downsample 8 / 64 channels, 224² estimator, hidden 256; untrained codec and
estimator, the procedural head; on CPU ``--paper-gaussians``/``--paper-batch`` below the paper's, as shown).

Part 2, time to quality: for each variant (default ``dit`` and ``unet``, i.e. ``gaussian.renderer=...``) the
stage's own ``train_loop`` + ``GaussianTrainer`` train from the same initialization seed for the same budget
of training time (``--budget-s`` each; evaluation time is not counted; ``--clock cpu``, the default on CPU,
counts this process's CPU seconds, which with one thread equal wall-clock on an idle core and do not depend on
other jobs sharing the machine; ``--clock wall`` counts wall-clock), and every ``--eval-every-s`` the held-out
PSNR/SSIM/gaze error of ``train.evaluation.protocol.evaluate`` is recorded (the eval stage's pairs and
metrics, ``--pairs`` pairs per held-out subject, but no test-time fit: the renders take the held-out subjects'
generator codes, so the curve follows the training alone and its PSNR is not the report's). Prints both tables
and writes ``out/benchmarks/train.png`` (PSNR against training seconds).

    .venv/bin/python benchmarks/train.py --run-dir out/demo/run [--budget-s 180] [--threads 1]
    .venv/bin/python benchmarks/train.py --run-dir RUN --skip-breakdown --variants dit:,nogaze:gaussian.lambda_gaze=0

``--run-dir`` needs the stages data, geometry, codec and estimator of a ``demo`` run (``make demo`` makes
one); without it they are run (demo preset) into ``out/benchmarks/train_run`` first (~6 CPU-minutes).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import typing
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import OUT_DIR, count, format_table, machine_info, positive, save_plot  # noqa: E402
from benchmarks.step_timing import PARTS, peak_memory_gib, time_steps  # noqa: E402
from toolkit.errors import CliParser, ToolkitError, run_cli  # noqa: E402
from train.run_config import GaussianStageConfig  # noqa: E402


# ----------------------------------------------------------------------------- the run
def open_prereqs(run_dir: Path, overrides: list[str]):
    """A ``TrainedRun`` whose stages data..estimator are up to date (run them when missing)."""
    from train import run
    from train.config import apply_overrides, load_yaml_config
    from train.run_config import RunConfig
    from train.stages import STAGES
    from train.stages.pipeline import RunContext, run_stages
    from train.trained_run import TrainedRun

    need = ("data", "geometry", "codec", "estimator")
    if not (run_dir / "config.yaml").is_file():
        print(f"[bench] no run at {run_dir}: running stages {need} with the demo preset first", flush=True)
        code = run.main(["--preset", "demo", "--run-dir", str(run_dir), "--stages", ",".join(need)])
        if code:
            raise ToolkitError(f"the prerequisite stages failed (exit {code})")
    ctx = RunContext(run_dir, apply_overrides(load_yaml_config(RunConfig, run_dir / "config.yaml"), overrides),
                     log=lambda m: None)
    run_stages(STAGES, [], ctx)
    missing = [s for s in need if s not in ctx.outputs]
    if missing:
        raise ToolkitError(f"{run_dir}: stage(s) {missing} are not up to date; run "
                           f"python -m train.run --run-dir {run_dir} --stages {','.join(need)}")
    return TrainedRun(ctx)


def with_overrides(trained, overrides: list[str]):
    """``trained`` (a ``TrainedRun``) under its config with ``overrides``, reading the same stage outputs."""
    from train.config import apply_overrides
    from train.stages.pipeline import RunContext
    from train.trained_run import TrainedRun

    c = trained.context
    return TrainedRun(RunContext(c.run_dir, apply_overrides(c.config, overrides), outputs=dict(c.outputs), log=c.log))


# ----------------------------------------------------------------------------- part 1: breakdown
def demo_trainer(trained, device):
    from train.training.trainer import GaussianTrainer, open_split

    cfg = trained.config
    torch.manual_seed(cfg.seed)
    model, renderer = trained.build_model(device)
    data = open_split(trained.split("train"), "all", cfg.data.res)  # the stage's reader
    trainer = GaussianTrainer(cfg.gaussian, model, renderer, trained.estimator("loss", device), data, device,
                              cfg.gaussian.steps, seed=cfg.seed)
    return trainer, model.num_face + model.num_eye


def paper_trainer(trained, device, n_gaussians: int, batch: int):
    """The paper configuration's modules (untrained codec/estimator, procedural head) on 512² data."""
    import torch.nn.functional as F

    from toolkit.cameras import resize_intrinsics
    from toolkit.procedural import demo_head_scene
    from train.estimator.config import GazeEstimatorConfig
    from train.estimator.network import GazeEstimator
    from train.model.codec import AutoencoderConfig, KLAutoencoder
    from train.model.gaussian_model import GaussianModel
    from train.model.renderer import make_renderer
    from train.presets import paper_preset
    from train.training.trainer import GaussianTrainer, TrainBatchData, model_config, open_split

    p = paper_preset()
    g = replace(p.gaussian, batch=batch)
    res = p.data.res
    torch.manual_seed(0)
    model = GaussianModel.from_scene(demo_head_scene(n_gaussians), model_config(g)).to(device)
    codec = KLAutoencoder(AutoencoderConfig(downsample=p.codec.downsample, base_channels=p.codec.base_channels)).to(device)
    renderer = make_renderer("dit", codec, model=g.dit_model, output_size=res, upscale=g.feature_upscale).to(device)
    est = GazeEstimator(GazeEstimatorConfig(input_size=p.estimator.input_size)).to(device)
    split = open_split(trained.split("train"), "all", trained.config.data.res, workers=0)
    n = min(len(split), 4 * batch)
    d, r0 = split.take(torch.arange(n), "cpu"), split.res  # its first n rows: all the paper's batches read
    split.close()
    up = lambda x, mode: F.interpolate(x, size=(res, res), mode=mode)  # noqa: E731
    data = TrainBatchData(image=up(d["image"], "bilinear"), head=up(d["head"], "nearest"),
                          eyes=up(d["eyes"], "nearest"), code=d["code"], pose=d["pose"], gaze_head=d["gaze_head"],
                          gaze_cam=d["gaze_cam"], head_pose_cam=d["head_pose_cam"], viewmat=d["viewmat"],
                          K=resize_intrinsics(d["K"], r0, r0, res, res), landmarks=d["landmarks"] * (res / r0))
    # The procedural head sits at the origin of its own frame like the geometry scene: the demo poses fit it.
    return GaussianTrainer(g, model, renderer, est, data, device, g.steps), n_gaussians


def unet_label(trained) -> str:
    """The baseline renderer as configured: GazeGaussian's renderer upsamples log2(feature_upscale) times, so at
    ``feature_upscale=1`` (the demo's) it is one 1x1 convolution of the splatted features, and says so."""
    up = trained.config.gaussian.feature_upscale
    return f"U-Net, upscale {up}" + (": a 1x1 conv, no upsampling blocks" if up == 1 else "")


def breakdown(trained, device, args) -> list[dict]:
    rows = []
    cfg = trained.config
    configs = [("demo", lambda: demo_trainer(trained, device), cfg.gaussian.batch, cfg.data.res, cfg.gaussian.dit_model)]
    run_preset = cfg.preset  # the row is the run's configuration, whichever preset made it
    if not args.skip_paper:
        configs.append(("paper", lambda: paper_trainer(trained, device, args.paper_gaussians, args.paper_batch),
                        args.paper_batch, 512, "DiT-Gaze-paper"))
    for name, make, batch, res, dit in configs:
        for kind in args.breakdown_renderers.split(","):
            if name == "paper" and kind != "dit":
                continue  # the paper configuration is the DiT's
            sub = with_overrides(trained, [f"gaussian.renderer={kind}"]) if name == "demo" else trained
            print(f"[bench] step breakdown: {name} / {kind} ...", flush=True)
            trainer, n_g = (demo_trainer(sub, device) if name == "demo" else make())
            params = [p for m in (trainer.model, trainer.renderer) for p in m.parameters() if p.requires_grad]
            clock = time.process_time if args.clock == "cpu" else time.perf_counter  # as the curves below
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            t = time_steps(trainer, params, device, warmup=args.warmup, repeats=args.repeats, clock=clock)
            shown = run_preset if name == "demo" else name
            label = f"{shown} ({res}², batch {batch}, {n_g} Gaussians, {dit if kind == 'dit' else unet_label(sub)})"
            if name == "paper" and (n_g, batch) != (100_000, 4):  # the paper's own scale needs no note
                label += " [paper: 100000 Gaussians, batch 4; reduced]"
            rows.append({"config": label, **{k: 1000 * v for k, v in t.items()}, "peak GiB": peak_memory_gib(device)})
    return rows


# ----------------------------------------------------------------------------- part 2: time to quality
class _BudgetReached(Exception):
    """A variant's training budget is spent: raised from the loop's log hook to stop it."""


def time_to_quality(trained, device, overrides: list[str], args, test_files) -> list[dict]:
    """Train the stage for ``budget_s`` seconds of training time; evaluate every ``eval_every_s``."""
    from train.evaluation.protocol import evaluate
    from train.run_config import eval_sampling_steps
    from train.training.loop import train_loop
    from train.training.trainer import GaussianTrainer, init_rgb, lr_factor, open_split, optimizer_groups

    sub = with_overrides(trained, overrides)
    cfg = sub.config
    g = cfg.gaussian
    torch.manual_seed(cfg.seed)
    model, renderer = sub.build_model(device)
    data = open_split(sub.split("train"), "all", cfg.data.res)  # the stage's reader
    if g.rgb_init:
        init_rgb(model, data)
    trainer = GaussianTrainer(g, model, renderer, sub.estimator("loss", device), data, device, g.steps,
                              seed=cfg.seed)
    est = sub.estimator("eval", device)
    opt = torch.optim.Adam(optimizer_groups(model, renderer, g))
    points: list[dict] = []
    now = time.process_time if args.clock == "cpu" else time.perf_counter
    clock = {"train": 0.0, "since": now(), "next_eval": 0.0}

    def measure(step: int) -> None:
        m = evaluate(model, renderer, est, test_files, res=cfg.data.res, pairs_per_subject=args.pairs,
                     sampling_steps=eval_sampling_steps(cfg), seed=cfg.seed, device=device, log=lambda s: None)["metrics"]
        points.append({"train_s": clock["train"], "step": step, "psnr": m["psnr"], "ssim": m["ssim"],
                       "gaze_deg": m["gaze_error_deg"]})
        print(f"[bench]   {clock['train']:6.1f} s, step {step:4d}: PSNR {points[-1]['psnr']:.2f} dB, "
              f"SSIM {points[-1]['ssim']:.3f}", flush=True)
        clock["next_eval"] = clock["train"] + args.eval_every_s

    def on_log(step: int, values: dict) -> None:
        clock["train"] += now() - clock["since"]
        clock["step"] = step
        if clock["train"] >= clock["next_eval"] or clock["train"] >= args.budget_s:
            measure(step)
        if clock["train"] >= args.budget_s:
            raise _BudgetReached
        clock["since"] = now()

    measure(0)
    clock["since"] = now()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            train_loop("gaussian", trainer.step, modules={"model": model, "renderer": renderer},
                       optimizers={"adam": opt}, steps=args.max_steps, run_dir=tmp, seed=cfg.seed,
                       ckpt_every=10**9, log_every=1, grad_clip=g.grad_clip, progress=False, on_log=on_log,
                       lr_factor=lr_factor(g))  # as the stage (and the sampler): over gaussian.steps, then its last rate
        except _BudgetReached:
            pass
    if points[-1]["step"] != clock.get("step", 0):  # stopped by --max-steps between two measurements
        measure(clock["step"])
    data.close()
    return points


RENDERERS = typing.get_args(typing.get_type_hints(GaussianStageConfig)["renderer"])
"""The values of ``gaussian.renderer``: the variant names that need no overrides."""


def check_overrides(overrides: list[str], flag: str = "") -> None:
    """The overrides' keys and values against the config's fields, before the prerequisite stages run: a typo
    would otherwise surface minutes later, after the breakdown. ``flag`` prefixes the error line."""
    from train.config import apply_overrides
    from train.run_config import RunConfig

    try:
        apply_overrides(RunConfig(), overrides)
    except ToolkitError as e:
        raise ToolkitError(f"{flag}: {e}" if flag else str(e)) from None


def parse_variants(spec: str) -> list[tuple[str, list[str]]]:
    """``"dit:gaussian.renderer=dit,unet:gaussian.renderer=unet"``; a bare name X (or ``X:``) means
    gaussian.renderer=X, so it must be one of :data:`RENDERERS`: anything else would silently measure the run
    config under a made-up name. Each variant's overrides are checked against the config's keys and types now,
    before the prerequisite stages and the breakdown run."""
    out = []
    for part in spec.split(","):
        name, _, ov = part.partition(":")
        if not name:
            raise ToolkitError(f"--variants: empty name in {spec!r}")
        ovs = [o for o in ov.split(";") if o]
        if not ovs:
            if name not in RENDERERS:
                raise ToolkitError(f"--variants: unknown variant {name!r}; a name without overrides is a renderer, "
                                   f"one of {list(RENDERERS)} (else give NAME:section.key=value;...)")
            ovs = [f"gaussian.renderer={name}"]
        check_overrides(ovs, f"--variants {name}")
        out.append((name, ovs))
    return out


def main(argv=None) -> int:
    ap = CliParser(description=__doc__.split("\n")[0], epilog=__doc__,
                   formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-dir", default=str(OUT_DIR / "train_run"), help="a demo run with its first four stages")
    ap.add_argument("--threads", type=count("--threads", 1), default=1, help="torch CPU threads (default 1)")
    ap.add_argument("--budget-s", type=positive("--budget-s"), default=180.0, help="training seconds per variant (default 180)")
    ap.add_argument("--clock", choices=("cpu", "wall"), default=None,
                    help="training time as process CPU seconds (default on CPU: with one thread it equals "
                         "wall-clock on an idle core and is robust to other jobs on a shared machine) or wall-clock "
                         "(default on CUDA)")
    ap.add_argument("--eval-every-s", type=positive("--eval-every-s"), default=45.0, help="training seconds between evaluations")
    ap.add_argument("--pairs", type=count("--pairs", 1), default=12, help="evaluation pairs per held-out subject")
    ap.add_argument("--max-steps", type=count("--max-steps", 1), default=100_000, help="stop a variant earlier at this many steps")
    ap.add_argument("--variants", default="dit,unet",
                    help="comma-separated NAME[:override;override...]; a NAME without overrides is a renderer, dit "
                         "or unet (gaussian.renderer=NAME; default dit,unet)")
    ap.add_argument("--breakdown-renderers", default="dit,unet")
    ap.add_argument("--paper-gaussians", type=count("--paper-gaussians", 1), default=20000)
    ap.add_argument("--paper-batch", type=count("--paper-batch", 1), default=1)
    ap.add_argument("--warmup", type=count("--warmup", 0), default=1)
    ap.add_argument("--repeats", type=count("--repeats", 1), default=3)
    ap.add_argument("--skip-breakdown", action="store_true")
    ap.add_argument("--skip-paper", action="store_true")
    ap.add_argument("--skip-curve", action="store_true")
    ap.add_argument("overrides", nargs="*", help="config overrides applied to every measurement (section.key=value)")
    args = ap.parse_args(argv)
    if args.budget_s <= 0 or args.eval_every_s <= 0:
        raise ToolkitError("--budget-s and --eval-every-s must be > 0")
    torch.set_num_threads(args.threads)
    print(machine_info())
    print(f"load average at start: {os.getloadavg()[0]:.2f} (1 min)")
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if args.clock is None:
        args.clock = "wall" if device.type == "cuda" else "cpu"
    if args.clock == "cpu" and args.threads != 1:
        print("note: --clock cpu with several threads counts the CPU time of all of them")
    variants = parse_variants(args.variants)  # before any measurement: a typo should not cost the breakdown
    check_overrides(args.overrides)
    trained = open_prereqs(Path(args.run_dir), args.overrides)
    if not args.skip_breakdown:
        rows = breakdown(trained, device, args)
        print(f"\nTraining step time ({'CPU ms of the training thread' if args.clock == 'cpu' else 'wall ms'}, median "
              f"of {args.repeats} steps after {args.warmup} warm-up; main pass + weak-supervision pass):")
        print(format_table(rows, ["config", *PARTS, "other fwd", "backward", "optim", "step", "peak GiB"]))
    if not args.skip_curve:
        test_files = trained.split("test")
        series, final = {}, []
        for name, ovs in variants:
            print(f"[bench] time to quality: {name} ({' '.join(ovs) or 'run config'}), {args.budget_s:.0f} "
                  f"{args.clock} s budget", flush=True)
            pts = time_to_quality(trained, device, ovs, args, test_files)
            series[name] = ([p["train_s"] for p in pts], [p["psnr"] for p in pts])
            last = pts[-1]
            final.append({"variant": name, "overrides": " ".join(ovs) or "-", "train s": last["train_s"],
                          "steps": last["step"], "s/step": last["train_s"] / max(1, last["step"]),
                          "PSNR dB": last["psnr"], "SSIM": last["ssim"], "gaze err deg": last["gaze_deg"],
                          "best PSNR": max(p["psnr"] for p in pts)})
            print("\n" + format_table([{"variant": name, **p} for p in pts]) + "\n")
        print(f"Held-out quality at equal training time ({args.budget_s:.0f} {args.clock} s each, "
              f"{len(test_files)} held-out subjects x {args.pairs} pairs):")
        print(format_table(final))
        path = save_plot(OUT_DIR / "train.png", series, xlabel=f"training time ({args.clock} s)",
                         ylabel="held-out PSNR (dB)", title=f"gaussian stage: time to quality "
                                                            f"({machine_info().split(',')[0]}, {args.threads} thread(s))")
        print(f"wrote {path}")
    print(f"load average at end: {os.getloadavg()[0]:.2f} (1 min)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
