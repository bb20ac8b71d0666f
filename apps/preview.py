"""Live gaze scrubbing of a Gaussian head: a glfw window, or a headless gaze sweep through EGL.

    python apps/preview.py SCENE                                  # window: drag to move the gaze
    python apps/preview.py SCENE --headless --sweep out/sweep.mp4  # or .png for a contact sheet
    python apps/preview.py demo:20000 --headless --sweep out/sweep.png --pitch -20:20:3 --yaw -30:30:5

Without a trained model, the eye Gaussians (part 1 and 2) rotate rigidly about each eyeball's centre
(from ``scene.metadata["eyes"]``, else a sphere fitted per eye): exact for the procedural demo head.
The picture comes from ``render.preview.PreviewSplatter`` and equals ``render.splat.rasterize``.

The scene, its cameras and gaze frames are ``apps/gaze_scene.py``; the headless sweep ``apps/preview_sweep.py``;
the window ``apps/preview_window.py``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Sequence

if __package__ in (None, ""):  # run as a script (python apps/preview.py): make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch

from apps.preview_sweep import MAX_FRAMES, MAX_GAZES, check_sweep, parse_range, render_gaze_sweep
from apps.preview_window import run_window
from toolkit.errors import CliParser, ToolkitError, run_cli
from toolkit.io import check_not_an_input, check_output_folder
from toolkit.limits import check_allocation, check_count

DEMO_MIN = 64
"""Fewest Gaussians of the procedural demo head (``demo:N``, ``apps.demo --gaussians``)."""
DEMO_MAX = 2_000_000
"""Most Gaussians of the procedural demo head (``demo:N``): ~15 us each to build (a 2 M head takes half a
minute), and a full preview frame of a few million already takes seconds on a software GL."""
DEMO_BYTES_PER_GAUSSIAN = 2048
"""Peak memory per demo Gaussian, generously: building the head (~0.5 KB measured) plus the preview's copies."""
MAX_SIDE = 8192
"""Largest --size side: its float targets alone take W x H x 16 bytes each, four of them."""
MAX_WINDOW_FRAMES = 10_000_000

WINDOW_HELP = """window controls:
  left drag / arrow keys        change gaze pitch and yaw
  shift + left drag / arrows    orbit the camera (right drag works too)
  R  reset gaze and camera      O  toggle the eye-region overlay
  S  save a screenshot (PNG)    Q / Esc  quit
"""


# ---------------------------------------------------------------------------------------------- scenes
def check_demo_gaussians(n: object, name: str, sized: str | None = None, how: str = "") -> int:
    """``n`` as the Gaussian count of a demo head, refused outside [DEMO_MIN, DEMO_MAX] or past the memory budget.
    ``name`` (and ``sized``, default ``name``) name the count in the range (and the memory) error; ``how`` says
    how it was given (" (demo:N)"). Shared by ``demo:N`` here and ``apps.demo --gaussians``: one rule for both."""
    n = check_count(n, name, DEMO_MIN, DEMO_MAX, f"a number of demo Gaussians{how}")
    check_allocation(n * DEMO_BYTES_PER_GAUSSIAN, sized or name, f"ask for fewer Gaussians{how}")
    return n


def load_trained_scene(run_dir: str):
    """A trained run directory (train/run.py) -> the model's Gaussians as an RGB scene.

    The two-stream model is posed with a training subject's code, the identity head pose and a frontal
    gaze; its feature channels 0..2 (supervised as the low-resolution RGB image) become the colours.
    The eyes are then scrubbed rigidly about their fitted eyeball centres, like any scene.
    """
    from train.data.dataset import GazeDataset
    from train.trained_run import TrainedRun

    run = TrainedRun.open(run_dir)
    model, _ = run.load_model("cpu")
    item = GazeDataset(run.split("train"), res=run.config.data.res)[0]
    code = torch.as_tensor(item["latent_code"]).float()[None]
    scene = model.export_scene(code, torch.zeros(1, 6), torch.zeros(1, 2))
    scene.features = scene.features[:, :3].clamp(0, 1)
    scene.metadata["feature_kind"] = "rgb"
    return scene.validate()


def load_scene(spec: str):
    """A ``.safetensors`` / ``.ply`` scene path, a trained run directory, or ``demo[:N]`` (the procedural head)."""
    from toolkit.io import check_readable_file
    from toolkit.procedural import demo_head_scene
    from toolkit.scene import GaussianScene

    if spec == "demo" or spec.startswith("demo:"):
        try:
            n = int(spec.split(":", 1)[1]) if ":" in spec else 20000
        except ValueError:
            raise ToolkitError(f"scene {spec!r}: expected demo or demo:N with an integer N") from None
        check_demo_gaussians(n, f"scene {spec}", how=" (demo:N)")
        return demo_head_scene(n)
    if os.path.isdir(spec) and os.path.isfile(os.path.join(spec, "config.yaml")):
        return load_trained_scene(spec)
    ext = os.path.splitext(spec)[1].lower()
    if ext not in (".ply", ".safetensors"):
        raise ToolkitError(f"{spec}: expected a .safetensors or .ply Gaussian scene, a trained run directory "
                           "(with config.yaml), or demo[:N]")
    check_readable_file(spec, "scene file")
    return GaussianScene.read(spec)


# ---------------------------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> int:
    ap = CliParser(
        prog="python apps/preview.py", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Preview a Gaussian head and scrub its gaze live (OpenGL; headless through EGL).",
        epilog=WINDOW_HELP + "\nSCENE is a .safetensors or .ply Gaussian scene, a trained run directory "
        "(train/run.py: its Gaussians' RGB channels, posed with a training subject's code), or demo[:N] for the "
        "procedural head. The eye Gaussians are rotated rigidly about their eyeball centres.")
    ap.add_argument("scene", help="scene file (.safetensors / .ply), a trained run directory, or demo[:N] "
                    f"(N in [{DEMO_MIN}, {DEMO_MAX}], default 20000)")
    ap.add_argument("--headless", action="store_true", help="no window: render --sweep through EGL")
    ap.add_argument("--sweep", help="headless output: .mp4 video or .png contact sheet of the gaze grid")
    ap.add_argument("--pitch", default="20:-20:3", help="pitch grid in degrees, MIN:MAX:N or a,b,c; the first is the "
                    f"top row (default 20:-20:3; at most {MAX_GAZES} gazes, {MAX_FRAMES} pitches x yaws)")
    ap.add_argument("--yaw", default="-30:30:5", help="yaw grid in degrees, MIN:MAX:N or a,b,c; write --yaw=-30:30:5 "
                    f"for a leading minus (default -30:30:5; at most {MAX_GAZES} gazes)")
    ap.add_argument("--size", type=int, nargs=2, default=(512, 512), metavar=("W", "H"),
                    help=f"image size, 1..{MAX_SIDE} pixels per side (an .mp4 sweep: 2..8191)")
    ap.add_argument("--background", default="1,1,1", help="background colour R,G,B in [0, 1]")
    ap.add_argument("--fps", type=float, default=8.0, help="video frame rate")
    ap.add_argument("--max-frames", type=int, default=None,
                    help=f"window: quit after this many frames (1..{MAX_WINDOW_FRAMES})")
    ap.add_argument("--screenshot-dir", default="out/preview", help="window: where S saves screenshots")
    args = ap.parse_args(argv)
    w, h = args.size
    check_count(w, "--size W", 1, MAX_SIDE, "pixels per side")
    check_count(h, "--size H", 1, MAX_SIDE, "pixels per side")
    check_allocation(4 * 16 * w * h, f"--size {w} {h} (the preview's float frames)", "lower --size")
    try:
        bg = [float(v) for v in args.background.split(",")]
        if len(bg) != 3 or not all(0.0 <= v <= 1.0 for v in bg):  # NaN fails the range too
            raise ValueError
    except ValueError:
        raise ToolkitError(f"--background: expected R,G,B each in [0, 1], got {args.background!r}") from None
    if not 0.1 <= args.fps <= 240:  # NaN too; OpenCV reports a bad rate as a missing encoder
        raise ToolkitError(f"--fps: expected a video frame rate in [0.1, 240], got {args.fps}")
    if args.max_frames is not None:
        check_count(args.max_frames, "--max-frames", 1, MAX_WINDOW_FRAMES, "a number of window frames")
    if args.headless and not args.sweep:
        raise ToolkitError("--headless needs --sweep OUT.mp4 or OUT.png")
    if args.sweep and not args.headless:
        raise ToolkitError("--sweep is the headless output: add --headless (without it the window opens)")
    if not args.headless:
        # Not a file in the way; whether it can be written is found when a screenshot is taken (most never are).
        check_output_folder(args.screenshot_dir, f"--screenshot-dir {args.screenshot_dir}", writable=False)
    if args.sweep:
        # Everything about the sweep is refused before the scene is loaded or built.
        pitches, yaws = parse_range(args.pitch, "pitch"), parse_range(args.yaw, "yaw")
        check_sweep(args.sweep, len(pitches), len(yaws), w, h)
        check_not_an_input(args.sweep, [args.scene], "--sweep", "scene")
    scene = load_scene(args.scene)
    if args.headless:
        t0 = time.perf_counter()
        res = render_gaze_sweep(scene, args.sweep, pitches, yaws, w, h, background=bg, fps=args.fps)
        print(f"wrote {res['path']} ({len(res['frames'])} gazes, {w}x{h}, {scene.num_gaussians} Gaussians) "
              f"in {time.perf_counter() - t0:.1f} s")
        return 0
    res = run_window(scene, w, h, background=bg, max_frames=args.max_frames, screenshot_dir=args.screenshot_dir)
    print(f"{res['frames']} frames, {res['fps']:.1f} FPS")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
