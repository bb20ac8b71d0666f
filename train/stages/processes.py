"""Jobs of a stage run at once in spawned processes (the estimator stage's two estimators, the eval stage's
groups of test subjects), and the shipping of their tensors back."""

from __future__ import annotations

import torch

from toolkit.errors import ToolkitError
from toolkit.host import keep_freed_memory


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


def tensors_to_numpy(obj):
    """``obj`` with every tensor (in dicts and lists) as a numpy array: a spawned process's result must not hold
    tensors, which the queue would pass as shared-memory handles that die with the process."""
    if isinstance(obj, torch.Tensor):
        return obj.numpy()
    if isinstance(obj, dict):
        return {k: tensors_to_numpy(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [tensors_to_numpy(v) for v in obj]
    return obj


def tensors_from_numpy(obj):
    """The inverse of :func:`tensors_to_numpy`."""
    import numpy as np

    if isinstance(obj, np.ndarray):
        return torch.from_numpy(obj)
    if isinstance(obj, dict):
        return {k: tensors_from_numpy(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [tensors_from_numpy(v) for v in obj]
    return obj
