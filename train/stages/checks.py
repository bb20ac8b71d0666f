"""The run config's rules across fields, and those that read something outside the config (a file, the model
table, the camera rig), each stated once. :func:`check_config` runs them before any work, after every field's
own type and range (declared on the field, ``train.config.check_fields``)."""

from __future__ import annotations

from pathlib import Path

from toolkit.errors import ToolkitError
from train.config import check_component, check_fields
from train.run_config import RunConfig


def _require(ok: object, key: str, text: str) -> None:
    """Raise "config key '{key}': {text}" unless ``ok``."""
    if not ok:
        raise ToolkitError(f"config key '{key}': {text}")


def check_config(cfg: RunConfig) -> None:
    """Every check of a run config, before any work; each failure is one ``ToolkitError`` naming the key."""
    check_values(cfg)
    _check_memory(cfg)
    _check_files(cfg)  # last: what names something outside the config, once the values themselves are sound


def check_values(cfg: RunConfig) -> None:
    """The checks of the config's values alone (not the files it names, nor this machine's memory): what a
    finished run's ``config.yaml`` must still pass to be opened."""
    check_fields(cfg)
    _check_sizes(cfg)
    _check_models(cfg)
    _check_fit(cfg)


def _check_sizes(cfg: RunConfig) -> None:
    """What the data, the image size, the scale factors, the rig and the Gaussian counts must agree on."""
    from train.data.generate import RES_RANGE, RIG_RADIUS, eth_xgaze_rig

    d, lo, hi = cfg.data, *RES_RANGE
    _require(d.root or d.subjects >= 2, "data.subjects", f"expected >= 2 synthetic subjects (at least one to train "
                                                         f"on and one held out), got {d.subjects}")
    _require(lo <= d.res <= hi, "data.res", f"expected an image size in [{lo}, {hi}] pixels, got {d.res}")
    # Inputs come from the first half of a held-out subject's frames, targets from the second: an odd count
    # pairs a frame with itself (no redirection to score).
    _require(d.test_frames or d.frames % 2 == 0 or d.root, "data.frames",
             f"with data.test_frames=0 the held-out subjects get data.frames frames, which must be even (each pair's "
             f"input and target are different frames), got {d.frames}; set data.test_frames to an even count")
    _require(cfg.codec.kind != "sd-vae" or d.res % 8 == 0, "data.res",
             f"the SD-VAE codec downsamples 8x, so the image size must be a multiple of 8, got {d.res}")
    factors = {"gaussian.feature_upscale": cfg.gaussian.feature_upscale}
    if cfg.codec.kind == "ae":  # the SD-VAE and pixel codecs fix their own factor
        factors["codec.downsample"] = cfg.codec.downsample
    for key, f in factors.items():
        _require(f >= 1 and not f & (f - 1) and d.res % f == 0, key,
                 f"expected a power of two dividing data.res={d.res}, got {f}")
    n_cams = len(eth_xgaze_rig(radius=RIG_RADIUS))
    _require(cfg.estimator.cameras_per_frame <= n_cams, "estimator.cameras_per_frame",
             f"expected at most the rig's {n_cams} cameras, got {cfg.estimator.cameras_per_frame}")
    g = cfg.geometry
    _require(g.lid_gaussians == 0 or (g.lid_gaussians > 0 and g.eye_gaussians > 0), "geometry.lid_gaussians",
             f"expected 0, or > 0 with geometry.eye_gaussians > 0, got {g.lid_gaussians} with "
             f"geometry.eye_gaussians={g.eye_gaussians}")


def _check_models(cfg: RunConfig) -> None:
    """What the estimator, the renderer and the gaze sampler accept."""
    from train.estimator.config import GazeEstimatorTrainConfig
    from train.model.diffusion import DiffusionConfig
    from train.model.dit import DIT_MODELS
    from train.model.gaussian_config import GaussianModelConfig
    from train.training.gaze_sampler import GazeSamplerConfig

    g = cfg.gaussian
    if cfg.estimator.crop != "eyes":
        from train.estimator.network import GazeEstimator
        from train.stages.estimator import estimator_design

        try:  # the network's constructor holds the size rule; building it costs milliseconds
            GazeEstimator(estimator_design(cfg))
        except ToolkitError as err:
            raise ToolkitError(f"config key 'estimator.input_size': {err}") from None
    if g.renderer == "dit":
        T = DiffusionConfig().num_timesteps
        for key, steps in (("gaussian.sampling_steps", g.sampling_steps), ("eval.sampling_steps", cfg.eval.sampling_steps)):
            _require(steps <= T, key, f"expected at most the diffusion's {T} timesteps, got {steps}")
        _require(g.dit_model in DIT_MODELS, "gaussian.dit_model",
                 f"expected one of {sorted(DIT_MODELS)}, got {g.dit_model!r}")
    check_component(GazeSamplerConfig, g, "gaussian.")
    check_component(GazeEstimatorTrainConfig, cfg.estimator, "estimator.")
    check_component(GaussianModelConfig, g, "gaussian.")


def _check_fit(cfg: RunConfig) -> None:
    """What the test-time fit's settings need of each other and of the trained model."""
    e, g = cfg.eval, cfg.gaussian
    _require("eye_colours" not in e.tta_weights or g.eyeball_colours, "eval.tta_weights",
             "'eye_colours' needs gaussian.eyeball_colours=true (the parametric eyeball whose colours it fits)")
    _require("decoder" not in e.tta_weights or (g.renderer == "dit" and cfg.codec.kind != "pixel"), "eval.tta_weights",
             f"'decoder' needs a codec decoder: gaussian.renderer=dit with codec.kind ae or sd-vae (got renderer "
             f"{g.renderer}, codec {cfg.codec.kind})")
    outside = [w for w in e.tta_gaze_reach if w != "code" and w not in e.tta_weights]
    _require(not outside, "eval.tta_gaze_reach", f"the gaze term may reach only the code and the fitted "
                                                 f"eval.tta_weights {list(e.tta_weights)}, got {outside}")
    _require(e.tta_gaze_terms or not e.tta_gaze_weight > 0, "eval.tta_gaze_terms",
             "expected at least one of target, own when eval.tta_gaze_weight > 0")


def _memory_needs(cfg: RunConfig) -> list[tuple[str, float]]:
    """(config keys, bytes) of one array each stage must hold, a strict lower bound of its memory (no gradients,
    no activations): enough to refuse a typo such as ``geometry.gaussians=1e9`` before anything is allocated."""
    d, g, c, e, geo = cfg.data, cfg.gaussian, cfg.codec, cfg.estimator, cfg.geometry
    px, n_gauss = d.res * d.res, geo.gaussians + 2 * (geo.eye_gaussians + geo.lid_gaussians)
    rig = 18  # ETH-XGaze's cameras: every synthetic frame is rendered by each
    return [
        ("data.frames, data.test_frames, data.res", max(d.frames, d.test_frames) * rig * px * 6),  # uint8 image, masks
        ("geometry.pool", geo.pool * 16.0),  # a point and its signed distance
        ("geometry.gaussians, gaussian.batch, gaussian.gaussians_hidden", n_gauss * g.batch * g.gaussians_hidden * 4),
        ("gaussian.batch, data.res, gaussian.feature_upscale", g.batch * px * g.feature_upscale ** 2 * 32 * 4),
        ("codec.batch, codec.base_channels, data.res", c.batch * px * c.base_channels * 4),
        ("estimator.batch, estimator.input_size", e.batch * e.input_size ** 2 * 3 * 4),
        ("estimator.synthetic_subjects, estimator.synthetic_frames, estimator.cameras_per_frame, data.res",
         e.synthetic_subjects * e.synthetic_frames * e.cameras_per_frame * px * 3),  # uint8 RGB
    ]


def _check_memory(cfg: RunConfig) -> None:
    """Every count that sizes an allocation, bounded by what it would allocate (``toolkit.limits``)."""
    from toolkit.limits import check_allocation

    for keys, nbytes in _memory_needs(cfg):
        check_allocation(nbytes, f"config keys {keys} ({', '.join(_values(cfg, keys))})",
                         "lower them, or raise DITGAZE_MEMORY_GB on a larger machine")


def _values(cfg: RunConfig, keys: str) -> list[str]:
    out = []
    for key in keys.split(", "):
        section, name = key.split(".")
        out.append(f"{name}={getattr(getattr(cfg, section), name)}")
    return out


def _check_files(cfg: RunConfig) -> None:
    """The files the config names: present, and the pairing file readable whole."""
    if cfg.eval.pairing_file:
        from train.data.pairing import load_pairing

        try:  # read whole before any work: a bad file fails here, not after training
            load_pairing(cfg.eval.pairing_file)
        except ToolkitError as err:
            raise ToolkitError(f"config key 'eval.pairing_file': {err}") from None
    _require(not cfg.data.split_file or Path(cfg.data.split_file).is_file(), "data.split_file",
             f"{cfg.data.split_file}: no such file (a split file: JSON {{\"train\": [...], \"test\": [...]}})")
    e = cfg.eval
    _require(not e.data_root or Path(e.data_root).is_dir(), "eval.data_root",
             f"{e.data_root}: no such folder (a folder of subject files to evaluate on)")
    _require(not e.data_split_file or Path(e.data_split_file).is_file(), "eval.data_split_file",
             f"{e.data_split_file}: no such file (a split file of eval.data_root's subjects)")
    if cfg.data.root and Path(cfg.data.root).exists():
        _check_layout(cfg.data.root, cfg.data.layout, "data.layout")
    if e.data_root:
        _check_layout(e.data_root, e.data_layout, "eval.data_layout")
    if e.data_root or (cfg.data.root and Path(cfg.data.root).exists()):  # the held-out files are known before training
        from train.stages.pipeline import RunContext

        _check_held_out_pairing(RunContext(Path("."), cfg))
    lp = {"eval.lpips_vgg_path": e.lpips_vgg_path, "eval.lpips_lin_path": e.lpips_lin_path}
    if any(lp.values()) and not all(lp.values()):
        raise ToolkitError(f"config keys {list(lp)}: LPIPS needs both files (the VGG16 weights and the linear "
                           f"layers), got {lp}")
    estimator_hint = " (a trained gaze estimator, .safetensors; empty: train one)"
    files = {"estimator.loss_path": (cfg.estimator.loss_path, estimator_hint),
             "estimator.eval_path": (cfg.estimator.eval_path, estimator_hint),
             **{key: (path, "") for key, path in lp.items()}, "eval.identity_model_path": (e.identity_model_path, ""),
             "eval.estimator_path": (e.estimator_path, " (GazeNeRF's gaze estimator checkpoint, .pth.tar)"),
             "gaussian.vgg_path": (cfg.gaussian.vgg_path, " (a VGG16 state dict for the perceptual term)")}
    for key, (path, hint) in files.items():
        _require(not path or Path(path).is_file(), key, f"{path}: no such file{hint}")
    c = cfg.codec
    _require(c.kind != "sd-vae" or (c.sd_vae_path and Path(c.sd_vae_path).is_dir()), "codec.sd_vae_path",
             f"{c.sd_vae_path!r}: no such directory (codec.kind=sd-vae reads a local diffusers AutoencoderKL folder)")


def _check_layout(root: str, layout: str, key: str) -> None:
    """A named ``layout`` (config key ``key``) fits the keys of every file under ``root`` (keys only: the stages
    check the rest); ``auto`` is decided file by file when a stage opens them."""
    if layout == "auto":
        return
    from train.data.dataset import find_subject_files
    from train.data.layouts import check_layout, describe_file

    for f in find_subject_files([root]):
        keys, shapes = describe_file(f)
        check_layout(layout, keys, shapes, str(f))


def check_run_pairing(ctx, will_run: set[str]) -> None:
    """The eval stage's pairing against the run's own held-out files, when that stage will run and the data stage
    will not (its files are the current ones): before ``config.yaml`` is written, so that a refused pairing
    file leaves it as it was. The config check covers the files of ``data.root`` and ``eval.data_root``."""
    cfg = ctx.config
    if "eval" not in will_run or "data" in will_run or "data" not in ctx.outputs or cfg.data.root or cfg.eval.data_root:
        return
    _check_held_out_pairing(ctx)


def _check_held_out_pairing(ctx) -> None:
    """:func:`check_eval_pairing` on the held-out files ``ctx`` names; a folder the stages cannot read or split is
    left to the stage that reads it (it names what is wrong), and ETH-XGaze release files under ``data.root``, which
    feed the estimator stage alone, to the eval stage's own one-line refusal; under ``eval.data_root``, which the
    eval stage alone reads, they are refused here, before any training."""
    from train.data.patches import release_layout
    from train.stages.artifacts import RunArtifacts

    cfg, e = ctx.config, ctx.config.eval
    try:
        test = RunArtifacts(ctx).eval_files()
    except ToolkitError:
        return
    if e.data_root and test:  # only the eval stage reads them: files it cannot score are refused before training
        from train.data.layout_files import row_layout

        try:
            row_layout(test[0], e.data_layout)
        except ToolkitError as err:
            raise ToolkitError(f"config key 'eval.data_root': {err}") from None
    if not (test and release_layout(test, e.data_layout if e.data_root else cfg.data.layout)):
        check_eval_pairing(cfg, test)


def check_eval_pairing(cfg: RunConfig, test_files: list[Path]) -> None:
    """Every held-out subject has pairs inside its rows (``train.data.pairing.check_pairing_rows``): one line
    before any work, from the config check (``data.root`` names the files) or the eval stage's start."""
    from train.data.pairing import check_pairing_rows, load_pairing

    path = cfg.eval.pairing_file
    try:
        check_pairing_rows(test_files, load_pairing(path) if path else None,
                           f"the pairing file {path}" if path else "the generated pairing",
                           cfg.eval.data_layout if cfg.eval.data_root else cfg.data.layout)
    except ToolkitError as err:
        raise ToolkitError(f"config key 'eval.pairing_file': {err}" if path else str(err)) from None
