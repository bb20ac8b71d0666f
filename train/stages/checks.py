"""The run config's value checks, made before any work: each failure is one ``ToolkitError`` naming the key."""

from __future__ import annotations

import functools
import math
import re
from pathlib import Path

from toolkit.errors import ToolkitError
from train.run_config import RunConfig

COUNT_KEYS = ("data.frames", "geometry.steps", "geometry.pool", "geometry.gaussians", "codec.steps", "codec.batch",
              "codec.base_channels", "estimator.steps", "estimator.batch", "estimator.input_size",
              "estimator.synthetic_frames", "estimator.cameras_per_frame", "gaussian.steps", "gaussian.batch",
              "gaussian.sampling_steps", "gaussian.gaussians_hidden", "gaussian.ckpt_every", "gaussian.log_every",
              "eval.pairs_per_subject", "eval.sweep_frames")
"""Config keys that count something and must be >= 1 (checked before any work)."""

WEIGHT_KEYS = ("geometry.pretrain_steps", "estimator.synthetic_subjects", "gaussian.ortho_weight",
               "gaussian.weak_weight", "gaussian.lambda_rgb", "gaussian.lambda_gaze", "gaussian.lambda_ssim",
               "gaussian.diffusion_weight")
"""Config keys that may be 0 (off) but not negative or non-finite."""


def check_config(cfg: RunConfig) -> None:
    """Values the type check cannot catch, before any work."""
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", cfg.device):
        raise ToolkitError(f"config key 'device': expected auto, cpu, cuda or cuda:N, got {cfg.device!r}")
    if not cfg.data.root and cfg.data.subjects < 2:
        raise ToolkitError(f"config key 'data.subjects': expected >= 2 synthetic subjects (at least one to train on "
                           f"and one held out), got {cfg.data.subjects}")
    from train.data.generate import RES_RANGE

    lo, hi = RES_RANGE
    if not lo <= cfg.data.res <= hi:
        raise ToolkitError(f"config key 'data.res': expected an image size in [{lo}, {hi}] pixels, got {cfg.data.res}")
    value = lambda key: functools.reduce(getattr, key.split("."), cfg)  # noqa: E731
    for key in ("gaussian.lr", "gaussian.renderer_lr", "gaussian.means_lr", "eval.tta_renderer_lr"):
        if not (math.isfinite(rate := value(key)) and 0 < rate <= 1):  # Adam's step is the rate: > 1 overflows
            raise ToolkitError(f"config key '{key}': expected a learning rate in (0, 1], got {rate}")
    for key in COUNT_KEYS:
        if not (count := value(key)) >= 1:
            raise ToolkitError(f"config key '{key}': expected a count >= 1, got {count}")
    for key in WEIGHT_KEYS:
        if not (math.isfinite(w := value(key)) and w >= 0):
            raise ToolkitError(f"config key '{key}': expected a finite value >= 0, got {w}")
    for key in ("seed", "data.seed"):
        if (seed := value(key)) < 0:
            raise ToolkitError(f"config key '{key}': expected a seed >= 0, got {seed}")
    lower = {"geometry.gaussians": (16, "Gaussians (the initialization needs 16 surface points)"),
             "geometry.pool": (1000, "pool points (the SDF fit draws its batches and surface seeds from them)")}
    for key, (least, what) in lower.items():
        if (n := value(key)) < least:
            raise ToolkitError(f"config key '{key}': expected >= {least} {what}, got {n}")
    from train.data.generate import RIG_RADIUS, eth_xgaze_rig

    n_cams = len(eth_xgaze_rig(radius=RIG_RADIUS))
    if cfg.estimator.cameras_per_frame > n_cams:
        raise ToolkitError(f"config key 'estimator.cameras_per_frame': expected at most the rig's {n_cams} cameras, "
                           f"got {cfg.estimator.cameras_per_frame}")
    if cfg.estimator.crop != "eyes":
        from train.estimator.network import GazeEstimator
        from train.stages.estimator import estimator_design

        try:  # the network's constructor holds the size rule; building it costs milliseconds
            GazeEstimator(estimator_design(cfg))
        except ToolkitError as err:
            raise ToolkitError(f"config key 'estimator.input_size': {err}") from None
    if cfg.gaussian.renderer == "dit":
        from train.model.diffusion import DiffusionConfig

        for key in ("gaussian.sampling_steps", "eval.sampling_steps"):
            if value(key) > (T := DiffusionConfig().num_timesteps):
                raise ToolkitError(f"config key '{key}': expected at most the diffusion's {T} timesteps, got {value(key)}")
    if cfg.codec.kind == "sd-vae" and cfg.data.res % 8:
        raise ToolkitError(f"config key 'data.res': the SD-VAE codec downsamples 8x, so the image size must be a "
                           f"multiple of 8, got {cfg.data.res}")
    if not 4 <= cfg.geometry.extract_res <= 512:
        raise ToolkitError(f"config key 'geometry.extract_res': expected a tet-grid resolution in [4, 512], "
                           f"got {cfg.geometry.extract_res}")
    if not 0.0 < cfg.gaussian.sampler_range_deg <= 89.0:
        raise ToolkitError(f"config key 'gaussian.sampler_range_deg': expected (0, 89] degrees, "
                           f"got {cfg.gaussian.sampler_range_deg}")
    if not 0.0 <= cfg.data.light_jitter <= 2.0:
        raise ToolkitError(f"config key 'data.light_jitter': expected a value in [0, 2], got {cfg.data.light_jitter}")
    # the SD-VAE and pixel codecs fix their own factor; only the trained autoencoder reads codec.downsample
    powers_of_two = ["gaussian.feature_upscale"] + (["codec.downsample"] if cfg.codec.kind == "ae" else [])
    for key in powers_of_two:
        if (f := value(key)) < 1 or f & (f - 1) or cfg.data.res % f:
            raise ToolkitError(f"config key '{key}': expected a power of two dividing data.res={cfg.data.res}, got {f}")
    if cfg.geometry.subject < 0:
        raise ToolkitError(f"config key 'geometry.subject': expected a training-subject index >= 0, got {cfg.geometry.subject}")
    if cfg.eval.pairing_file:
        from train.data.pairing import load_pairing

        try:  # read whole before any work: a bad file fails here, not after training
            load_pairing(cfg.eval.pairing_file)
        except ToolkitError as err:
            raise ToolkitError(f"config key 'eval.pairing_file': {err}") from None
    if not (math.isfinite(cfg.gaussian.grad_clip) and cfg.gaussian.grad_clip >= 0):
        raise ToolkitError(f"config key 'gaussian.grad_clip': expected a gradient-norm bound >= 0 (0 = no clipping), "
                           f"got {cfg.gaussian.grad_clip}")
    if cfg.eval.sampling_steps < 0:
        raise ToolkitError(f"config key 'eval.sampling_steps': expected 0 (gaussian.sampling_steps) or a DDIM step "
                           f"count >= 1, got {cfg.eval.sampling_steps}")
    if cfg.eval.tta_steps < 0:
        raise ToolkitError(f"config key 'eval.tta_steps': expected a step count >= 0, got {cfg.eval.tta_steps}")
    if cfg.geometry.lid_gaussians < 0 or (cfg.geometry.lid_gaussians > 0 and cfg.geometry.eye_gaussians == 0):
        raise ToolkitError(f"config key 'geometry.lid_gaussians': expected 0, or > 0 with geometry.eye_gaussians > 0, "
                           f"got {cfg.geometry.lid_gaussians} with geometry.eye_gaussians={cfg.geometry.eye_gaussians}")
    if cfg.geometry.eye_gaussians < 0 or 0 < cfg.geometry.eye_gaussians < 4:
        raise ToolkitError(f"config key 'geometry.eye_gaussians': expected 0 (the mesh's eye points) or >= 4, "
                           f"got {cfg.geometry.eye_gaussians}")
    if not cfg.codec.eye_weight >= 0:
        raise ToolkitError(f"config key 'codec.eye_weight': expected a weight >= 0, got {cfg.codec.eye_weight}")
    if not 0.0 <= cfg.gaussian.onestep_fraction <= 1.0:
        raise ToolkitError(f"config key 'gaussian.onestep_fraction': expected a share in [0, 1], "
                           f"got {cfg.gaussian.onestep_fraction}")
    if cfg.gaussian.dit_feature_hidden < 1:
        raise ToolkitError(f"config key 'gaussian.dit_feature_hidden': expected a channel count >= 1, "
                           f"got {cfg.gaussian.dit_feature_hidden}")
    if not 0.0 <= cfg.gaussian.ema_decay < 1.0:
        raise ToolkitError(f"config key 'gaussian.ema_decay': expected a decay in [0, 1) (0: no average), "
                           f"got {cfg.gaussian.ema_decay}")
    if not 0.0 <= cfg.gaussian.lr_final <= 1.0:
        raise ToolkitError(f"config key 'gaussian.lr_final': expected a factor in [0, 1] of the rates at the last "
                           f"step, got {cfg.gaussian.lr_final}")
    if cfg.gaussian.eyeball_colours and cfg.gaussian.eye_appearance:
        raise ToolkitError("config keys 'gaussian.eyeball_colours' and 'gaussian.eye_appearance' both set the eye "
                           "Gaussians' colours: enable one of them")
    if "eye_colours" in cfg.eval.tta_weights and not cfg.gaussian.eyeball_colours:
        raise ToolkitError("config key 'eval.tta_weights': 'eye_colours' needs gaussian.eyeball_colours=true (the "
                           "parametric eyeball whose colours it fits)")
    # Last: what names something outside the config (a model, a file) once the values themselves are sound.
    from train.model.dit import DIT_MODELS

    if cfg.gaussian.renderer == "dit" and cfg.gaussian.dit_model not in DIT_MODELS:
        raise ToolkitError(f"config key 'gaussian.dit_model': expected one of {sorted(DIT_MODELS)}, "
                           f"got {cfg.gaussian.dit_model!r}")
    lp = {key: value(key) for key in ("eval.lpips_vgg_path", "eval.lpips_lin_path")}
    if any(lp.values()) and not all(lp.values()):
        raise ToolkitError(f"config keys {list(lp)}: LPIPS needs both files (the VGG16 weights and the linear "
                           f"layers), got {lp}")
    estimator_hint = " (a trained gaze estimator, .safetensors; empty: train one)"
    files = {"estimator.loss_path": estimator_hint, "estimator.eval_path": estimator_hint,
             **dict.fromkeys([*lp, "eval.identity_model_path"], "")}
    for key, hint in files.items():
        if (path := value(key)) and not Path(path).is_file():
            raise ToolkitError(f"config key '{key}': {path}: no such file{hint}")
    if cfg.codec.kind == "sd-vae" and not (cfg.codec.sd_vae_path and Path(cfg.codec.sd_vae_path).is_dir()):
        raise ToolkitError(f"config key 'codec.sd_vae_path': {cfg.codec.sd_vae_path!r}: no such directory (codec.kind="
                           f"sd-vae reads a local diffusers AutoencoderKL folder)")
    if cfg.data.test_frames < 0 or cfg.data.test_frames % 2:
        raise ToolkitError(f"config key 'data.test_frames': expected 0 (as data.frames) or an even frame count, "
                           f"got {cfg.data.test_frames}")
    if cfg.data.test_frames == 0 and cfg.data.frames % 2 and not cfg.data.root:
        # Inputs come from the first half of a held-out subject's frames, targets from the second: an odd count
        # pairs a frame with itself (no redirection to score).
        raise ToolkitError(f"config key 'data.frames': with data.test_frames=0 the held-out subjects get data.frames "
                           f"frames, which must be even (each pair's input and target are different frames), got "
                           f"{cfg.data.frames}; set data.test_frames to an even count")
    if not 0.0 <= cfg.data.test_fraction < 1.0:
        raise ToolkitError(f"config key 'data.test_fraction': expected a share in [0, 1), got {cfg.data.test_fraction}")
    e = cfg.estimator
    if not 0.0 <= e.blur_prob <= 1.0:
        raise ToolkitError(f"config key 'estimator.blur_prob': expected a probability in [0, 1], got {e.blur_prob}")
    if not e.blur_sigma >= 0:
        raise ToolkitError(f"config key 'estimator.blur_sigma': expected a width >= 0 (pixels), got {e.blur_sigma}")
    if not cfg.eval.tta_renderer_lr > 0:
        raise ToolkitError(f"config key 'eval.tta_renderer_lr': expected a learning rate > 0, got {cfg.eval.tta_renderer_lr}")
    if not cfg.eval.tta_gaze_weight >= 0:
        raise ToolkitError(f"config key 'eval.tta_gaze_weight': expected a weight >= 0, got {cfg.eval.tta_gaze_weight}")
    if cfg.eval.tta_gaze_every < 1:
        raise ToolkitError(f"config key 'eval.tta_gaze_every': expected a step count >= 1, got {cfg.eval.tta_gaze_every}")
    if "decoder" in cfg.eval.tta_weights and (cfg.gaussian.renderer != "dit" or cfg.codec.kind == "pixel"):
        raise ToolkitError("config key 'eval.tta_weights': 'decoder' needs a codec decoder: gaussian.renderer=dit "
                           f"with codec.kind ae or sd-vae (got renderer {cfg.gaussian.renderer}, codec {cfg.codec.kind})")
    outside = [g for g in cfg.eval.tta_gaze_reach if g != "code" and g not in cfg.eval.tta_weights]
    if outside:
        raise ToolkitError(f"config key 'eval.tta_gaze_reach': the gaze term may reach only the code and the fitted "
                           f"eval.tta_weights {list(cfg.eval.tta_weights)}, got {outside}")
    if cfg.eval.tta_gaze_weight > 0 and not cfg.eval.tta_gaze_terms:
        raise ToolkitError("config key 'eval.tta_gaze_terms': expected at least one of target, own when "
                           "eval.tta_gaze_weight > 0")
