"""A training step timed by parts, in place: the parts' callables wrapped by a timer (``benchmarks/train.py``'s
step breakdown; same inputs, same code path as the gaussian stage's step)."""

from __future__ import annotations

import functools
import statistics
import time

import torch

from toolkit.errors import ToolkitError

PARTS = ("fields", "splat", "renderer", "losses")


class PartTimer:
    """Wraps callables so their wall-clock time adds up under a part name (CUDA synchronized)."""

    def __init__(self, device: torch.device, clock=time.perf_counter):
        self.sync, self.clock, self.depth = device.type == "cuda", clock, 0
        self.reset()

    def wrap(self, part: str, fn):
        @functools.wraps(fn)
        def timed(*a, **kw):
            if self.depth:  # a part called from inside another part counts once (in the outer one)
                return fn(*a, **kw)
            if self.sync:
                torch.cuda.synchronize()
            self.depth += 1
            t0 = self.clock()
            try:
                return fn(*a, **kw)
            finally:
                if self.sync:
                    torch.cuda.synchronize()
                self.t[part] += self.clock() - t0
                self.depth -= 1
        return timed

    def reset(self) -> None:
        self.t = dict.fromkeys(PARTS, 0.0)


def instrument(trainer, timer: PartTimer) -> None:
    from render.splat import rasterize

    m = trainer.model
    m.face_stream = timer.wrap("fields", m.face_stream)
    m.eye_stream = timer.wrap("fields", m.eye_stream)
    m._posed = timer.wrap("fields", m._posed)
    m._rasterizer = timer.wrap("splat", rasterize)
    trainer.renderer.training_forward = timer.wrap("renderer", trainer.renderer.training_forward)
    for loss in (trainer.image_loss, trainer.gaze_loss):
        loss.forward = timer.wrap("losses", loss.forward)
    if trainer.ortho is not None:  # a plain callable object: replace it by a timed proxy of its bound __call__
        trainer.ortho = _Proxy(timer.wrap("losses", trainer.ortho.__call__))


class _Proxy:
    def __init__(self, fn):
        self.fn = fn

    def __call__(self, *a, **kw):
        return self.fn(*a, **kw)


def time_steps(trainer, params, device, *, warmup: int, repeats: int, seed: int = 0,
               clock=time.perf_counter) -> dict[str, float]:
    """Median seconds per part over ``repeats`` real training steps (after ``warmup``).

    ``clock``: ``time.perf_counter`` (wall) or ``time.process_time`` (the process's CPU time, all its threads:
    with one torch thread on CPU it measures the work itself and not the other jobs on a shared machine)."""
    from train.training.loop import step_generator

    timer = PartTimer(device, clock)
    instrument(trainer, timer)
    opt = torch.optim.Adam(params)
    rows = []
    for s in range(warmup + repeats):
        timer.reset()
        opt.zero_grad(set_to_none=True)
        sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
        sync()
        t0 = clock()
        terms = trainer.step(s, step_generator(seed, s))
        sync()
        t1 = clock()
        terms["total"].backward()
        sync()
        t2 = clock()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        sync()
        t3 = clock()
        if not torch.isfinite(terms["total"]):
            raise ToolkitError(f"benchmark step {s}: non-finite loss")
        row = dict(timer.t)
        row.update({"other fwd": (t1 - t0) - sum(timer.t.values()), "backward": t2 - t1, "optim": t3 - t2,
                    "step": t3 - t0})
        if s >= warmup:
            rows.append(row)
    return {k: statistics.median(r[k] for r in rows) for k in rows[0]}


def peak_memory_gib(device) -> float:
    """Peak memory since the last reset: the GPU's allocations on CUDA; on CPU this process's peak resident set
    so far (it never goes down, so a later row includes the earlier ones)."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux
