"""Gaussian diffusion for the DiT renderer: noise schedules, epsilon / v targets, q_sample, the loss, DDIM.

Notation (Ho et al. 2020; Song et al. 2021; Salimans & Ho 2022): ``abar_t`` is the cumulative product of
``1 - beta``; ``a = sqrt(abar_t)``, ``s = sqrt(1 - abar_t)``.

* forward process  ``x_t = a x0 + s eps``
* epsilon target   ``eps``                      -> ``x0 = (x_t - s eps) / a``
* v target         ``v = a eps - s x0``         -> ``x0 = a x_t - s v``,  ``eps = s x_t + a v``

Timesteps are integers in ``[0, T)``; ``t = T - 1`` is the noisiest. With ``zero_terminal_snr`` (Lin et al.
2024, the default) ``abar_{T-1} = 0``: the last step is pure noise, so DDIM with one step starting there maps
noise straight to the model's x0 estimate (``x0 = -v``) -- the deterministic 1-step path. That combination
needs the v target (epsilon carries no information about x0 at zero SNR), which the config checks.

During training the image and gaze losses see :func:`GaussianDiffusion.predict_x0` of the network output,
decoded by the codec: the "decoded x0 estimate" of the method.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Callable, Literal

import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.limits import is_finite_number

EPS = 1e-12  # floor under square roots and divisions by sqrt(abar)

BETA_DEFAULTS = {"linear": (1e-4, 2e-2), "scaled_linear": (0.00085, 0.012)}
"""(beta_start, beta_end) of the (scaled) linear schedules when the config leaves them None."""

ModelFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``model_fn(x_t [B, C, H, W], t [B] long) -> network output [B, C, H, W]`` (conditioning bound in)."""


@dataclass
class DiffusionConfig:
    """Noise schedule and parameterization."""

    num_timesteps: int = 1000
    schedule: Literal["linear", "scaled_linear", "cosine"] = "scaled_linear"
    """linear: DDPM betas 1e-4..2e-2; scaled_linear: Stable Diffusion's (sqrt-linear 0.00085..0.012);
    cosine: Nichol & Dhariwal's abar = cos^2."""
    beta_start: float | None = None
    """First beta of the (scaled) linear schedules; None uses the schedule's standard value."""
    beta_end: float | None = None
    prediction: Literal["eps", "v"] = "v"
    zero_terminal_snr: bool = True
    """Rescale the schedule so abar at the last step is exactly 0 (needs prediction 'v')."""

    def validate(self) -> None:
        T = self.num_timesteps
        if not isinstance(T, numbers.Integral) or isinstance(T, bool) or T < 2:
            raise ToolkitError(f"DiffusionConfig.num_timesteps: expected an integer >= 2, got {T!r}")
        if self.schedule not in ("linear", "scaled_linear", "cosine"):
            raise ToolkitError(f"DiffusionConfig.schedule: expected linear, scaled_linear or cosine, got {self.schedule!r}")
        for name in ("beta_start", "beta_end"):
            b = getattr(self, name)
            if b is not None and not 0.0 <= b < 1.0:
                raise ToolkitError(f"DiffusionConfig.{name}: expected a beta in [0, 1), got {b}")
        if self.schedule in BETA_DEFAULTS:
            b0, b1 = (_or(b, d) for b, d in zip((self.beta_start, self.beta_end), BETA_DEFAULTS[self.schedule]))
            if b0 > b1:
                raise ToolkitError(f"DiffusionConfig: need beta_start <= beta_end (a non-decreasing {self.schedule} "
                                   f"schedule), got beta_start={b0}, beta_end={b1}")
        if self.prediction not in ("eps", "v"):
            raise ToolkitError(f"DiffusionConfig.prediction: expected 'eps' or 'v', got {self.prediction!r}")
        if self.zero_terminal_snr and self.prediction == "eps":
            raise ToolkitError("DiffusionConfig: zero_terminal_snr needs prediction='v' (x0 is undefined from eps at zero SNR)")


def _or(value: float | None, default: float) -> float:
    return default if value is None else value  # an explicit 0.0 is a value, not "unset"


def make_betas(config: DiffusionConfig) -> torch.Tensor:
    """The schedule's ``beta [T]`` in float64."""
    T = config.num_timesteps
    if config.schedule == "linear":
        b0, b1 = _or(config.beta_start, BETA_DEFAULTS["linear"][0]), _or(config.beta_end, BETA_DEFAULTS["linear"][1])
        betas = torch.linspace(b0, b1, T, dtype=torch.float64)
    elif config.schedule == "scaled_linear":
        b0, b1 = (_or(config.beta_start, BETA_DEFAULTS["scaled_linear"][0]),
                  _or(config.beta_end, BETA_DEFAULTS["scaled_linear"][1]))
        betas = torch.linspace(b0**0.5, b1**0.5, T, dtype=torch.float64) ** 2
    else:
        s = 0.008
        steps = torch.arange(T + 1, dtype=torch.float64) / T
        abar = torch.cos((steps + s) / (1 + s) * math.pi / 2) ** 2
        betas = (1 - abar[1:] / abar[:-1]).clamp(max=0.999)
    if config.zero_terminal_snr:
        betas = rescale_zero_terminal_snr(betas)
    return betas


def rescale_zero_terminal_snr(betas: torch.Tensor) -> torch.Tensor:
    """Shift and scale ``sqrt(abar)`` so its last value is 0 and its first unchanged (Lin et al., Alg. 1)."""
    sqrt_abar = torch.cumprod(1 - betas, 0).sqrt()
    first, last = sqrt_abar[0].clone(), sqrt_abar[-1].clone()
    sqrt_abar = (sqrt_abar - last) * first / (first - last)
    abar = sqrt_abar**2
    alphas = torch.cat([abar[:1], abar[1:] / abar[:-1]])
    return 1 - alphas


def ddim_timesteps(num_timesteps: int, steps: int) -> torch.Tensor:
    """``steps`` descending timesteps with "trailing" spacing: the first is always ``T - 1``.

    Trailing spacing (Lin et al. 2024, Table 2) makes a 1-step sampler start from pure noise, which the
    deterministic 1-step path relies on.
    """
    if not 1 <= steps <= num_timesteps:
        raise ToolkitError(f"DDIM steps: expected 1..{num_timesteps}, got {steps}")
    ts = torch.round(torch.arange(num_timesteps, 0, -num_timesteps / steps, dtype=torch.float64)).long() - 1
    return ts[:steps]


class GaussianDiffusion:
    """Schedule tables plus the algebra between x0, eps, v and x_t; DDIM sampling. Holds no parameters."""

    def __init__(self, config: DiffusionConfig | None = None):
        self.config = config or DiffusionConfig()
        self.config.validate()
        betas = make_betas(self.config)
        self.num_timesteps = self.config.num_timesteps
        self.alphas_cumprod = torch.cumprod(1 - betas, 0)  # float64, cast on use

    # ------------------------------------------------------------------ tables
    def _coef(self, t: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(sqrt(abar_t), sqrt(1 - abar_t))`` for ``t [B]``, shaped ``[B, 1, 1, 1]`` like ``x``."""
        abar = self.alphas_cumprod.to(x.device)[t.long()]
        a = abar.clamp(min=0).sqrt().to(torch.float32)
        s = (1 - abar).clamp(min=0).sqrt().to(torch.float32)
        shape = (-1,) + (1,) * (x.dim() - 1)
        return a.view(shape), s.view(shape)

    def sample_timesteps(self, batch: int, generator: torch.Generator | None = None,
                         device: torch.device | str = "cpu", t_min: int = 0, t_max: int | None = None) -> torch.Tensor:
        """Uniform training timesteps ``[B]`` in ``[t_min, t_max]`` (default the whole range)."""
        t_max = self.num_timesteps - 1 if t_max is None else t_max
        if not 0 <= t_min <= t_max < self.num_timesteps:
            raise ToolkitError(f"timestep range: expected 0 <= t_min <= t_max < {self.num_timesteps}, got [{t_min}, {t_max}]")
        return torch.randint(t_min, t_max + 1, (batch,), generator=generator).to(device)

    # ------------------------------------------------------------------ algebra
    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Forward process ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) noise``; all ``[B, C, H, W]``."""
        a, s = self._coef(t, x0)
        return a.to(x0.dtype) * x0 + s.to(x0.dtype) * noise

    def training_target(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """What the network regresses: ``noise`` (eps) or ``v = a noise - s x0``."""
        if self.config.prediction == "eps":
            return noise
        a, s = self._coef(t, x0)
        return a.to(x0.dtype) * noise - s.to(x0.dtype) * x0

    def predict_x0(self, model_output: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The x0 estimate from the network output at ``(x_t, t)`` -- what the image losses see in training."""
        a, s = self._coef(t, x_t)
        if self.config.prediction == "v":
            return a * x_t - s * model_output
        return (x_t - s * model_output) / a.clamp(min=math.sqrt(EPS))

    def predict_eps(self, model_output: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The noise estimate from the network output at ``(x_t, t)``."""
        if self.config.prediction == "eps":
            return model_output
        a, s = self._coef(t, x_t)
        return s * x_t + a * model_output

    def loss(self, model_output: torch.Tensor, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Mean squared error to the training target (a scalar), computed in float32."""
        target = self.training_target(x0.float(), noise.float(), t)
        return F.mse_loss(model_output.float(), target)

    def training_step(self, model_fn: ModelFn, x0: torch.Tensor, t: torch.Tensor | None = None,
                      noise: torch.Tensor | None = None, generator: torch.Generator | None = None
                      ) -> dict[str, torch.Tensor]:
        """Noise ``x0``, run the network, return ``{"loss", "x0_pred", "x_t", "t", "noise"}``.

        ``x0_pred`` keeps the graph, so image and gaze losses on its decoding train the network too.
        """
        B = x0.shape[0]
        if t is None:
            t = self.sample_timesteps(B, generator, x0.device)
        if noise is None:
            noise = torch.randn(x0.shape, generator=generator, dtype=x0.dtype).to(x0.device)
        x_t = self.q_sample(x0, t, noise)
        out = model_fn(x_t, t)
        return {"loss": self.loss(out, x0, noise, t), "x0_pred": self.predict_x0(out.float(), x_t.float(), t),
                "x_t": x_t, "t": t, "noise": noise}

    # ------------------------------------------------------------------ sampling
    def ddim_sample(self, model_fn: ModelFn, noise: torch.Tensor, steps: int, eta: float = 0.0,
                    generator: torch.Generator | None = None, clip_x0: float | None = None) -> torch.Tensor:
        """DDIM from ``noise [B, C, H, W]`` (the state at ``t = T - 1``) to x0 in ``steps`` network calls.

        ``eta = 0`` is deterministic given ``noise``; ``eta > 0`` adds the DDIM stochastic term drawn from
        ``generator``. ``clip_x0`` clamps the intermediate x0 estimates to ``[-clip_x0, clip_x0]``. The
        last step lands on x0 (``abar = 1``), so ``steps = 1`` returns ``predict_x0(model(noise, T - 1))``.
        """
        if not is_finite_number(eta):
            raise ToolkitError(f"DDIM eta: expected a finite number (0: deterministic), got {eta!r}")
        ts = ddim_timesteps(self.num_timesteps, steps).to(noise.device)
        x = noise
        B = noise.shape[0]
        for i, t in enumerate(ts):
            tb = t.expand(B)
            out = model_fn(x, tb).float()
            x0 = self.predict_x0(out, x.float(), tb)
            if clip_x0 is not None:
                x0 = x0.clamp(-clip_x0, clip_x0)
            if i == len(ts) - 1:
                return x0.to(noise.dtype)
            eps = self.predict_eps(out, x.float(), tb) if clip_x0 is None else self._eps_from_x0(x0, x.float(), tb)
            abar_t = self.alphas_cumprod[t.item()]
            abar_prev = self.alphas_cumprod[ts[i + 1].item()]
            sigma = eta * math.sqrt(max((1 - abar_prev) / max(1 - abar_t, EPS) * (1 - abar_t / max(abar_prev, EPS)), 0.0))
            dir_coef = math.sqrt(max(1 - abar_prev - sigma**2, 0.0))
            x = math.sqrt(abar_prev) * x0 + dir_coef * eps
            if sigma > 0:
                x = x + sigma * torch.randn(x.shape, generator=generator).to(x.device)
            x = x.to(noise.dtype)
        return x  # unreachable: the loop returns at its last step

    def _eps_from_x0(self, x0: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        a, s = self._coef(t, x_t)
        return (x_t - a * x0) / s.clamp(min=math.sqrt(EPS))
