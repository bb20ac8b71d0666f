"""The intermediate gaze sampler: target gazes the eye rotation field is driven to during training.

Gazes are ``[B, 2]`` (pitch, yaw) in radians, ETH-XGaze convention (README), head frame. Modes, with the
range half-width ``R`` (``range_deg``):

* ``uniform``       -- pitch and yaw independently uniform in ``[-R, R]``;
* ``biased_center`` -- independently a normal of std ``center_std * R`` truncated to ``[-R, R]`` (exact,
  inverse-CDF sampling: no rejection loop, so the number of random draws is fixed);
* ``mixed``         -- ``round(grid_fraction * B)`` samples from the grid ``g_yaw = -R + 2R i/(N-1)``,
  ``g_pitch = -R + 2R j/(N-1)`` (``i, j = 0..N-1``), the rest uniform. Grid points are dealt from a seeded
  random permutation, so every point is used once per ``N^2`` grid draws (coverage is guaranteed).

Progressive schedule (``progressive=True``), a function of training progress ``p`` in [0, 1]: with
``s = min(p / ramp_end, 1)`` the half-width is ``R_p = R (start_range + (1 - start_range) s)`` and a fraction
``w_p = start_center_weight (1 - s)`` of the non-grid samples is drawn centre-biased (in ``R_p``) instead of
from the mode -- a small, centre-biased range early, widening and moving to the mode (uniform) later.
``R_p`` is non-decreasing and ``w_p`` non-increasing in ``p``.

All randomness comes from one ``torch.Generator`` seeded from the config; ``state_dict`` captures it (and
the grid permutation), so a resumed run draws the same gazes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

from toolkit.errors import ToolkitError

MAX_GAZE = math.radians(89.0)  # beyond +-90 deg pitch/yaw the gaze angles stop being a chart of the sphere

Mode = Literal["uniform", "biased_center", "mixed"]


@dataclass
class GazeSamplerConfig:
    """How intermediate gazes are drawn."""

    mode: Mode = "mixed"
    range_deg: float = 30.0
    """Half-width R of the pitch and yaw range, degrees."""
    grid_size: int = 5
    """N: grid points per axis in ``mixed`` mode (N^2 in all)."""
    grid_fraction: float = 0.5
    """Share of each ``mixed`` batch taken from the grid."""
    center_std: float = 0.35
    """Std of the centre-biased normal as a fraction of the current half-width."""
    progressive: bool = False
    start_range: float = 0.3
    """Progressive: half-width at progress 0, as a fraction of R."""
    start_center_weight: float = 1.0
    """Progressive: share of non-grid samples drawn centre-biased at progress 0."""
    ramp_end: float = 0.7
    """Progressive: progress at which the full range and the plain mode are reached."""
    seed: int = 0

    def validate(self) -> None:
        if self.mode not in ("uniform", "biased_center", "mixed"):
            raise ToolkitError(f"GazeSamplerConfig.mode: expected uniform, biased_center or mixed, got {self.mode!r}")
        if not 0 < self.range_deg <= 89:
            raise ToolkitError(f"GazeSamplerConfig.range_deg: expected (0, 89] degrees, got {self.range_deg}")
        if self.grid_size < 2:
            raise ToolkitError(f"GazeSamplerConfig.grid_size: expected >= 2, got {self.grid_size}")
        for name in ("grid_fraction", "start_range", "start_center_weight"):
            if not 0 <= getattr(self, name) <= 1:
                raise ToolkitError(f"GazeSamplerConfig.{name}: expected a value in [0, 1], got {getattr(self, name)}")
        if self.center_std <= 0 or self.ramp_end <= 0:
            raise ToolkitError(f"GazeSamplerConfig: center_std and ramp_end must be > 0, got {self.center_std}, {self.ramp_end}")


def gaze_grid(n: int, half_width: float) -> torch.Tensor:
    """The ``[n * n, 2]`` (pitch, yaw) grid ``-R + 2R k/(n-1)`` on both axes; row ``j * n + i`` = (pitch_j, yaw_i)."""
    axis = torch.linspace(-half_width, half_width, n, dtype=torch.float64)
    pitch, yaw = torch.meshgrid(axis, axis, indexing="ij")
    return torch.stack([pitch.reshape(-1), yaw.reshape(-1)], dim=1).float()


def truncated_normal(shape: tuple[int, ...], std: float, bound: float, generator: torch.Generator) -> torch.Tensor:
    """Normal(0, std) truncated to ``[-bound, bound]`` by inverse-CDF sampling (exactly one uniform per value)."""
    lo = torch.special.ndtr(torch.tensor(-bound / std, dtype=torch.float64))
    u = lo + (1 - 2 * lo) * torch.rand(shape, generator=generator, dtype=torch.float64)
    return (std * torch.special.ndtri(u.clamp(1e-12, 1 - 1e-12))).clamp(-bound, bound).float()


class GazeSampler:
    """Draws intermediate gazes; ``sample(batch, progress)`` -> ``[B, 2]`` (pitch, yaw) radians."""

    def __init__(self, config: GazeSamplerConfig | None = None):
        self.config = config or GazeSamplerConfig()
        self.config.validate()
        self.generator = torch.Generator().manual_seed(self.config.seed)
        n2 = self.config.grid_size**2
        self._perm = torch.randperm(n2, generator=self.generator)
        self._cursor = 0

    def schedule(self, progress: float) -> tuple[float, float]:
        """``(half_width_rad, center_weight)`` at training progress in [0, 1] (constant unless progressive)."""
        c = self.config
        R = math.radians(c.range_deg)
        if not c.progressive:
            return R, 0.0
        s = min(max(float(progress), 0.0) / c.ramp_end, 1.0)
        return R * (c.start_range + (1 - c.start_range) * s), c.start_center_weight * (1 - s)

    def _grid_indices(self, k: int) -> torch.Tensor:
        out = []
        for _ in range(k):
            if self._cursor == len(self._perm):
                self._perm = torch.randperm(len(self._perm), generator=self.generator)
                self._cursor = 0
            out.append(int(self._perm[self._cursor]))
            self._cursor += 1
        return torch.tensor(out, dtype=torch.long)

    def sample(self, batch: int, progress: float = 1.0, center: torch.Tensor | None = None) -> torch.Tensor:
        """``batch`` gazes ``[B, 2]`` (pitch, yaw) in radians, offset by ``center [B, 2]`` if given.

        The result is clamped to +-89 degrees. Grid samples (``mixed``) come first in the batch.
        """
        if batch < 1:
            raise ToolkitError(f"gaze sampler batch: expected >= 1, got {batch}")
        if center is not None and tuple(center.shape) != (batch, 2):
            raise ToolkitError(f"gaze sampler center: expected [{batch}, 2], got {list(center.shape)}")
        c, g = self.config, self.generator
        R, w = self.schedule(progress)
        n_grid = round(c.grid_fraction * batch) if c.mode == "mixed" else 0
        n_rest = batch - n_grid
        parts = []
        if n_grid:
            parts.append(gaze_grid(c.grid_size, R)[self._grid_indices(n_grid)])
        if n_rest:
            # Draw every kind for all rest samples, then select: the number of draws per call is fixed,
            # so the generator stream (and reproducibility) does not depend on the mixture outcome.
            uniform = (torch.rand(n_rest, 2, generator=g) * 2 - 1) * R
            biased = truncated_normal((n_rest, 2), c.center_std * R, R, g)
            pick_biased = torch.rand(n_rest, 1, generator=g) < w
            mode_draw = biased if c.mode == "biased_center" else uniform
            parts.append(torch.where(pick_biased, biased, mode_draw))
        gaze = torch.cat(parts)
        if center is not None:
            gaze = gaze.to(center.device) + center
        return gaze.clamp(-MAX_GAZE, MAX_GAZE)

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state(), "perm": self._perm.clone(), "cursor": self._cursor}

    def load_state_dict(self, state: dict) -> None:
        if set(state) != {"generator", "perm", "cursor"} or len(state["perm"]) != self.config.grid_size**2:
            raise ToolkitError("gaze sampler state: expected keys generator, perm, cursor for this grid size")
        self.generator.set_state(state["generator"])
        self._perm = state["perm"].clone()
        self._cursor = int(state["cursor"])
