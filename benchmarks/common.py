"""Shared pieces of the benchmarks: machine banner, timing, a plain-text table and a PNG plot.

Benchmarks are programs, not tests: each prints a table of run time against error and writes a PNG
under ``out/benchmarks/``. Timings are medians of repeated runs after a warm-up.
"""

from __future__ import annotations

import io
import os
import platform
import resource
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_bytes
from toolkit.limits import check_allocation

OUT_DIR = Path(os.environ.get("DITGAZE_BENCH_OUT", "out/benchmarks"))

MODEL_GAUSSIAN_BYTES = 4 << 10
MODEL_ITEM_BYTES = 1 << 10
MODEL_HIDDEN_BYTES = 16
"""Peak memory per Gaussian of one ``GaussianModel`` in a forward + backward: 4 KB, plus for each batch item 1 KB
and 16 bytes per hidden unit of the field MLPs. Fitted to the peak resident memory of benchmarks.field_switches
(its four models of 40,000 Gaussians, hidden 64 and 128, batch 1 and 4, measured ~3.1 KB, ~0.8 KB and ~10 bytes)
and rounded up."""
MODEL_PIXEL_BYTES = 1024
"""Peak memory per rendered pixel and batch item, generously: 32 float32 feature channels of the head, face and
eye renders, their alphas and their gradients."""


def count(flag: str, least: int = 1) -> Callable[[str], int]:
    """An argparse type for the count flag ``flag``: an integer >= ``least``, else a one-line ToolkitError."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < least:
            raise ToolkitError(f"{flag}: expected an integer >= {least}, got {text!r}")
        return value

    return parse


def positive(flag: str) -> Callable[[str], float]:
    """An argparse type for the duration, rate or budget flag ``flag``: a finite number > 0."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not 0 < value < float("inf"):
            raise ToolkitError(f"{flag}: expected a positive finite number, got {text!r}")
        return value

    return parse


def check_device(device: str) -> torch.device:
    """The ``--device`` flag's value as a device: cpu, cuda or cuda:N, the CUDA ones only where CUDA is."""
    from toolkit.io import check_device as usable

    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise ToolkitError(f"--device: expected cpu, cuda or cuda:N, got {device!r}")
    return usable(device, "--device")  # CUDA present, GPU N among its GPUs


def check_model_memory(what: str, gaussians: int, hidden: int, batch: int, size: int, models: int = 1,
                       hint: str = "") -> None:
    """Refuse, before any model is built, a ``GaussianModel`` scale whose forward + backward would not fit the
    memory budget (``toolkit.limits``): ``models`` models of ``gaussians`` Gaussians with ``hidden``-wide fields,
    rendering ``batch`` images of ``size`` x ``size``. ``what`` names the flag."""
    per_gaussian = MODEL_GAUSSIAN_BYTES + batch * (MODEL_ITEM_BYTES + MODEL_HIDDEN_BYTES * hidden)
    check_allocation(models * gaussians * per_gaussian + models * batch * size * size * MODEL_PIXEL_BYTES, what, hint)


def machine_info() -> str:
    """One line naming the CPU, cores, torch version and threads (and the GPU where present)."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    gpu = f", GPU {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    return (f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__} ({torch.get_num_threads()} threads), "
            f"Python {platform.python_version()}{gpu}")


def timeit(fn: Callable[[], Any], *, repeats: int = 5, warmup: int = 1, sync_cuda: bool = False) -> float:
    """Median wall-clock seconds of ``fn()`` over ``repeats`` (>= 1) runs after ``warmup`` runs."""
    if repeats < 1:
        raise ValueError(f"timeit: repeats must be >= 1, got {repeats}")
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if sync_cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if sync_cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def peak_rss_gb() -> float:
    """Peak resident memory of this process so far, in GiB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def format_table(rows: Sequence[dict[str, Any]], columns: Sequence[str] | None = None) -> str:
    """Rows of dicts -> a Markdown table (floats to 4 significant digits; missing values as n/a)."""
    if not rows:
        return "(no rows)"
    columns = list(columns or rows[0].keys())

    def fmt(v: Any) -> str:
        if v is None:
            return "n/a"
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cells = [[fmt(r.get(c)) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    line = lambda vals: "| " + " | ".join(v.rjust(w) for v, w in zip(vals, widths)) + " |"  # noqa: E731
    return "\n".join([line(columns), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(r) for r in cells])


def save_plot(path: str | Path, series: dict[str, tuple[Sequence[float], Sequence[float]]], *, xlabel: str,
              ylabel: str, title: str, logx: bool = False, logy: bool = False) -> Path:
    """Write a line plot PNG: ``series`` maps a label to (x values, y values)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)  # its folder is made by the atomic writer
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    for label, (xs, ys) in series.items():
        ax.plot(list(xs), list(ys), marker="o", label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png")
    finally:
        plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def demo_or_tiny_run(tiny_name: str) -> str:
    """``out/demo/run`` when ``make demo`` trained it; else a tiny-preset run in ``OUT_DIR / tiny_name``, trained
    here once (seconds to minutes) and reused by later calls."""
    from train import run

    demo = Path("out/demo/run")
    if (demo / "gaussian" / "final.safetensors").is_file() and (demo / "stages" / "eval.json").is_file():
        return str(demo)
    tiny = OUT_DIR / tiny_name
    print(f"no trained demo run at {demo} (`make demo` makes one): using the tiny preset in {tiny}")
    if run.main(["--preset", "tiny", "--run-dir", str(tiny)]) != 0:
        raise SystemExit("training the tiny run failed")
    return str(tiny)
