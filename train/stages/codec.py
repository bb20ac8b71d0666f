"""Stage ``codec``: train the small KL autoencoder the latent DiT works in (nothing to train for the pixel
codec or a user's SD-VAE)."""

from __future__ import annotations

from toolkit.errors import ToolkitError
from train.config import component
from train.stages.artifacts import RunArtifacts
from train.stages.pipeline import RunContext


def stage_codec(ctx: RunContext) -> dict[str, str]:
    """Train the autoencoder on the training split's images (eye pixels weighted by ``codec.eye_weight``) ->
    ``codec.safetensors``; logs to ``metrics.jsonl`` as it trains."""
    c = ctx.config.codec
    if c.kind != "ae":
        if c.kind == "sd-vae" and not c.sd_vae_path:
            raise ToolkitError("codec.kind=sd-vae needs codec.sd_vae_path (a local diffusers AutoencoderKL folder)")
        return {}
    from tqdm import tqdm

    from train.model.codec import AutoencoderConfig, save_autoencoder, train_autoencoder
    from train.training.loop import MetricsLogger

    run = RunArtifacts(ctx)
    images, weights = codec_rows(run.split("train"), ctx.config.data.res, ctx.config.data.layout, c.eye_weight)
    metrics = MetricsLogger(ctx.run_dir, tensorboard=True)
    metrics.start("codec", 0)  # no checkpoints: a re-run trains from the start
    every = max(1, c.steps // 50)
    with tqdm(total=c.steps, desc="codec", dynamic_ncols=True) as bar:
        def log(step: int, values: dict[str, float]) -> None:
            bar.update(1)
            if (step + 1) % every == 0 or step + 1 == c.steps:
                bar.set_postfix({k: f"{v:.4g}" for k, v in values.items()})
                metrics.log("codec", step + 1, values)

        try:
            model, hist = train_autoencoder(images, component(AutoencoderConfig, c),
                                            steps=c.steps, batch_size=c.batch, seed=ctx.config.seed,
                                            pixel_weights=weights, device=run.device, log=log)
        finally:
            metrics.close()
            images.source.close()
    save_autoencoder(ctx.run_dir / "codec.safetensors", model, {"final_loss": hist[-1] if hist else None})
    ctx.log(f"[codec] autoencoder trained: final loss {hist[-1] if hist else float('nan'):.4f}")
    return {"codec": "codec.safetensors"}


def codec_rows(files, res: int, layout: str, eye_weight: float):
    """(images, pixel weights or None) of the training split as ``train.data.rows.RowImages`` [N, 3, R, R] float
    in [0, 1] and [N, 1, R, R] (``1 + eye_weight`` × the dilated eye masks inside the head): read from the files
    a batch at a time, as the Gaussian stage reads its rows, never the whole split in memory."""
    import torch

    from train.data.dataset import GazeDataset
    from train.data.rows import DEFAULT_CACHE_BYTES, RowImages, RowSource, default_workers
    from train.model.codec import eye_weights
    from train.training.trainer import train_row

    def row(item: dict) -> dict:
        r = train_row(item)
        out = {"image": r["image"]}
        if eye_weight > 0:
            out["weight"] = eye_weights((r["eyes"] * r["head"])[None], eye_weight)[0]
        return out

    ds = GazeDataset(files, split="all", res=res, layout=layout)
    source = RowSource(ds, row, cache_bytes=DEFAULT_CACHE_BYTES, workers=default_workers())
    images = RowImages(source, "image", (3, res, res), torch.float32)
    return images, RowImages(source, "weight", (1, res, res), torch.float32) if eye_weight > 0 else None
