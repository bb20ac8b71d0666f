"""Benchmark: the DiT renderer against GazeGaussian's baseline renderer -- run time against image error.

1. Speed: per-image time of the DiT renderer (tiny and paper configurations; DDIM steps 1..50) and of the
   baseline at 128^2 and 512^2 outputs (feature maps at 1/4 resolution, the project's KL autoencoder as
   codec). Weights do not change the run time, so these use freshly built models.
2. Error: a small model trained here, briefly, on procedural image/feature pairs (a head-like ellipse with a
   code-dependent tint, two eyes with gaze-dependent pupils, rendered sharp at full resolution; the features
   are the same scene at 1/4 resolution mixed into 32 channels, as a splatter would give): held-out MSE and
   PSNR of the DiT renderer for DDIM steps (1, 2, 4, 8, 25, 50), of the baseline, and of the codec alone
   (the floor any latent renderer is bounded by).

Prints both tables with the machine and `uptime` load, writes out/benchmarks/renderer.png and
renderer.json. ``--quick`` is a smoke run (minutes -> seconds; numbers meaningless).

    .venv/bin/python benchmarks/renderer.py [--quick] [--threads N] [--device cuda]
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    OUT_DIR,
    check_device,
    count,
    format_table,
    machine_info,
    positive,
    save_plot,
    timeit,
)
from toolkit.errors import CliParser, ToolkitError, run_cli  # noqa: E402
from toolkit.io import atomic_write_json  # noqa: E402
from toolkit.limits import check_allocation  # noqa: E402
from train.model.baseline_renderer import BaselineConfig, BaselineRenderer  # noqa: E402
from train.model.codec import AutoencoderConfig, KLAutoencoder, train_autoencoder  # noqa: E402
from train.model.diffusion import GaussianDiffusion  # noqa: E402
from train.model.dit import make_dit  # noqa: E402
from train.model.renderer import DiTRenderer  # noqa: E402

STEPS = (1, 2, 4, 8, 25, 50)
CODEC_DOWNSAMPLE = 8
"""The KL autoencoders' downsampling (``fit_renderers``, ``speed_table``): the DiT's latent grid is 1/8 of the image."""
DATA_BYTES_PER_PIXEL = 64
"""Peak memory of ``make_dataset`` per pixel of an image, generously: the RGB image (12 bytes), the 32 feature
channels at 1/4 resolution (8) and ``scene_images``' single-channel masks and their temporaries."""


# ----------------------------------------------------------------------------- procedural data
def _soft_ellipse(xx, yy, cx, cy, rx, ry, sharp):
    d = ((xx - cx[:, None, None]) / rx[:, None, None]) ** 2 + ((yy - cy[:, None, None]) / ry[:, None, None]) ** 2
    return torch.sigmoid(sharp * (1 - d))


def scene_images(params: dict[str, torch.Tensor], size: int) -> torch.Tensor:
    """Render the procedural heads at ``size`` -> ``[N, 3, size, size]`` in [0, 1] (white background)."""
    p = params
    ax = (torch.arange(size) + 0.5) / size
    yy, xx = torch.meshgrid(ax, ax, indexing="ij")
    sharp = 0.08 * size  # edge width ~ a pixel at every resolution
    head = _soft_ellipse(xx, yy, p["cx"], p["cy"], p["rx"], p["ry"], sharp)
    img = torch.ones(len(p["cx"]), 3, size, size)
    img = img * (1 - head[:, None]) + p["skin"][:, :, None, None] * head[:, None]
    for side in (-1, 1):
        ex, ey = p["cx"] + side * 0.45 * p["rx"], p["cy"] - 0.15 * p["ry"]
        er = 0.22 * p["rx"]
        eye = _soft_ellipse(xx, yy, ex, ey, er, 0.6 * er, sharp)
        img = img * (1 - eye[:, None]) + eye[:, None]  # white sclera
        px, py = ex - er * 0.5 * torch.sin(p["yaw"]), ey - 0.6 * er * 0.5 * torch.sin(p["pitch"])
        pupil = _soft_ellipse(xx, yy, px, py, 0.4 * er, 0.4 * er, sharp) * eye
        img = img * (1 - pupil[:, None]) + p["iris"][:, :, None, None] * pupil[:, None]
    return img.clamp(0, 1)


def make_dataset(n: int, size: int, seed: int) -> dict[str, torch.Tensor]:
    """Images ``[N, 3, S, S]``, features ``[N, 32, S/4, S/4]`` and shape codes ``[N, 144]``."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    code = torch.randn(n, 144, generator=g)
    params = {"cx": 0.5 + 0.08 * (u(n) - 0.5), "cy": 0.52 + 0.08 * (u(n) - 0.5), "rx": 0.3 + 0.06 * u(n),
              "ry": 0.4 + 0.06 * u(n), "yaw": (u(n) - 0.5) * 1.2, "pitch": (u(n) - 0.5) * 0.8,
              "iris": 0.1 + 0.4 * u(n, 3),
              # the skin tint comes from the shape code only: the renderer must read the code to get it right
              "skin": torch.sigmoid(code[:, :3] * 0.8 + torch.tensor([1.0, 0.3, 0.0]))}
    images = scene_images(params, size)
    low = scene_images({**params, "skin": torch.full_like(params["skin"], 0.6)}, size // 4)
    gmix = torch.Generator().manual_seed(1234)  # a fixed "splatter": the same mixing for every sample
    mix = torch.randn(32, 3, generator=gmix)
    feats = torch.tanh(torch.einsum("fc,nchw->nfhw", mix, low * 2 - 1))
    feats[:, :3] = low  # as GazeGaussian, the first three feature channels are a low-resolution RGB
    return {"images": images, "feats": feats, "code": code}


# ----------------------------------------------------------------------------- training
def train_pairs(model_step, data, steps: int, batch: int, seed: int, label: str) -> list[float]:
    g = torch.Generator().manual_seed(seed)
    losses = []
    t0 = time.perf_counter()
    for i in range(steps):
        idx = torch.randint(0, len(data["images"]), (batch,), generator=g)
        losses.append(model_step(data["feats"][idx], data["code"][idx], data["images"][idx], g))
        if (i + 1) % max(1, steps // 5) == 0:
            print(f"  {label}: step {i + 1}/{steps} loss {sum(losses[-20:]) / len(losses[-20:]):.4f} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return losses


def fit_renderers(args, device):
    train = make_dataset(args.train_images, args.train_size, seed=0)
    test = make_dataset(args.test_images, args.train_size, seed=1)
    train = {k: v.to(device) for k, v in train.items()}
    test = {k: v.to(device) for k, v in test.items()}
    print(f"training the KL autoencoder ({args.ae_steps} steps, {args.train_size}^2) ...", flush=True)
    torch.manual_seed(0)
    ae_config = AutoencoderConfig(downsample=8, base_channels=args.speed_codec_channels[0], max_channels=64)
    every = max(1, args.ae_steps // 5)

    def log(i, metrics):
        if (i + 1) % every == 0:
            print(f"  autoencoder: step {i + 1}/{args.ae_steps} L1 {metrics['recon_l1']:.4f}", flush=True)

    codec, _ = train_autoencoder(train["images"], ae_config, steps=args.ae_steps, batch_size=16, lr=2e-3,
                                 model=KLAutoencoder(ae_config).to(device), log=log)
    torch.manual_seed(0)
    grid = args.train_size // ae_config.downsample
    dit = DiTRenderer(make_dit(args.model, input_size=grid, base_channels=codec.latent_channels).to(device), codec,
                      GaussianDiffusion())
    base = BaselineRenderer(BaselineConfig()).to(device)

    def step_fn(renderer, opt):
        def step(f, c, x, g):
            out = renderer.training_forward(f, c, x, generator=g)
            loss = out.aux_loss + (out.image - x).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            return loss.item()
        return step

    print(f"training {args.model} and the baseline ({args.steps} steps each) ...", flush=True)
    train_pairs(step_fn(dit, torch.optim.AdamW(dit.dit.parameters(), lr=args.lr)), train, args.steps, args.batch, 1,
                args.model)
    train_pairs(step_fn(base, torch.optim.AdamW(base.parameters(), lr=args.lr)), train, args.steps, args.batch, 1,
                "baseline")
    return codec, dit.eval(), base.eval(), test


def psnr(mse: float) -> float:
    return 10 * math.log10(1.0 / max(mse, 1e-12))


@torch.no_grad()
def error_table(codec, dit, base, test, device, repeats):
    f, c, x = test["feats"], test["code"], test["images"]
    n = len(x)
    rows, series_t, series_e = [], [], []
    sync = device.type == "cuda"
    for k in STEPS:
        mse = F.mse_loss(dit.render(f, c, steps=k, seed=0), x).item()
        sec = timeit(lambda k=k: dit.render(f, c, steps=k), repeats=repeats, sync_cuda=sync) / n  # noqa: B023
        rows.append({"renderer": f"DiT {k}-step", "ms/img": 1e3 * sec, "MSE": mse, "PSNR dB": psnr(mse)})
        series_t.append(1e3 * sec)
        series_e.append(mse)
    mse_b = F.mse_loss(base.render(f, c), x).item()
    sec_b = timeit(lambda: base.render(f, c), repeats=repeats, sync_cuda=sync) / n
    rows.append({"renderer": "baseline (GazeGaussian)", "ms/img": 1e3 * sec_b, "MSE": mse_b, "PSNR dB": psnr(mse_b)})
    mse_ae = F.mse_loss(codec.decode(codec.encode(x)).clamp(0, 1), x).item()
    rows.append({"renderer": "codec round trip (floor)", "ms/img": None, "MSE": mse_ae, "PSNR dB": psnr(mse_ae)})
    return rows, {"DiT (DDIM steps 1..50)": (series_t, series_e), "baseline": ([1e3 * sec_b], [mse_b])}


# ----------------------------------------------------------------------------- speed
@torch.no_grad()
def speed_table(args, device):
    """Rows per (renderer, size, precision, steps). One-step renders are always measured end to end; so is every
    step count of the cheap settings. For the heavy ones the K-step time is ``K * t_call + t_rest`` from a
    measured network call and a measured 1-step render (each DDIM step is one identical network call)."""
    rows = []
    sync = device.type == "cuda"
    codecs = {ch: KLAutoencoder(AutoencoderConfig(downsample=8, base_channels=ch, max_channels=64)).to(device).freeze()
              for ch in args.speed_codec_channels}
    precisions = ["fp32", "bf16"] if args.bf16 else ["fp32"]

    def run(fn, precision, repeats):
        def call():
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16"):
                return fn()
        return timeit(call, repeats=repeats, sync_cuda=sync)

    for size in (128, 512):
        B = args.speed_batch if size == 128 else max(1, args.speed_batch // 4)
        f = torch.randn(B, 32, size // 4, size // 4, device=device)
        c = torch.randn(B, 144, device=device)
        base = BaselineRenderer().to(device).eval()
        for prec in precisions:
            sec = run(lambda: base.render(f, c), prec, args.repeats) / B  # noqa: B023
            rows.append({"renderer": "baseline", "codec": "-", "size": size, "prec": prec, "steps": 1, "ms/img": 1e3 * sec,
                         "img/s": 1 / sec, "params M": sum(p.numel() for p in base.parameters()) / 1e6,
                         "how": "measured"})
        for name, ch in [(m, ch) for m in args.speed_models for ch in args.speed_codec_channels
                         if "tiny" in m or ch == args.speed_codec_channels[0]]:
            torch.manual_seed(0)
            r = DiTRenderer(make_dit(name, input_size=size // 8, base_channels=codecs[ch].latent_channels).to(device),
                            codecs[ch]).eval()
            params = sum(p.numel() for p in r.dit.parameters()) / 1e6
            heavy = size == 512 or "tiny" not in name
            reps = 1 if size == 512 and "tiny" not in name else args.repeats
            z = torch.randn(B, 4, size // 8, size // 8, device=device)
            emb = r.dit.encode_features(f, (size // 8, size // 8))
            zb = r.base_latent(f)
            t999 = torch.full((B,), 999, device=device)
            for prec in precisions:
                t1 = run(lambda: r.render(f, c, steps=1), prec, reps) / B  # noqa: B023
                t_call = run(lambda: r.dit(z, t999, f, c, feature_embedding=emb, base=zb), prec, reps) / B  # noqa: B023
                for k in STEPS:
                    if k == 1:
                        sec, how = t1, "measured"
                    elif not heavy:
                        sec, how = run(lambda k=k: r.render(f, c, steps=k), prec, max(1, args.repeats // 2)) / B, "measured"  # noqa: B023
                    else:
                        sec, how = t1 + (k - 1) * t_call, "t1 + (K-1) t_call"
                    rows.append({"renderer": name, "codec": f"AE c{ch}", "size": size, "prec": prec, "steps": k, "ms/img": 1e3 * sec,
                                 "img/s": 1 / sec, "params M": params, "how": how})
    return rows


def check_training_set(args) -> None:
    """``--train-size`` and the sets' memory, before the speed table: the trained codec makes a latent grid of
    1/8 of the image and the DiT cuts it into patches, so the size must be a multiple of 8 x the patch size."""
    step = CODEC_DOWNSAMPLE * make_dit(args.model, input_size=8).config.patch_size
    if args.train_size % step:
        raise ToolkitError(f"--train-size: expected a multiple of {step} ({args.model}: the codec downsamples "
                           f"{CODEC_DOWNSAMPLE}x, then patches of {step // CODEC_DOWNSAMPLE}), got {args.train_size}")
    pixels = (args.train_images + args.test_images) * args.train_size**2
    check_allocation(pixels * DATA_BYTES_PER_PIXEL, f"--train-images {args.train_images} --test-images "
                     f"{args.test_images} at --train-size {args.train_size}", "lower them")


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return f"loadavg {os.getloadavg()}"


def main(argv=None) -> int:
    ap = CliParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: few steps, small sets")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--threads", type=count("--threads", 1), default=None, help="torch CPU threads (default: torch's choice)")
    ap.add_argument("--model", default="DiT-Gaze-tiny", help="DiT configuration trained for the error curve")
    ap.add_argument("--train-size", type=count("--train-size", 1), default=64)
    ap.add_argument("--train-images", type=count("--train-images", 1), default=2048)
    ap.add_argument("--test-images", type=count("--test-images", 1), default=32)
    ap.add_argument("--ae-steps", type=count("--ae-steps", 1), default=800)
    ap.add_argument("--steps", type=count("--steps", 1), default=600)
    ap.add_argument("--batch", type=count("--batch", 1), default=16)
    ap.add_argument("--lr", type=positive("--lr"), default=1e-3)
    ap.add_argument("--speed-batch", type=count("--speed-batch", 1), default=8)
    ap.add_argument("--repeats", type=count("--repeats", 1), default=5)
    ap.add_argument("--speed-models", nargs="+", default=["DiT-Gaze-tiny", "DiT-Gaze-paper", "DiT-Gaze-paper/4"])
    ap.add_argument("--speed-codec-channels", type=count("--speed-codec-channels", 1), nargs="+", default=[16, 8],
                    help="full-resolution channels of the KL autoencoders timed (the first is the one trained)")
    ap.add_argument("--skip-training", action="store_true", help="speed table only")
    ap.add_argument("--no-bf16", dest="bf16", action="store_false", help="skip the bf16 autocast timings")
    args = ap.parse_args(argv)
    if args.quick:
        args.ae_steps, args.steps, args.train_images, args.test_images, args.repeats = 20, 20, 64, 8, 1
        args.speed_models, args.bf16 = ["DiT-Gaze-tiny"], False
    if args.threads:
        torch.set_num_threads(args.threads)
    make_dit(args.model, input_size=8)  # an unknown --model fails here, not after the speed table
    if not args.skip_training:
        check_training_set(args)
    device = check_device(args.device)
    print(machine_info())
    print(f"load before: {uptime()}\n", flush=True)

    speed = speed_table(args, device)
    print(f"\n## Per-image time, {device}, batch {args.speed_batch} at 128^2 ({max(1, args.speed_batch // 4)} at 512^2), "
          "KL autoencoder codecs (8x down; cN = N channels at full resolution)\n")
    print(format_table(speed, ["renderer", "codec", "size", "prec", "steps", "ms/img", "img/s", "params M", "how"]), flush=True)

    result = {"machine": machine_info(), "speed": speed, "args": vars(args)}
    if not args.skip_training:
        t0 = time.perf_counter()
        codec, dit, base, test = fit_renderers(args, device)
        rows, series = error_table(codec, dit, base, test, device, args.repeats)
        print(f"\n## Held-out error at {args.train_size}^2 after {args.steps} training steps "
              f"({args.model}; trained in {time.perf_counter() - t0:.0f} s)\n")
        print(format_table(rows, ["renderer", "ms/img", "MSE", "PSNR dB"]))
        result["error"] = rows
        png = save_plot(OUT_DIR / "renderer.png", series, xlabel="ms per image", ylabel="held-out MSE",
                        title=f"DiT renderer (DDIM steps) vs baseline, {args.train_size}^2, {device}", logx=True,
                        logy=True)
        print(f"\nplot: {png}")
    load = uptime()
    result["uptime"] = load
    print(f"load after: {load}")
    atomic_write_json(OUT_DIR / "renderer.json", result)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
