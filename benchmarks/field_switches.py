"""The Gaussian model's field switches: a training-like forward and backward per setting of
``field_input`` and ``eye_field_terms`` (docs/model.md), at the tiny preset's and the demo's scale.

Each row times the model alone: the head, face and eye renders of a batch, a loss summing them, and its backward,
with the last layers of every field MLP drawn at random (a trained-like model; zero-initialized ones would
skip no work but read as untrained). Settings are interleaved within each repeat, so a machine busy with other
work slows them alike; the clock is this process's CPU time on one thread. Prints a Markdown table and writes
``out/benchmarks/field_switches.png`` (ms per batch against the Gaussian count, one line per setting).

    .venv/bin/python benchmarks/field_switches.py [--scales 800:16:64:2,12000:64:128:4] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apps.preview import DEMO_MAX, MAX_SIDE  # noqa: E402
from benchmarks.common import OUT_DIR, check_model_memory, count, format_table, machine_info, save_plot  # noqa: E402
from toolkit.errors import CliParser, ToolkitError, run_cli  # noqa: E402
from toolkit.limits import check_count  # noqa: E402
from toolkit.procedural import demo_camera, demo_head_scene  # noqa: E402
from train.model.gaussian_config import GaussianModelConfig  # noqa: E402
from train.model.gaussian_model import GaussianModel  # noqa: E402

SETTINGS = {"position (default)": {}, "field_input=feature": {"field_input": "feature"},
            "eye_field_terms": {"eye_field_terms": True},
            "both (paper)": {"field_input": "feature", "eye_field_terms": True}}


def _scales(text: str) -> list[tuple[int, int, int, int]]:
    """``N:hidden:size:batch`` comma list, or a one-line error naming ``--scales``; each scale bounded before
    any head is built (N as ``apps.preview``'s ``demo:N``, the splat side as its ``--size``) and its models'
    memory checked (all four settings' models are alive at once)."""
    try:
        out = [tuple(int(v) for v in item.split(":")) for item in text.split(",") if item.strip()]
    except ValueError:
        out = []
    if not out or any(len(s) != 4 or min(s) < 1 or s[0] < 64 or s[2] < 16 for s in out):
        raise ToolkitError(f"--scales: expected a comma list of N:hidden:size:batch (N >= 64, size >= 16), got {text!r}")
    for n, hidden, size, batch in out:
        check_count(n, "--scales N", 64, DEMO_MAX, "a number of demo Gaussians")
        check_count(size, "--scales size", 16, MAX_SIDE, "pixels per side")
        check_model_memory(f"--scales {n}:{hidden}:{size}:{batch}", n, hidden, batch, size, models=len(SETTINGS),
                           hint="ask for a smaller scale")
    return out


def _time_scale(n: int, hidden: int, size: int, batch: int, repeats: int) -> dict[str, float]:
    """{setting: median CPU seconds of one forward + backward}."""
    scene, cam = demo_head_scene(n), demo_camera(size, size)
    g = torch.Generator().manual_seed(0)
    code, pose = torch.randn(batch, 144, generator=g) * 0.5, torch.zeros(batch, 6)
    gaze = (torch.rand(batch, 2, generator=g) - 0.5) * 0.6
    vm, K = cam.viewmat.expand(batch, 4, 4).clone(), cam.K.expand(batch, 3, 3).clone()
    models = {}
    for name, switches in SETTINGS.items():
        torch.manual_seed(0)
        models[name] = m = GaussianModel.from_scene(scene, GaussianModelConfig(hidden=hidden, render_scale=1.0,
                                                                                **switches))
        for mod in m.modules():
            if hasattr(mod, "last") and isinstance(mod.last, torch.nn.Linear):
                torch.nn.init.normal_(mod.last.weight, std=0.05, generator=g)
    times: dict[str, list[float]] = {k: [] for k in SETTINGS}
    for _ in range(repeats + 1):  # the first round warms up
        for name, m in models.items():
            m.zero_grad(set_to_none=True)
            m.clear_cache()
            t0 = time.process_time()
            out = m(code, pose, gaze, vm, K, size, size)
            sum(v.mean() for k, v in out.items() if not k.endswith("_alpha")).backward()
            times[name].append(time.process_time() - t0)
    return {k: statistics.median(v[1:]) for k, v in times.items()}


def main(argv=None) -> int:
    ap = CliParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scales", default="800:16:64:2,12000:64:128:4",
                    help="N:hidden:size:batch per scale (default: the tiny preset's, the demo's)")
    ap.add_argument("--repeats", type=count("--repeats", 1), default=5)
    a = ap.parse_args(argv)
    scales = _scales(a.scales)
    torch.set_num_threads(1)
    print(machine_info())
    rows, series = [], {name: ([], []) for name in SETTINGS}
    for n, hidden, size, batch in scales:
        t = _time_scale(n, hidden, size, batch, a.repeats)
        base = t["position (default)"]
        for name, sec in t.items():
            rows.append({"gaussians": n, "hidden": hidden, "splat": f"{size}²", "batch": batch, "setting": name,
                         "ms_fwd_bwd": 1000 * sec, "vs_default": sec / base})
            series[name][0].append(n)
            series[name][1].append(1000 * sec)
    print(format_table(rows))
    png = save_plot(OUT_DIR / "field_switches.png", series, xlabel="Gaussians", ylabel="ms per forward + backward",
                    title="Gaussian model, field switches (CPU, 1 thread)", logy=True)
    print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
