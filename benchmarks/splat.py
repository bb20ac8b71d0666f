"""Benchmark of render.splat: run time, peak memory and error against a dense reference.

    .venv/bin/python benchmarks/splat.py            # full grid (several minutes on 2 cores)
    .venv/bin/python benchmarks/splat.py --quick    # small subset (about a minute)

Grid: N in {10k, 50k, 100k, 200k} x resolution {128, 256, 512} x D {3, 32}, on the procedural demo head
(``toolkit.procedural.demo_head_scene`` framed by ``demo_camera``, the head fills the frame) and on a random
cloud. Each configuration runs in a fresh subprocess so its peak RSS is its own. Error is the max |difference|
against a dense (every pixel x every Gaussian, pixel-chunked) reference where that costs at most
``--ref-budget`` pixel-Gaussian pairs, and the fraction of pixels that differ by more than 1e-5. A second
table sweeps the knobs (tile size, chunk, alpha and T thresholds) on one scene, with the error against the
default (reference) settings. A third compares one call for a batch of C cameras, each with its own posed
head (``means [C, N, 3]``, as the gaussian stage renders a training batch), against C single-camera calls,
with the largest difference between the two. Writes out/benchmarks/splat_grid.png, splat_knobs.png and
splat_batch.png.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    OUT_DIR,
    count,
    format_table,
    machine_info,
    peak_rss_gb,
    positive,
    save_plot,
    timeit,
)
from toolkit.errors import CliParser  # noqa: E402


def make_scene(kind: str, n: int, res: int, d: int, device: str):
    """(args tuple for rasterize) for the demo head or a random cloud filling the same camera."""
    from toolkit.procedural import demo_camera, demo_head_scene

    cam = demo_camera(res, res)
    g = torch.Generator().manual_seed(0)
    if kind == "head":
        s = demo_head_scene(n, seed=0)
        means, quats, scales, opac = s.means, s.unit_quats, s.scales, s.opacities
    else:
        means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([0.2, 0.25, 0.2])
        quats = torch.randn(n, 4, generator=g)
        scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 - 5.5)
        opac = torch.rand(n, generator=g) * 0.9 + 0.05
    feats = torch.rand(n, d, generator=g)
    t = [x.to(device) for x in (means, quats, scales, opac, feats, cam.viewmat[None], cam.K[None])]
    return (*t, res, res)


@torch.no_grad()
def dense_reference(args):
    """Every pixel x every visible Gaussian with the same projection and thresholds (front-to-back cumprod)."""
    from render._raster import ALPHA_MAX, ALPHA_MIN, T_MIN
    from render.projection import project_gaussians

    means, quats, scales, opac, feats, V, K, w, h = args
    p = project_gaussians(means, quats, scales, V, K, w, h)
    vis = (p.radii[0] > 0).all(-1) & (opac > ALPHA_MIN)
    ids = torch.nonzero(vis).flatten()
    ids = ids[torch.argsort(p.depths[0, ids], stable=True)]
    m2d, con, o, f = p.means2d[0, ids].double(), p.conics[0, ids].double(), opac[ids].double(), feats[ids].double()
    jj, ii = torch.meshgrid(torch.arange(w), torch.arange(h), indexing="xy")
    pix = torch.stack([jj.reshape(-1) + 0.5, ii.reshape(-1) + 0.5], -1).double()
    out = torch.zeros(pix.shape[0], f.shape[1], dtype=torch.float64)
    pixel_chunk = max(1, int(1e7 // max(1, ids.numel())))  # bounds the [pixels x Gaussians] temporaries
    for s in range(0, pix.shape[0], pixel_chunk):
        d = pix[s:s + pixel_chunk, None, :] - m2d[None]
        sig = 0.5 * (con[:, 0] * d[..., 0] ** 2 + con[:, 2] * d[..., 1] ** 2) + con[:, 1] * d[..., 0] * d[..., 1]
        a = torch.clamp(o * torch.exp(-sig), max=ALPHA_MAX)
        a = torch.where((sig >= 0) & (a >= ALPHA_MIN), a, torch.zeros_like(a))
        T_after = torch.cumprod(1 - a, 1)
        T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], 1)
        wgt = a * T_before * (T_after > T_MIN)
        out[s:s + pixel_chunk] = wgt @ f
    return out.view(h, w, -1).float()


def run_config(cfg: dict) -> dict:
    """One configuration in its own process: timings, peak RSS and error."""
    torch.set_num_threads(cfg["threads"])
    from render.splat import rasterize

    dev = cfg.get("device", "cpu")
    args = make_scene(cfg["kind"], cfg["n"], cfg["res"], cfg["d"], dev)
    base_rss = peak_rss_gb()
    kw = cfg.get("kw", {})
    sync = dev == "cuda"

    def fwd():
        with torch.no_grad():
            return rasterize(*args, **kw)

    leaves = [args[0].clone().requires_grad_(True), args[1].clone().requires_grad_(True),
              args[2].clone().requires_grad_(True), args[3].clone().requires_grad_(True),
              args[4].clone().requires_grad_(True)]

    def fwd_bwd():
        img, alpha, _ = rasterize(*leaves, *args[5:], **kw)
        (img.square().sum() + alpha.sum()).backward()

    reps = cfg.get("repeats", 3)

    def timed(fn):
        """(median wall seconds, mean CPU seconds) per call over the repeats, after one discarded warm-up call."""
        fn()
        c0 = time.process_time()
        wall = timeit(fn, repeats=reps, warmup=0, sync_cuda=sync)
        return wall, (time.process_time() - c0) / reps

    t_fwd, c_fwd = timed(fwd)
    t_fb, c_fb = timed(fwd_bwd)
    img, _, meta = fwd()
    # CPU seconds of this process per call, summed over its threads: the work done, which a loaded shared
    # machine inflates less than it inflates the wall clock. On an idle machine it is up to `threads` times
    # the wall clock, so compare it between rows, not with the wall-clock columns.
    row = dict(scene=cfg["kind"], N=cfg["n"], res=cfg["res"], D=cfg["d"], fwd_s=t_fwd, fwd_bwd_s=t_fb,
               fwd_cpu_s=c_fwd, fwd_bwd_cpu_s=c_fb,
               peak_rss_gb=peak_rss_gb(), rss_over_base_gb=peak_rss_gb() - base_rss,
               pairs=meta["counters"]["intersections"], rounds=meta["counters"]["rounds"])
    if sync:
        row["peak_cuda_gb"] = torch.cuda.max_memory_allocated() / 1024**3
    if cfg.get("ref_default"):
        with torch.no_grad():
            ref = rasterize(*args)[0][0]
        diff = (img[0] - ref).abs().amax(-1)
        row.update(max_err=float(diff.max()), frac_gt_1e5=float((diff > 1e-5).float().mean()))
    elif cfg["n"] * cfg["res"] ** 2 <= cfg["ref_budget"]:
        ref = dense_reference([a.cpu() if isinstance(a, torch.Tensor) else a for a in args])
        diff = (img[0].cpu() - ref).abs().amax(-1)
        row.update(max_err=float(diff.max()), frac_gt_1e5=float((diff > 1e-5).float().mean()))
    return row


def camera_batch_row(c: int, res: int, n: int, device: str, repeats: int = 5) -> dict:
    """fwd+bwd seconds of one rasterize call over C cameras (camera c sees its own posed copy of the head,
    turned by a few degrees) against C single-camera calls, and their largest difference."""
    from render.splat import rasterize
    from toolkit.procedural import demo_camera, demo_head_scene
    from toolkit.rotations import matrix_to_quat, quat_multiply, so3_exp

    s = demo_head_scene(n, seed=0)
    g = torch.Generator().manual_seed(1)
    R = so3_exp(torch.randn(c, 3, generator=g) * 0.1)  # [C, 3, 3] a different head pose per camera
    means = torch.einsum("cij,nj->cni", R, s.means)
    quats = quat_multiply(matrix_to_quat(R)[:, None].expand(c, n, 4), s.unit_quats[None].expand(c, n, 4))
    cam = demo_camera(res, res)
    t = [x.to(device) for x in (means, quats, s.scales[None].expand(c, n, 3), s.opacities[None].expand(c, n),
                                torch.rand(c, n, 32, generator=g), cam.viewmat[None].expand(c, 4, 4),
                                cam.K[None].expand(c, 3, 3))]
    leaves = [x.clone().requires_grad_(True) for x in t[:5]]

    def batched():
        img, alpha, _ = rasterize(*leaves, t[5], t[6], res, res)
        (img.square().sum() + alpha.sum()).backward()
        return img.detach()

    def looped():
        imgs = []
        for k in range(c):
            img, alpha, _ = rasterize(*(x[k] for x in leaves), t[5][k:k + 1], t[6][k:k + 1], res, res)
            (img.square().sum() + alpha.sum()).backward()
            imgs.append(img.detach())
        return torch.cat(imgs)

    sync = device == "cuda"
    err = float((batched() - looped()).abs().max())
    return dict(device=device, cameras=c, res=res, N=n, one_call_s=timeit(batched, repeats=repeats, sync_cuda=sync),
                per_camera_calls_s=timeit(looped, repeats=repeats, sync_cuda=sync), max_abs_diff=err)


def run_all(cfgs: list[dict]) -> list[dict]:
    rows = []
    ctx = mp.get_context("spawn")
    for cfg in cfgs:
        with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx) as ex:
            row = ex.submit(run_config, cfg).result()
        extra = {k: v for k, v in cfg.get("kw", {}).items()}
        row.update(extra)
        rows.append(row)
        print("  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
              flush=True)
    return rows


def main(argv=None) -> int:
    ap = CliParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small subset (about a minute)")
    ap.add_argument("--threads", type=count("--threads", 1), default=torch.get_num_threads())
    ap.add_argument("--ref-budget", type=positive("--ref-budget"), default=4e8, help="max pixel x Gaussian pairs for the dense ref")
    ap.add_argument("--cuda", action="store_true", help="also time on CUDA where available")
    ap.add_argument("--no-knobs", action="store_true")
    a = ap.parse_args(argv)
    print(machine_info())
    print(f"load average (1, 5, 15 min): {os.getloadavg()}; benchmark threads: {a.threads}")
    if a.quick:
        grid = [(k, n, r, d) for k in ("head",) for n in (10_000, 20_000) for r in (128, 256) for d in (3, 32)]
        grid += [("head", 100_000, 512, 32), ("cloud", 20_000, 256, 32)]
    else:
        grid = [(k, n, r, d) for k in ("head", "cloud") for n in (10_000, 50_000, 100_000, 200_000)
                for r in (128, 256, 512) for d in (3, 32)]
        grid.insert(0, ("head", 20_000, 256, 32))
    devices = ["cpu"] + (["cuda"] if a.cuda and torch.cuda.is_available() else [])
    grid_section(a, grid, devices)
    if not a.no_knobs:
        knob_sections(a)
    torch.set_num_threads(a.threads)
    camera_batch_section(a, devices)
    print(f"load average after: {os.getloadavg()}")
    return 0


def grid_section(a: argparse.Namespace, grid: list[tuple], devices: list[str]) -> None:
    """The (scene, N, res, D) grid on each device: table and splat_grid.png."""
    cfgs = [dict(kind=k, n=n, res=r, d=d, threads=a.threads, ref_budget=a.ref_budget, device=dev)
            for dev in devices for (k, n, r, d) in grid]
    print(f"\n## grid ({len(cfgs)} configurations; error vs dense reference where N x pixels <= {a.ref_budget:g})")
    rows = run_all(cfgs)
    for r, c in zip(rows, cfgs):
        r["device"] = c["device"]
    cols = ["device", "scene", "N", "res", "D", "fwd_s", "fwd_bwd_s", "fwd_cpu_s", "fwd_bwd_cpu_s", "peak_rss_gb", "rss_over_base_gb", "pairs",
            "rounds", "max_err", "frac_gt_1e5"]
    print(format_table(rows, cols))
    series = {}
    for r in rows:
        if r["D"] == 32 and r["device"] == "cpu":
            key = f"{r['scene']} {r['res']}^2 fwd+bwd"
            series.setdefault(key, ([], []))
            series[key][0].append(r["N"])
            series[key][1].append(r["fwd_bwd_s"])
    png = save_plot(OUT_DIR / "splat_grid.png", series, xlabel="Gaussians", ylabel="seconds (median)",
                    title=f"render.splat fwd+bwd, D=32 ({a.threads} threads)\n{machine_info()[:90]}", logx=True,
                    logy=True)
    print(f"wrote {png}")


def knob_sections(a: argparse.Namespace) -> None:
    """The knobs against the default settings on one scene (splat_knobs.png), then the chunk on a small image."""
    base = dict(kind="head", n=20_000, res=256, d=32, threads=a.threads, ref_budget=0, device="cpu")
    knobs = [dict(tile_size=t) for t in (4, 8, 16)] + [dict(chunk=c) for c in (8, 16, 64)]
    knobs += [dict(max_elements=1 << m) for m in (16, 19)]
    knobs += [dict(alpha_min=x) for x in (2 / 255, 8 / 255)] + [dict(t_min=x) for x in (1e-3, 1e-2)]
    if a.quick:
        knobs = [dict(tile_size=16), dict(chunk=16), dict(t_min=1e-2)]
    kcfgs = [dict(base, kw=k, ref_default=True) for k in knobs]
    print("\n## knobs (head 20k, 256^2, D=32; error vs the default settings)")
    krows = run_all(kcfgs)
    for r, k in zip(krows, knobs):
        r["knob"] = ", ".join(f"{kk}={v:.4g}" if isinstance(v, float) else f"{kk}={v}" for kk, v in k.items())
    print(format_table(krows, ["knob", "fwd_s", "fwd_bwd_s", "fwd_cpu_s", "fwd_bwd_cpu_s", "peak_rss_gb", "pairs",
                               "rounds", "max_err", "frac_gt_1e5"]))
    ks: dict = {}
    for r, k in zip(krows, knobs):
        name = next(iter(k))
        xs, ys = ks.setdefault(name, ([], []))
        xs.append(max(r.get("max_err", 0.0), 1e-9))
        ys.append(r["fwd_bwd_s"])
    png = save_plot(OUT_DIR / "splat_knobs.png", ks, xlabel="max |error| vs default (1e-9 = exact)",
                    ylabel="fwd+bwd seconds", title="render.splat knob trade-offs (labels in the table)",
                    logx=True)
    print(f"wrote {png}")

    # The training splat is small (the demo's 128^2 output splats at 32^2): there the chunk sets the
    # number of rounds, and the default (auto) chunk grows to keep rounds large.
    small = dict(base, n=6000, res=32)
    chunks = [dict(chunk=c) for c in ((32, 256) if a.quick else (16, 32, 64, 128, 256, 512))]
    print("\n## chunk on a small image (head 6k, 32^2, D=32; error vs the default, auto chunk)")
    crows = run_all([dict(small, kw=k, ref_default=True) for k in [{}] + chunks])
    for r, k in zip(crows, [dict(chunk="auto")] + chunks):
        r["knob"] = f"chunk={k['chunk']}"
    print(format_table(crows, ["knob", "fwd_s", "fwd_bwd_s", "rounds", "max_err"]))


def camera_batch_section(a: argparse.Namespace, devices: list[str]) -> None:
    """One call over C cameras against C calls, per device and resolution: table and splat_batch.png."""
    print("\n## camera batch (head 6k, D=32, fwd+bwd: one call with per-camera Gaussians vs one call per camera)")
    brows = [camera_batch_row(c, r, 6000, dev) for dev in devices for r in ((32,) if a.quick else (32, 128))
             for c in (1, 4, 8)]
    for r in brows:
        r["speedup"] = r["per_camera_calls_s"] / r["one_call_s"]
    print(format_table(brows, ["device", "cameras", "res", "N", "one_call_s", "per_camera_calls_s", "speedup",
                               "max_abs_diff"]))
    series = {}
    for r in brows:
        for how in ("one_call_s", "per_camera_calls_s"):
            xs, ys = series.setdefault(f"{r['device']} {r['res']}^2 {how[:-2].replace('_', ' ')}", ([], []))
            xs.append(r["cameras"])
            ys.append(r[how])
    png = save_plot(OUT_DIR / "splat_batch.png", series, xlabel="cameras", ylabel="fwd+bwd seconds",
                    title="render.splat: a batch of cameras in one call", logy=True)
    print(f"wrote {png}")


if __name__ == "__main__":
    from toolkit.errors import run_cli

    raise SystemExit(run_cli(main))
