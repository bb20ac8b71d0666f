"""``make demo``: the project's main job on its embedded default data (no downloads).

Step 1: builds the procedural Gaussian demo head (face Gaussians on an analytic head surface plus two
eyeballs, with part labels and RGB features), saves it as ``.safetensors`` and as a graphdeco 3DGS
``.ply`` under ``--out``, reloads both to check them, and prints a summary.
Step 2: renders a gaze sweep of the demo head through the headless preview splatter (each eye turned
rigidly about its own eyeball centre) as an .mp4 and a .png contact sheet.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

import torch

from toolkit.errors import ToolkitError, run_cli
from toolkit.procedural import demo_head_scene
from toolkit.scene import GaussianScene


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m apps.demo", description="Run the DiT-Gaze demo pipeline.")
    ap.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    ap.add_argument("--gaussians", type=int, default=20000, help="Gaussians in the demo head (default: 20000)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.gaussians < 64:
        raise ToolkitError(f"--gaussians must be >= 64, got {args.gaussians}")
    out = Path(args.out)
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

    from apps.preview import render_gaze_sweep

    print("== gaze sweep of the demo head (preview splatter) ==")
    pitches, yaws = [20, 0, -20], [-30, -15, 0, 15, 30]
    for name in ("gaze_sweep.mp4", "gaze_sweep.png"):
        info = render_gaze_sweep(scene, out / name, pitches, yaws, 256, 256)
        print(f"wrote {info['path']} ({len(info['gazes'])} gazes: pitch {pitches} x yaw {yaws} degrees)")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
