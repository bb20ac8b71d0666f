"""Two-stream Gaussian model: forward time per batch against feature-map error.

Rows: Gaussian count × output size (the splat runs at 1/4 of it) × mode, where mode is
- ``fp32 all``: face + eyes + head renders, face stream computed;
- ``fp32 gaze-only``: same inputs but a new gaze, so the face stream comes from the cache;
- ``fp32 head only``: only the whole-head render (face-only / eye-only renders skipped);
- ``bf16 all``: CPU/CUDA autocast bf16 for the fields (splatting stays float32).
Error is the max |difference| of the head feature map against ``fp32 all`` (0 = identical). Writes
``out/benchmarks/gaussian_model.png``.

    .venv/bin/python benchmarks/gaussian_model.py [--gaussians 5000,20000] [--sizes 128,512] [--batch 2]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apps.preview import DEMO_MAX, MAX_SIDE  # noqa: E402
from benchmarks.common import (  # noqa: E402
    OUT_DIR,
    check_model_memory,
    count,
    format_table,
    machine_info,
    save_plot,
    timeit,
)
from toolkit.errors import CliParser, ToolkitError, run_cli  # noqa: E402
from toolkit.procedural import demo_camera, demo_head_scene  # noqa: E402
from train.model.gaussian_config import GaussianModelConfig  # noqa: E402
from train.model.gaussian_model import GaussianModel  # noqa: E402


def _counts(flag: str, text: str, least: int, most: int) -> list[int]:
    """A comma list of integers in [``least``, ``most``], or a one-line error naming ``flag``."""
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        values = []
    if not values or min(values) < least or max(values) > most:
        raise ToolkitError(f"{flag}: expected a comma list of integers in [{least}, {most}], got {text!r}")
    return values


def main(argv=None) -> int:
    ap = CliParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", default="5000,20000")
    ap.add_argument("--sizes", default="128,512")
    ap.add_argument("--batch", type=count("--batch", 1), default=2)
    ap.add_argument("--hidden", type=count("--hidden", 1), default=128)
    ap.add_argument("--repeats", type=count("--repeats", 1), default=3)
    a = ap.parse_args(argv)
    # Bounded before any head is built: the Gaussians as apps.preview's demo:N, the output side as its --size.
    gaussians, sizes = _counts("--gaussians", a.gaussians, 64, DEMO_MAX), _counts("--sizes", a.sizes, 16, MAX_SIDE)
    check_model_memory(f"--gaussians {max(gaussians)} --sizes {max(sizes)} --batch {a.batch} --hidden {a.hidden}",
                       max(gaussians), a.hidden, a.batch, max(sizes), hint="lower --gaussians, --sizes or --batch")
    print(machine_info())
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    rows, series = [], {}
    for n in gaussians:
        scene = demo_head_scene(n)
        torch.manual_seed(0)
        model = GaussianModel.from_scene(scene, GaussianModelConfig(hidden=a.hidden)).to(dev)
        for mlp in (model.face_field.expr_mlp, model.face_field.pose_mlp, model.eye_field.mlp):
            torch.nn.init.normal_(mlp.last.weight, std=0.05)  # a non-trivial (trained-like) deformation
        B = a.batch
        g = torch.Generator().manual_seed(0)
        code = (torch.randn(B, 144, generator=g) * 0.5).to(dev)
        pose = torch.zeros(B, 6, device=dev)
        gaze = ((torch.rand(B, 2, generator=g) - 0.5) * 0.6).to(dev)
        for size in sizes:
            cam = demo_camera(size, size)
            vm, K = cam.viewmat.expand(B, 4, 4).to(dev), cam.K.expand(B, 3, 3).to(dev)
            sync = dev == "cuda"

            def run(gz=gaze, renders=("head", "face", "eyes"), bf16=False, clear=True, model=model, code=code,
                    pose=pose, vm=vm, K=K, size=size):
                if clear:
                    model.clear_cache()
                with torch.no_grad(), torch.autocast(dev, dtype=torch.bfloat16, enabled=bf16):
                    return model(code, pose, gz, vm, K, size, size, renders=renders)

            ref = run()["head"]
            modes = {
                "fp32 all": lambda run=run: run(),
                "fp32 gaze-only": lambda run=run, gz=gaze + 0.1: run(gz=gz, clear=False),
                "fp32 head only": lambda run=run: run(renders=("head",)),
                "bf16 all": lambda run=run: run(bf16=True),
            }
            run()  # fill the cache for the gaze-only mode
            for mode, fn in modes.items():
                sec = timeit(fn, repeats=a.repeats, sync_cuda=sync)
                out = fn()["head"]
                err = 0.0 if mode == "fp32 gaze-only" else float((out - ref).abs().max())
                if mode == "fp32 gaze-only":
                    # The eyes moved, so compare against an uncached run with the same gaze instead.
                    err = float((out - run(gz=gaze + 0.1)["head"]).abs().max())
                rows.append({"gaussians": n, "output": f"{size}²", "splat": f"{size // 4}²", "mode": mode,
                             "ms_per_batch": 1000 * sec, "images_per_s": B / sec, "max_abs_err": err})
                series.setdefault(f"{mode} N={n}", ([], []))
                series[f"{mode} N={n}"][0].append(size)
                series[f"{mode} N={n}"][1].append(1000 * sec / B)
    print(format_table(rows))
    png = save_plot(OUT_DIR / "gaussian_model.png", series, xlabel="output size (px)", ylabel="ms per image",
                    title=f"two-stream Gaussian model forward (batch {a.batch}, {dev})", logy=True)
    print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
