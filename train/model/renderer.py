"""The DiT-Gaze renderer (behind the interface of :mod:`train.model.renderer_interface`) and
:func:`make_renderer`, which builds it or the baseline by name.

:class:`DiTRenderer`: encode the target with the frozen codec, noise it at a random timestep, run the DiT
with the features and codes, take the x0 estimate, decode it (training); at inference run DDIM from seeded
noise with K steps (K = 1 is the deterministic one-step path) and decode. The baseline (GazeGaussian's
renderer) is :class:`train.model.baseline_renderer.BaselineRenderer`.

**Residual parametrization** (``residual=True``, the default): the splat already knows a blurry image, its
first three feature channels (``rgb``, supervised at 1/4 resolution). The renderer encodes that RGB, bilinearly
upsampled to the output size and clamped to [0, 1], with the frozen codec into a base latent
``z_base = codec.encode(up(rgb))`` and lets the DiT model only what is missing: the diffusion runs on the
residual ``r0 = z0 - z_base`` (``x_t = a r0 + s eps``; targets ``eps`` or ``v = a eps - s r0``) and the clean
latent estimate is ``x0 = z_base + r0_hat`` -- in the training pass (what the image and gaze losses see, with
gradients through ``z_base`` into the features) and in DDIM (which samples ``r0`` from pure noise at
``t = T - 1`` and adds ``z_base``). This is the ordinary diffusion of ``z0`` with the network's input shifted by
``a z_base`` and its output by the known ``v``/``eps`` of ``z_base`` -- not SDEdit: no noise level is chosen and
the one-step path still starts from pure noise. With v-prediction and zero terminal SNR (the defaults) the
zero-initialized final layer (adaLN-Zero) predicts ``v = 0``, i.e. ``r0_hat = a_{T-1} x_{T-1} = 0``: the
untrained one-step renderer returns exactly ``codec.decode(z_base)``, the splat's own image, and training
learns the correction. The DiT also sees ``z_base`` as extra input channels when its ``base_channels`` is set
(:func:`make_renderer` does so). ``residual=False`` is the plain latent DiT that starts from nothing.
"""

from __future__ import annotations

import numbers

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.limits import is_finite_number
from train.model.baseline_renderer import BaselineConfig, BaselineRenderer
from train.model.codec import LatentCodec
from train.model.diffusion import DiffusionConfig, GaussianDiffusion
from train.model.dit import DiT, make_dit
from train.model.renderer_interface import RenderOutput, check_finite_inputs, check_render_inputs


class DiTRenderer(nn.Module):
    """The DiT-Gaze renderer: features -> (DiT + DDIM in the codec's latent space) -> decoded image.

    ``upscale`` is output size / feature size (4 in GazeGaussian); the latent grid is then
    ``h * upscale / codec.downsample``. ``default_steps`` is the DDIM step count of ``render``.
    The codec is frozen here: only the DiT trains, gradients reach it through ``codec.decode`` (and, with
    ``residual``, into the features through ``codec.encode`` of the base latent).
    ``residual``: predict the clean latent as ``z_base + r0_hat`` around the encoded splat RGB (module docstring).
    """

    def __init__(self, dit: DiT, codec: LatentCodec, diffusion: GaussianDiffusion | None = None, *,
                 upscale: int = 4, default_steps: int = 1, residual: bool = True):
        super().__init__()
        if dit.config.latent_channels != codec.latent_channels:
            raise ToolkitError(f"DiTRenderer: DiT latent_channels={dit.config.latent_channels} but the codec "
                               f"has {codec.latent_channels}")
        if not isinstance(upscale, numbers.Integral) or isinstance(upscale, bool) or upscale < 1:
            raise ToolkitError(f"DiTRenderer upscale: expected an integer >= 1 (output size / feature-map size), "
                               f"got {upscale!r}")
        self.dit = dit
        self.codec = codec.freeze()
        self.diffusion = diffusion or GaussianDiffusion(DiffusionConfig())
        self.upscale = upscale
        self.default_steps = default_steps
        self.residual = residual
        if dit.config.base_channels and (not residual or dit.config.base_channels != codec.latent_channels):
            raise ToolkitError(f"DiTRenderer: DiT base_channels={dit.config.base_channels} needs residual=True and the "
                               f"codec's {codec.latent_channels} latent channels")
        if dit.config.feature_channels < 3 and residual:
            raise ToolkitError("DiTRenderer residual: the features need >= 3 channels (the first three are RGB)")

    def latent_shape(self, feats: torch.Tensor) -> tuple[int, int, int, int]:
        H, W = feats.shape[2] * self.upscale, feats.shape[3] * self.upscale
        h, w = self.codec.latent_size(H, W)
        return feats.shape[0], self.codec.latent_channels, h, w

    def base_latent(self, feats: torch.Tensor) -> torch.Tensor:
        """``z_base [B, C, H/f, W/f]``: the splatted RGB ``feats[:, :3]`` upsampled (bilinear) to the output size,
        clamped to [0, 1] and encoded by the frozen codec; differentiable with respect to ``feats``."""
        H, W = feats.shape[2] * self.upscale, feats.shape[3] * self.upscale
        rgb = F.interpolate(feats[:, :3], size=(H, W), mode="bilinear", align_corners=False)
        return self.codec.encode(rgb.clamp(0, 1)).float()

    def _model_fn(self, feats, shape_code, gaze, pose, latent_hw: tuple[int, int], base: torch.Tensor | None = None):
        # The feature map is the same at every sampling step: encode it once.
        emb = self.dit.encode_features(feats, latent_hw)
        base = base if self.dit.config.base_channels else None
        return lambda x, t: self.dit(x, t, feats, shape_code, gaze, pose, feature_embedding=emb, base=base)

    def training_forward(self, feats: torch.Tensor, shape_code: torch.Tensor, target: torch.Tensor, *,
                         gaze: torch.Tensor | None = None, pose: torch.Tensor | None = None,
                         generator: torch.Generator | None = None, t: torch.Tensor | None = None,
                         noise: torch.Tensor | None = None) -> RenderOutput:
        """``noise`` [B, C, h, w]: the diffusion's noise for these samples (default: drawn from ``generator``)."""
        check_render_inputs(feats, shape_code, self.dit.config.feature_channels, self.dit.config.shape_dim)
        B, C, h, w = self.latent_shape(feats)
        if target.shape != (B, 3, h * self.codec.downsample, w * self.codec.downsample):
            raise ToolkitError(f"DiTRenderer target: expected [{B}, 3, {h * self.codec.downsample}, "
                               f"{w * self.codec.downsample}] (features x {self.upscale}), got {list(target.shape)}")
        with torch.no_grad():
            x0 = self.codec.encode(target).float()
        base = self.base_latent(feats) if self.residual else None
        # The diffusion runs on the residual; its target uses a detached base so the diffusion loss does not
        # pull the splat toward the network's current output (the image losses train the splat through x0).
        r0 = x0 - base.detach() if base is not None else x0
        out = self.diffusion.training_step(self._model_fn(feats, shape_code, gaze, pose, (h, w), base), r0, t=t,
                                          noise=noise, generator=generator)
        latent = out["x0_pred"] + base if base is not None else out["x0_pred"]
        image = self.codec.decode(latent)
        extras = {"t": out["t"], "latent_pred": latent, "latent_target": x0}
        if base is not None:
            extras["latent_base"] = base
        return RenderOutput(image=image, aux_loss=out["loss"], extras=extras)

    def render(self, feats: torch.Tensor, shape_code: torch.Tensor, *, gaze: torch.Tensor | None = None,
               pose: torch.Tensor | None = None, steps: int | None = None, seed: int = 0,
               noise: torch.Tensor | None = None, eta: float = 0.0) -> torch.Tensor:
        """DDIM with ``steps`` (default ``default_steps``) from ``noise`` or from noise drawn with ``seed``."""
        check_render_inputs(feats, shape_code, self.dit.config.feature_channels, self.dit.config.shape_dim)
        if not is_finite_number(eta):
            raise ToolkitError(f"DiTRenderer eta: expected a finite number (0: deterministic DDIM), got {eta!r}")
        check_finite_inputs(feats=feats, shape_code=shape_code, gaze=gaze, pose=pose, noise=noise)
        shape = self.latent_shape(feats)
        g = torch.Generator().manual_seed(seed)
        if noise is None:
            noise = torch.randn(shape, generator=g)
        elif tuple(noise.shape) != shape:
            raise ToolkitError(f"DiTRenderer noise: expected {list(shape)}, got {list(noise.shape)}")
        base = self.base_latent(feats) if self.residual else None
        model_fn = self._model_fn(feats, shape_code, gaze, pose, shape[2:], base)
        latent = self.diffusion.ddim_sample(model_fn, noise.to(feats.device), steps or self.default_steps, eta=eta,
                                            generator=g)
        if base is not None:  # DDIM sampled the residual
            latent = latent + base.to(latent.dtype)
        return self.codec.decode(latent).clamp(0, 1)

    def forward(self, feats: torch.Tensor, shape_code: torch.Tensor, gaze: torch.Tensor | None = None,
                pose: torch.Tensor | None = None) -> torch.Tensor:
        return self.render(feats, shape_code, gaze=gaze, pose=pose)


def make_renderer(kind: str, codec: LatentCodec | None = None, *, model: str = "DiT-Gaze-tiny",
                  output_size: int = 128, upscale: int = 4, diffusion: DiffusionConfig | None = None,
                  residual: bool = True, **model_kw) -> nn.Module:
    """``"dit"`` (needs a codec) or ``"baseline"``; ``model_kw`` go to the DiT config / baseline config.

    ``residual`` (DiT only): the residual parametrization around the encoded splat RGB, with the base latent
    also fed to the DiT as input channels (``base_channels``)."""
    if kind == "dit":
        if codec is None:
            raise ToolkitError("make_renderer('dit'): a latent codec is required (see train.model.codec.load_codec)")
        if not isinstance(output_size, numbers.Integral) or output_size < codec.downsample:
            raise ToolkitError(f"make_renderer output_size: expected an image size >= the codec's downsample factor "
                               f"{codec.downsample}, got {output_size!r}")
        grid = output_size // codec.downsample
        if fixed := sorted({"input_size", "latent_channels"} & set(model_kw)):  # the codec and output_size set them
            raise ToolkitError(f"make_renderer: {fixed} follow from the codec and output_size; pass output_size")
        if residual:
            model_kw.setdefault("base_channels", codec.latent_channels)
        dit = make_dit(model, input_size=grid, latent_channels=codec.latent_channels, **model_kw)
        return DiTRenderer(dit, codec, GaussianDiffusion(diffusion), upscale=upscale, residual=residual)
    if kind == "baseline":
        return BaselineRenderer(BaselineConfig(upscale=upscale, **model_kw))
    raise ToolkitError(f"renderer kind: expected 'dit' or 'baseline', got {kind!r}")
