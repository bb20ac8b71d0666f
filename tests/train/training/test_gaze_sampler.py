"""The intermediate gaze sampler: grid coverage, distribution per mode, schedule, reproducibility."""

from __future__ import annotations

import math

import pytest
import torch

from toolkit import ToolkitError
from train.training.gaze_sampler import GazeSampler, GazeSamplerConfig, gaze_grid, truncated_normal

R = math.radians(30)


def test_grid_formula():
    grid = gaze_grid(5, R)
    assert grid.shape == (25, 2)
    for i in range(5):
        for j in range(5):
            torch.testing.assert_close(grid[j * 5 + i], torch.tensor([-R + 2 * R * j / 4, -R + 2 * R * i / 4]))


def test_mixed_mode_covers_the_grid():
    s = GazeSampler(GazeSamplerConfig(mode="mixed", grid_size=5, grid_fraction=0.5, seed=3))
    grid = gaze_grid(5, R)
    seen = torch.zeros(25, dtype=torch.bool)
    for _ in range(7):  # 4 grid samples per batch of 8: 28 >= 25 draws cover every point
        gz = s.sample(8)
        d = torch.cdist(gz[:4], grid)
        assert (d.min(dim=1).values < 1e-6).all()  # the first half are exact grid points
        seen[d.argmin(dim=1)] = True
        assert (torch.cdist(gz[4:], grid).min(dim=1).values > 1e-6).all()  # the rest are random
    assert seen.all()


def test_uniform_mode_distribution():
    gz = GazeSampler(GazeSamplerConfig(mode="uniform")).sample(20000)
    assert gz.abs().max() <= R
    assert gz.mean(0).abs().max() < 0.02
    torch.testing.assert_close(gz.std(0), torch.full((2,), R / math.sqrt(3)), rtol=0.03, atol=0)
    hist = torch.histc(gz[:, 1], bins=6, min=-R, max=R) / 20000
    assert (hist - 1 / 6).abs().max() < 0.02  # flat


def test_biased_center_mode_distribution():
    gz = GazeSampler(GazeSamplerConfig(mode="biased_center", center_std=0.35)).sample(20000)
    assert gz.abs().max() <= R
    inner = (gz.abs() < R / 3).float().mean().item()
    assert inner > 0.6  # uniform would give 1/3; a normal of std 0.35R truncated at R gives ~0.66
    std = gz.std(0)
    assert (std < 0.35 * R).all() and (std > 0.3 * R).all()  # truncation shrinks the std a little


def test_truncated_normal_matches_the_normal_inside():
    x = truncated_normal((50000,), 1.0, 3.0, torch.Generator().manual_seed(0))
    assert x.abs().max() <= 3.0
    assert abs(x.std().item() - 0.9866) < 0.01  # std of N(0,1) truncated to +-3


def test_progressive_schedule_is_monotone_and_widens():
    cfg = GazeSamplerConfig(mode="uniform", progressive=True, start_range=0.2, ramp_end=0.5)
    s = GazeSampler(cfg)
    ps = torch.linspace(0, 1, 41).tolist()
    ranges, weights = zip(*(s.schedule(p) for p in ps), strict=True)
    assert all(b >= a for a, b in zip(ranges, ranges[1:], strict=False))
    assert all(b <= a for a, b in zip(weights, weights[1:], strict=False))
    assert ranges[0] == pytest.approx(0.2 * R) and ranges[-1] == pytest.approx(R)
    assert weights[0] == 1.0 and weights[-1] == 0.0 and s.schedule(0.5) == (pytest.approx(R), 0.0)
    early, late = s.sample(5000, progress=0.0), s.sample(5000, progress=1.0)
    assert early.abs().max() <= 0.2 * R + 1e-6
    assert early.abs().mean() < 0.5 * late.abs().mean()
    hist = torch.histc(late[:, 0], bins=4, min=-R, max=R) / 5000
    assert (hist - 0.25).abs().max() < 0.03  # uniform at the end


def test_not_progressive_ignores_progress():
    a = GazeSampler(GazeSamplerConfig(seed=1)).sample(16, progress=0.0)
    b = GazeSampler(GazeSamplerConfig(seed=1)).sample(16, progress=1.0)
    assert torch.equal(a, b)


@pytest.mark.parametrize("mode", ["uniform", "biased_center", "mixed"])
def test_reproducible_from_seed_and_state(mode):
    cfg = GazeSamplerConfig(mode=mode, progressive=True, seed=7)
    a, b = GazeSampler(cfg), GazeSampler(cfg)
    assert torch.equal(torch.cat([a.sample(5, p) for p in (0.0, 0.3, 1.0)]),
                       torch.cat([b.sample(5, p) for p in (0.0, 0.3, 1.0)]))
    state = a.state_dict()
    x = a.sample(9, 0.5)
    b.load_state_dict(state)
    assert torch.equal(x, b.sample(9, 0.5))
    assert not torch.equal(x, GazeSampler(GazeSamplerConfig(mode=mode, progressive=True, seed=8)).sample(9, 0.5))


def test_center_offset_and_clamp():
    s = GazeSampler(GazeSamplerConfig(mode="uniform", range_deg=89))
    center = torch.tensor([[math.radians(80), 0.0]]).repeat(64, 1)
    gz = s.sample(64, center=center)
    assert gz.abs().max() <= math.radians(89) + 1e-6 and gz[:, 0].mean() > math.radians(40)


@pytest.mark.parametrize("bad", [dict(mode="grid"), dict(range_deg=0), dict(range_deg=120), dict(grid_size=1),
                                 dict(grid_fraction=1.5), dict(center_std=0)])
def test_bad_config(bad):
    with pytest.raises(ToolkitError, match="GazeSamplerConfig"):
        GazeSampler(GazeSamplerConfig(**bad))


def test_bad_calls():
    s = GazeSampler()
    with pytest.raises(ToolkitError, match="batch"):
        s.sample(0)
    with pytest.raises(ToolkitError, match="center"):
        s.sample(2, center=torch.zeros(3, 2))
    with pytest.raises(ToolkitError, match="state"):
        s.load_state_dict({"perm": torch.arange(3)})
