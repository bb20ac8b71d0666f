"""Stage ``gaussian``: end-to-end training of the two-stream Gaussian model and its renderer (DiT or U-Net),
resumable from its checkpoints and distributed under ``torchrun``."""

from __future__ import annotations

import dataclasses

import torch

from toolkit.errors import ToolkitError
from train.run_config import RunConfig
from train.stages.artifacts import CODE_WIDTHS_KEY, RunArtifacts, resolve_device
from train.stages.pipeline import RunContext, Stage, fingerprint

GAUSSIAN_INPUTS = ("geometry", "codec", "estimator")
"""The stages whose outputs the Gaussian stage reads (its Gaussians, codec and loss estimator)."""
def gaussian_section(cfg: RunConfig):
    """The part of the config the Gaussian stage's fingerprint hashes: the seed and the ``gaussian`` section."""
    return cfg.seed, cfg.gaussian


def stage_gaussian(ctx: RunContext) -> dict[str, str]:
    """Train the model and the renderer for ``gaussian.steps`` steps (checkpoints in ``gaussian/checkpoints``;
    ``--resume`` continues from the newest) -> ``gaussian/final.safetensors``, the weight average when
    ``gaussian.ema_decay`` > 0."""
    from train.training.distributed import cleanup, init_distributed
    from train.training.trainer import open_split

    cfg = ctx.config
    start = resume_step(ctx)  # before any work: the checkpoints may refuse the run
    run = RunArtifacts(ctx)
    info = init_distributed(cfg.device if cfg.device != "auto" else "auto")
    device = torch.device(info.device) if info.enabled else resolve_device(cfg)
    torch.manual_seed(cfg.seed)
    model, renderer = run.build_model(device)  # at the training files' code widths (RunArtifacts.training_code_widths)
    # Read a batch at a time: the paper's split is ~75 GB as float32 tensors (docs/pipeline.md, Data in memory).
    data = open_split(run.split("train"), "all", cfg.data.res, layout=cfg.data.layout)
    try:
        return _train(ctx, run, info, device, model, renderer, data, start)
    finally:
        data.close()
        cleanup(info)


def load_pretrained_fields(ctx: RunContext, model) -> None:
    """Start the model's fields from the geometry stage's pre-trained ones when it wrote them
    (``geometry.pretrain_fields``, :mod:`train.stages.field_pretrain`)."""
    fields = ctx.outputs.get("geometry", {}).get("fields")
    if fields is None:
        return
    from train.stages.field_pretrain import load_fields

    names = load_fields(model, ctx.run_dir / fields)
    ctx.log(f"[gaussian] {', '.join(names)} start from the geometry stage's pre-training ({fields})")


def resume_step(ctx: RunContext) -> int:
    """The step the stage starts at: 0, or under ``--resume`` the step recorded in the newest readable checkpoint
    (a name could lie; :meth:`~train.training.checkpoint.CheckpointManager.newest` refuses one that does). A
    directory under a checkpoint's name, or checkpoints none of which reads, are refused here, before the
    model is built."""
    from train.training.checkpoint import CheckpointManager

    mgr = CheckpointManager(ctx.run_dir / "gaussian" / "checkpoints")
    mgr.check_files()
    found = mgr.resume_from() if ctx.resume else None
    if found is None:
        return 0
    path, meta = found
    ema_decay = ctx.config.gaussian.ema_decay
    if ema_decay > 0 and "ema_model" not in meta["modules"]:
        raise ToolkitError(f"{path}: written without a weight average, so it cannot resume with "
                           f"gaussian.ema_decay={ema_decay}; resume with the run's earlier value (0), or "
                           "rerun the stage without --resume")
    return meta["step"]


def _train(ctx: RunContext, run: RunArtifacts, info, device, model, renderer, data, start: int) -> dict[str, str]:
    """The stage's training on ``data`` (:class:`train.training.trainer.TrainRows`) from the built modules, from
    step ``start`` (:func:`resume_step`)."""
    from train.training.checkpoint import save_training_checkpoint
    from train.training.distributed import shard
    from train.training.loop import MetricsLogger, train_loop
    from train.training.trainer import GaussianTrainer, init_rgb, lr_factor, optimizer_groups

    cfg = ctx.config
    g = cfg.gaussian
    if g.rgb_init:
        seen = init_rgb(model, data)
        ctx.log(f"[gaussian] RGB channels initialized from the training images ({100 * seen:.0f}% of the Gaussians seen)")
    # After the RGB initialization, as the pre-training ran: its fields were trained on the colours the fresh
    # (undeformed) fields give, which those loaded now would change under gaussian.field_input=feature.
    load_pretrained_fields(ctx, model)
    trainer = GaussianTrainer(g, model, renderer, run.estimator("loss", device), data, device, g.steps,
                              shard=shard(g.batch, info) if info.enabled else None, seed=cfg.seed)
    opt = torch.optim.Adam(optimizer_groups(model, renderer, g))
    stage_dir = ctx.run_dir / "gaussian"
    # The sampler's draws of the steps before ``start``; none past the last step, which no step would use.
    trainer.fast_forward(min(start, g.steps))
    modules, final, after_step = _trained_modules(model, renderer, g.ema_decay)
    metrics = MetricsLogger(ctx.run_dir, tensorboard=True)
    try:
        train_loop("gaussian", trainer.step, modules=modules, optimizers={"adam": opt},
                   steps=g.steps, run_dir=stage_dir, seed=cfg.seed, ckpt_every=g.ckpt_every, log_every=g.log_every,
                   resume=ctx.resume, grad_clip=g.grad_clip, metrics=metrics, is_main=info.is_main,
                   dist_info=info if info.enabled else None, lr_factor=lr_factor(g), after_step=after_step,
                   fingerprint=_resume_key(ctx), log=ctx.log)
        if info.is_main:  # the ranks hold the same weights; the others wait for this file at cleanup's barrier
            save_training_checkpoint(stage_dir / "final.safetensors", step=g.steps, modules=final,
                                     extra={"renderer": g.renderer, "ema_decay": g.ema_decay,
                                            CODE_WIDTHS_KEY: [model.config.identity_dim, model.config.expression_dim]})
    finally:
        metrics.close()
    return {"checkpoint": "gaussian/final.safetensors"}


def _trained_modules(model, renderer, ema_decay: float):
    """(the modules the checkpoints hold, the modules the final file holds, the loop's after-step hook): with
    ``ema_decay`` > 0 a weight average of the model and the renderer, updated after every step, is checkpointed
    too and is what the final file holds."""
    modules = {"model": model, "renderer": renderer}
    if not ema_decay > 0:
        return modules, modules, None
    from train.training.ema import averaged_copy, update_average

    final = {"model": averaged_copy(model), "renderer": averaged_copy(renderer)}

    def after_step(done: int) -> None:  # noqa: ARG001
        for name in ("model", "renderer"):
            update_average(final[name], modules[name], ema_decay)

    return {**modules, "ema_model": final["model"], "ema_renderer": final["renderer"]}, final, after_step


def _resume_key(ctx: RunContext) -> str:
    """What the Gaussian stage's checkpoints must share with a run that resumes them: the stage's own fingerprint
    (its seed and config, the fingerprints of the stages it reads) with the step counts left out, since a
    resumed run may train longer, or checkpoint and log at other intervals."""
    counts = dataclasses.replace(ctx.config.gaussian, steps=1, ckpt_every=1, log_every=1)
    stage = Stage("gaussian", stage_gaussian, GAUSSIAN_INPUTS, config=gaussian_section)
    return fingerprint(stage, dataclasses.replace(ctx.config, gaussian=counts), ctx.fingerprints)
