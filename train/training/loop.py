"""The training loop of the Gaussian stage (the one long training): resumable, NaN-guarded, interruptible,
logged. The codec and the gaze estimators train in minutes in loops of their own (``train.model.codec``,
``train.estimator.training``), which stop on a non-finite loss too but keep no checkpoints: a crashed one reruns.

A stage supplies ``step_fn(step, generator) -> {"total": loss, term: value, ...}``; the loop does the
backward pass, gradient clipping, the optimizer steps, periodic atomic checkpoints, metrics (JSONL and
optional TensorBoard) and a progress bar with the loss and ETA.

Determinism: the generator handed to ``step_fn`` is seeded from ``(seed, step)``, so the data a step
sees does not depend on how many steps ran in this process; with the RNG states restored from the
checkpoint, a resumed CPU run reproduces the uninterrupted one exactly.
"""

from __future__ import annotations

import json
import math
import os
import signal
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

import torch

from toolkit.errors import ToolkitError
from train.training.checkpoint import CheckpointManager, load_training_checkpoint
from train.training.distributed import DistInfo, all_ranks, average_gradients

StepFn = Callable[[int, torch.Generator], dict[str, torch.Tensor]]


class TrainingDiverged(ToolkitError):
    """A loss or gradient became NaN/inf; the message names the step, the terms and the last good checkpoint."""


class TrainingInterrupted(ToolkitError):
    """Ctrl-C / SIGTERM: a checkpoint was saved and the run stopped cleanly."""


def step_generator(seed: int, step: int, device: str | torch.device = "cpu") -> torch.Generator:
    """A generator whose stream depends only on (seed, step)."""
    g = torch.Generator(device=device)
    g.manual_seed((seed * 1_000_003 + step * 7919) % (2**63 - 1))
    return g


class MetricsLogger:
    """Appends one JSON object per logged step to ``metrics.jsonl``; mirrors scalars to TensorBoard if installed.

    The one output not written through ``toolkit.io.atomic_write``: a log that grows during the run. Each record
    is one ``write`` of a whole line on an ``O_APPEND`` descriptor, so a crash can tear at most the last line,
    and the records before it stay whole. TensorBoard's event files are streamed by its own writer."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True):
        self.path = Path(run_dir) / "metrics.jsonl"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(str(Path(run_dir) / "tb"))
            except Exception:  # tensorboard is an optional dependency (extra "eval")
                self._tb = None

    def start(self, stage: str, step: int) -> None:
        """``stage`` trains from ``step`` on (0, or the step a resume starts at): its records after that step,
        from a run that crashed or was re-run, are dropped, and so is a line torn by a crash, so the log holds
        each step of the model being trained once. Rewritten atomically; other stages' records are kept."""
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return
        except OSError as e:  # a directory or an unreadable file in its place: nothing trained yet
            raise ToolkitError(f"{self.path}: cannot read the metrics log ({e.strerror}); expected a file of "
                               "JSON lines (remove or move it to start a new log)") from None
        # Bytes, line by line: a line that is not UTF-8 is garbage like any other that is not a record, kept as it is.
        *whole, torn = data.split(b"\n")  # ``torn``: after the last newline, b"" or a line torn by a crash
        lines = [line + b"\n" for line in whole]

        def superseded(line: bytes) -> bool:
            try:
                rec = json.loads(line.decode("utf-8"))
            except (ValueError, RecursionError):  # UnicodeDecodeError among them; RecursionError: nested deep
                return False  # not ours to judge: kept as it is
            return isinstance(rec, dict) and rec.get("stage") == stage and isinstance(rec.get("step"), int) \
                and rec["step"] > step

        kept = b"".join(line for line in lines if not superseded(line))
        if kept != data:
            from toolkit.io import atomic_write_bytes

            atomic_write_bytes(self.path, kept)

    def log(self, stage: str, step: int, values: dict[str, float]) -> None:
        rec = {"stage": stage, "step": step, "time": time.time(), **values}
        line = (json.dumps(rec) + "\n").encode()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            os.write(fd, line)
        finally:
            os.close(fd)
        if self._tb is not None:
            for k, v in values.items():
                self._tb.add_scalar(f"{stage}/{k}", v, step)

    def close(self) -> None:
        if self._tb is not None:
            self._tb.flush()
            self._tb.close()


@contextmanager
def _stop_signals() -> Iterator[dict[str, bool]]:
    """Turn SIGINT/SIGTERM into a flag checked between steps (so a step is never cut in half)."""
    flag = {"stop": False}
    prev = {}

    def handler(signum, frame):  # noqa: ARG001
        flag["stop"] = True

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            prev[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread: signals stay with their defaults
            pass
    try:
        yield flag
    finally:
        for sig, h in prev.items():
            signal.signal(sig, h)


def train_loop(stage: str, step_fn: StepFn, *, modules: dict[str, torch.nn.Module],
               optimizers: dict[str, torch.optim.Optimizer], steps: int, run_dir: str | Path, seed: int = 0,
               ckpt_every: int = 100, log_every: int = 10, resume: bool = False, grad_clip: float | None = 1.0,
               metrics: MetricsLogger | None = None, progress: bool = True,
               lr_factor: Callable[[int], float] | None = None,
               on_log: Callable[[int, dict[str, float]], None] | None = None,
               after_step: Callable[[int], None] | None = None, is_main: bool = True,
               dist_info: DistInfo | None = None, fingerprint: str | None = None,
               log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run ``steps`` optimisation steps of ``step_fn``; returns {"step", "last": terms, "checkpoint"}.

    Checkpoints go to ``run_dir/checkpoints``. With ``resume``, training continues from the newest one.
    ``dist_info`` (torchrun): ``step_fn`` computes this rank's shard of the global batch; the loop averages
    the gradients over the ranks before clipping (:func:`train.training.distributed.average_gradients`) and stops every
    rank together on a non-finite loss. Logged terms are rank 0's shard's.
    ``lr_factor(step)``: each parameter group learns at its rate on entry times this factor at that step (a
    function of the step alone, so a resumed run follows the uninterrupted one's rates exactly).
    ``after_step(done)``: called after each step's optimizer update with the number of steps done, before that
    step's checkpoint (a weight average's update goes here, so the checkpoint holds it).
    ``fingerprint``: what the training depends on (its config but the step counts, its inputs), stored in every
    checkpoint; ``resume`` refuses a checkpoint written under another one. A run that does not resume starts
    from an empty checkpoint folder: another run's checkpoints would outnumber its own (the newest two are
    kept) and a later ``resume`` would load them. ``log``: where a skipped damaged checkpoint is reported.
    """
    _check_loop_settings(stage, ckpt_every, log_every, grad_clip)
    mgr = CheckpointManager(Path(run_dir) / "checkpoints")
    # The rates on entry, before a checkpoint's optimizer state (with the rates of its last step) replaces them.
    base_lrs = {name: [grp["lr"] for grp in opt.param_groups] for name, opt in optimizers.items()}
    start, last_ckpt = _starting_point(stage, mgr, modules, optimizers, resume=resume, fingerprint=fingerprint,
                                       is_main=is_main, log=log)
    if metrics is not None and is_main:
        metrics.start(stage, start)
    params = [p for m in modules.values() for p in m.parameters() if p.requires_grad]
    last: dict[str, float] = {}

    def save(step: int) -> Path | None:
        if not is_main:
            return None
        extra = {"stage": stage} if fingerprint is None else {"stage": stage, "fingerprint": fingerprint}
        return mgr.save(step, modules=modules, optimizers=optimizers, extra=extra)

    bar = _progress_bar(stage, steps, start) if progress and is_main else None
    step = start
    try:
        with _stop_signals() as flag:
            for step in range(start, steps):
                if _stop_requested(flag, dist_info):
                    last_ckpt = save(step)
                    raise TrainingInterrupted(
                        f"{stage}: interrupted at step {step}; checkpoint saved to {last_ckpt} (rerun with --resume)"
                    )
                total, values = _loss_terms(stage, step, step_fn, seed, modules, optimizers, params, dist_info,
                                            last_ckpt)
                gnorm = _optimizer_step(stage, step, total, values, params, optimizers, base_lrs, grad_clip,
                                        lr_factor, dist_info, last_ckpt)
                last = values
                done = step + 1
                if after_step is not None:
                    after_step(done)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix({k: f"{v:.4g}" for k, v in list(values.items())[:4]})
                if done % log_every == 0 or done == steps:
                    _log_step(stage, done, {**values, "grad_norm": float(gnorm)}, metrics if is_main else None, on_log)
                if done % ckpt_every == 0 or done == steps:
                    last_ckpt = save(done) or last_ckpt
            step = steps
            # A Ctrl-C during the last step: the run stops here, not in the next stage.
            if _stop_requested(flag, dist_info):
                raise TrainingInterrupted(f"{stage}: interrupted at its last step ({steps}); checkpoint saved to "
                                          f"{last_ckpt} (rerun with --resume to finish the stage)")
    finally:
        if bar is not None:
            bar.close()
    return {"step": step, "last": last, "checkpoint": last_ckpt}


def _check_loop_settings(stage: str, ckpt_every: int, log_every: int, grad_clip: float | None) -> None:
    if ckpt_every < 1 or log_every < 1:
        raise ToolkitError(f"{stage}: ckpt_every and log_every must be step counts >= 1, got {ckpt_every}, {log_every}")
    if grad_clip is not None and not (math.isfinite(grad_clip) and grad_clip >= 0):
        raise ToolkitError(f"{stage}: grad_clip must be a gradient-norm bound >= 0 (0 or None: no clipping), got {grad_clip}")


def _starting_point(stage: str, mgr: CheckpointManager, modules: dict[str, torch.nn.Module],
                    optimizers: dict[str, torch.optim.Optimizer], *, resume: bool, fingerprint: str | None,
                    is_main: bool, log: Callable[[str], None] | None) -> tuple[int, Path | None]:
    """``(first step, newest checkpoint)``: with ``resume`` the newest readable checkpoint is loaded into
    ``modules`` and ``optimizers`` (its fingerprint must match); without, the main rank deletes the old ones.
    Whatever keeps that from working (a directory under a checkpoint's name, checkpoints none of which reads)
    is refused here, before any step and with nothing deleted."""
    mgr.check_files()
    if not resume:
        if is_main:
            for old in mgr.all():
                old.unlink(missing_ok=True)
        return 0, None
    found = mgr.resume_from()  # reads checkpoint headers: once
    if found is None:
        return 0, None
    last_ckpt, meta = found
    if mgr.skipped and log is not None and is_main:
        log(f"[{stage}] skipped unreadable checkpoint(s) {[p.name for p in mgr.skipped]}; resuming from "
            f"{last_ckpt.name}")
    if fingerprint is not None and meta["extra"].get("fingerprint") != fingerprint:
        raise ToolkitError(f"{last_ckpt}: written by a run under another config or from other inputs than "
                           f"this one, so it cannot be resumed; rerun without --resume to train the stage afresh")
    return load_training_checkpoint(last_ckpt, modules=modules, optimizers=optimizers)["step"], last_ckpt


def _progress_bar(stage: str, steps: int, start: int):
    from tqdm import tqdm

    return tqdm(total=steps, initial=start, desc=stage, dynamic_ncols=True, leave=True)


def _stop_requested(flag: dict[str, bool], dist_info: DistInfo | None) -> bool:
    """Whether a signal asked to stop; under torchrun one rank's Ctrl-C stops all at the same step, before any
    collective."""
    stop = flag["stop"]
    if dist_info is not None:
        stop = not all_ranks(not stop, dist_info)
    return stop


def _loss_terms(stage: str, step: int, step_fn: StepFn, seed: int, modules: dict[str, torch.nn.Module],
                optimizers: dict[str, torch.optim.Optimizer], params: list[torch.Tensor],
                dist_info: DistInfo | None, last_ckpt: Path | None) -> tuple[torch.Tensor, dict[str, float]]:
    """``(total loss with its graph, every term as a float)`` of ``step_fn`` at ``step``, run in train mode
    with the gradients cleared; TrainingDiverged on non-finite weights or terms (on any rank)."""
    for m in modules.values():
        m.train()
    for opt in optimizers.values():
        opt.zero_grad(set_to_none=True)
    try:
        terms = step_fn(step, step_generator(seed, step))
    except ToolkitError as e:  # weights gone non-finite fail inside the forward pass, before any loss
        if all(bool(torch.isfinite(p).all()) for p in params):
            raise
        raise TrainingDiverged(f"{stage}: the weights are not finite at step {step} ({e}); last good "
                               f"checkpoint: {last_ckpt or 'none'}") from None
    values = {k: float(v.detach()) if isinstance(v, torch.Tensor) else float(v) for k, v in terms.items()}
    finite = all(math.isfinite(v) for v in values.values())
    if dist_info is not None:
        finite = all_ranks(finite, dist_info)
    if not finite:
        raise TrainingDiverged(f"{stage}: non-finite loss at step {step}: {_terms_text(values)}; last good "
                               f"checkpoint: {last_ckpt or 'none'}")
    return terms["total"], values


def _optimizer_step(stage: str, step: int, total: torch.Tensor, values: dict[str, float], params: list[torch.Tensor],
                    optimizers: dict[str, torch.optim.Optimizer], base_lrs: dict[str, list[float]],
                    grad_clip: float | None, lr_factor: Callable[[int], float] | None, dist_info: DistInfo | None,
                    last_ckpt: Path | None) -> torch.Tensor:
    """Backward pass of ``total``, gradients averaged over the ranks and clipped, every optimizer stepped at
    its base rates times ``lr_factor(step)``; returns the gradient norm before clipping (TrainingDiverged if
    it is not finite)."""
    total.backward()
    if dist_info is not None:
        average_gradients(params, dist_info)
    gnorm = torch.nn.utils.clip_grad_norm_(params, grad_clip if grad_clip else float("inf"))
    if not torch.isfinite(gnorm):
        raise TrainingDiverged(f"{stage}: non-finite gradient norm at step {step} (loss terms "
                               f"{_terms_text(values)}); last good checkpoint: {last_ckpt or 'none'}")
    factor = lr_factor(step) if lr_factor is not None else None
    for name, opt in optimizers.items():
        if factor is not None:
            for grp, base in zip(opt.param_groups, base_lrs[name]):
                grp["lr"] = base * factor
        opt.step()
    return gnorm


def _log_step(stage: str, done: int, values: dict[str, float], metrics: MetricsLogger | None,
              on_log: Callable[[int, dict[str, float]], None] | None) -> None:
    """Hand a logged step's terms (with ``grad_norm``) to the metrics log and the ``on_log`` hook."""
    if metrics is not None:
        metrics.log(stage, done, values)
    if on_log is not None:
        on_log(done, values)


def _terms_text(values: dict[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in values.items())
