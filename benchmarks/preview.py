"""Preview splatter benchmark: FPS of full redraws and gaze-only updates, split by stage, with PSNR.

The scene is the procedural demo head (Gaussians on its surface, scales from 3-NN spacing) at N = 10k, 50k,
100k, 300k, rendered at 512 x 512 with the head filling the frame. Per N:
- full redraw: the camera orbits by 1 degree every frame, so each frame re-sorts and redraws everything;
- gaze-only: the camera stays, the eyes turn (as in live scrubbing); the frame redraws the eyes'
  rectangle from the per-camera depth layers (built once per camera: "layers ms");
- stages: sort (depth order, mid-layer order, footprints), upload (diff + pack + texture writes),
  draw (GL, synchronised), read-back; "total" is the whole frame including the app's scene update;
- quad px: fragment-shader work per frame (cut quads, plus the two layer copies for gaze-only);
- PSNR of the preview against ``render.splat.rasterize`` (the torch splatter) on the same frame.

    python benchmarks/preview.py [--sizes 10000 50000 100000 300000] [--res 512] [--frames 8]
"""

from __future__ import annotations

import math
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.common import OUT_DIR, count, format_table, machine_info, save_plot  # noqa: E402
from toolkit.errors import CliParser, run_cli  # noqa: E402


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-20))


def torch_reference(scene, colors, camera, background):
    """The torch splatter's picture of the same frame, or None where render.splat is not there yet."""
    try:
        from render.splat import rasterize
    except ImportError:
        return None
    with torch.no_grad():
        img, _, _ = rasterize(scene.means, scene.unit_quats, scene.scales, scene.opacities,
                              torch.from_numpy(colors), camera.viewmat[None], camera.K[None], camera.width,
                              camera.height, backgrounds=torch.as_tensor(background, dtype=torch.float32)[None])
    return img[0].numpy()


def run(n: int, res: int, frames: int, ctx) -> dict:
    from apps.gaze_scene import GazeScene, frame_camera, orbit_camera
    from render.preview import PreviewSplatter
    from render.preview_footprints import project_footprints
    from toolkit.procedural import demo_head_scene

    scene = demo_head_scene(n)
    gs = GazeScene.prepare(scene)
    base = frame_camera(scene, res, res)
    target = scene.means.median(0).values
    bg = np.ones(3, np.float32)
    sp = PreviewSplatter(res, res, ctx=ctx)
    t0 = time.perf_counter()
    gs.draw(sp, base)
    sp.read()
    first, upload_all = time.perf_counter() - t0, sp.stats["upload_s"]

    def frame(cam, gaze=(0.0, 0.0)):
        """One app frame (eye update, splatter draw, read-back) -> (wall s, process CPU s, stats)."""
        t, c = time.perf_counter(), time.process_time()
        gs.draw(sp, cam, *gaze)
        sp.read()
        return time.perf_counter() - t, time.process_time() - c, dict(sp.stats)

    # Full redraws: a 1-degree orbit step per frame forces a new order and a complete redraw.
    full = [frame(orbit_camera(base, target, math.radians(1.0 * (k % 2)), 0.0)) for k in range(frames + 1)][1:]
    assert all(s["path"] == "full" and s["resorted"] for *_, s in full), "full-redraw frames took a shortcut"
    # Gaze-only updates: same camera, the eyes sweep; the first one builds the depth layers.
    frame(base)
    gazes = [(0.35 * math.sin(0.7 * k + 0.3), 0.5 * math.cos(0.45 * k)) for k in range(frames + 1)]
    gaze = [frame(base, g) for g in gazes]
    layers_ms = 1e3 * gaze[0][2]["layers_s"]
    gaze = gaze[1:]
    assert gaze and all(s["path"] == "incremental" and not s["layers_built"] for *_, s in gaze)

    def med(rows, key):
        return 1e3 * statistics.median(s[key] for *_, s in rows)

    cam = base
    fp = project_footprints(sp._rows, cam.viewmat.numpy(), cam.K.numpy(), res, res)
    quad_full = float(fp["quad_area"].sum())
    x, y, w, h = sp.last_rect
    # Gaze-only fragment work: the mid-range Gaussians drawn, clipped to the rectangle, and two layer copies.
    mid_rows = sp._rows[_last_mid(sp)]
    fpm = project_footprints(mid_rows, cam.viewmat.numpy(), cam.K.numpy(), res, res)
    bb = fpm["bbox"]
    iw = np.clip(np.minimum(bb[:, 2], x + w) - np.maximum(bb[:, 0], x), 0, None)
    ih = np.clip(np.minimum(bb[:, 3], y + h) - np.maximum(bb[:, 1], y), 0, None)
    share = iw * ih / np.maximum((bb[:, 2] - bb[:, 0]) * (bb[:, 3] - bb[:, 1]), 1e-12)
    quad_gaze = float((fpm["quad_area"] * np.minimum(share, 1)).sum()) + 2.0 * w * h
    # Parity: the last gaze frame, the preview against the torch splatter.
    rgba = sp.read()
    prev_rgb = rgba[..., :3] + (1 - rgba[..., 3:]) * bg
    ref = torch_reference(gs.scene_at(*gazes[-1]), gs.colors, cam, bg)
    sp.release()
    ft, gt = statistics.median(t for t, *_ in full), statistics.median(t for t, *_ in gaze)
    return {
        "N": n, "first ms": 1e3 * first, "upload all ms": 1e3 * upload_all,
        "full sort": med(full, "sort_s"), "full upload": med(full, "upload_s"), "full draw": med(full, "draw_s"),
        "full read": med(full, "read_s"), "full ms": 1e3 * ft, "full FPS": 1 / ft,
        "full CPU ms": 1e3 * statistics.median(c for _, c, _ in full),
        "full 1-core FPS": 1 / statistics.median(c for _, c, _ in full),
        "layers ms": layers_ms,
        "gaze sort": med(gaze, "sort_s"), "gaze upload": med(gaze, "upload_s"),
        "gaze draw": med(gaze, "draw_s"), "gaze read": med(gaze, "read_s"),
        "gaze ms": 1e3 * gt, "gaze FPS": 1 / gt, "gaze CPU ms": 1e3 * statistics.median(c for _, c, _ in gaze),
        "gaze 1-core FPS": 1 / statistics.median(c for _, c, _ in gaze),
        "quad Mpx full": quad_full / 1e6, "quad Mpx gaze": quad_gaze / 1e6, "rect": f"{w}x{h}",
        "mid N": sp.stats.get("n_mid"), "gaze-frame PSNR dB": None if ref is None else psnr(prev_rgb, ref),
    }


def _last_mid(sp) -> np.ndarray:
    """Ids in the splatter's mid-layer index buffer (read back from GL)."""
    lst = sp._lists["mid"]
    return np.frombuffer(lst.buffer.read(size=4 * lst.count), np.int32).astype(np.int64)


def main(argv=None) -> None:
    ap = CliParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=count("--sizes", 1), nargs="+", default=[10000, 50000, 100000, 300000])
    ap.add_argument("--res", type=count("--res", 1), default=512)
    ap.add_argument("--frames", type=count("--frames", 1), default=8)
    args = ap.parse_args(argv)
    from render.gl_context import shared_context

    ctx = shared_context()
    print(machine_info())
    print(f"GL: {ctx.info['GL_RENDERER']} / {ctx.info['GL_VERSION']}; load: {os.getloadavg()}")
    rows = []
    for n in args.sizes:
        rows.append(run(n, args.res, args.frames, ctx))
        print(f"  N={n}: full {rows[-1]['full FPS']:.1f} FPS, gaze-only {rows[-1]['gaze FPS']:.1f} FPS", flush=True)
    print(f"\n{args.res}x{args.res}, times in ms (medians of {args.frames} frames); "
          "stages: sort / upload / draw / read")
    print("full redraw (camera moved 1 degree: re-sort + redraw everything)")
    print(format_table(rows, ["N", "upload all ms", "full sort", "full upload", "full draw", "full read", "full ms",
                              "full FPS", "full CPU ms", "full 1-core FPS", "quad Mpx full"]))
    print("\ngaze-only update (same camera, eyes turned: eye rectangle from the depth-layer cache)")
    print(format_table(rows, ["N", "layers ms", "gaze sort", "gaze upload", "gaze draw", "gaze read", "gaze ms",
                              "gaze FPS", "gaze CPU ms", "gaze 1-core FPS", "quad Mpx gaze", "mid N", "rect",
                              "gaze-frame PSNR dB"]))
    print("gaze-frame PSNR: the last incremental gaze frame against the torch splatter at that gaze (tests/render/"
          "test_preview_frames.py checks incremental frames equal full redraws)")
    print("CPU ms = process CPU time per frame, summed over its threads (llvmpipe's included): the frame's work, "
          "which other processes on a shared machine\ninflate less than the wall times above. '1-core FPS' = "
          "1000 / CPU ms is the rate if that work ran on one free core without waiting. It is a\nmeasure of "
          "cost, not a bound on the idle rate: llvmpipe's threads can run in parallel, and a frame can wait.")
    print(f"load after: {os.getloadavg()}")
    ns = [r["N"] for r in rows]
    path = save_plot(OUT_DIR / "preview.png", {
        "full redraw FPS": (ns, [r["full FPS"] for r in rows]),
        "gaze-only FPS": (ns, [r["gaze FPS"] for r in rows]),
        "full redraw, 1-core FPS (1 / CPU time)": (ns, [r["full 1-core FPS"] for r in rows]),
        "gaze-only, 1-core FPS (1 / CPU time)": (ns, [r["gaze 1-core FPS"] for r in rows]),
        "PSNR vs torch splatter (dB)": (ns, [r["gaze-frame PSNR dB"] or float("nan") for r in rows]),
    }, xlabel="Gaussians (demo head)", ylabel="FPS / dB", logx=True, logy=True,
        title=f"moderngl preview, {args.res}^2, {ctx.info['GL_RENDERER']}")
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
