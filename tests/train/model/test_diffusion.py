"""Diffusion: schedules, eps/v algebra, DDIM (1-step determinism, multi-step consistency, exactness)."""

from __future__ import annotations

import pytest
import torch

from tests.train.threads import single_thread  # noqa: F401  (autouse)
from toolkit import ToolkitError
from train.model.diffusion import DiffusionConfig, GaussianDiffusion, ddim_timesteps, make_betas


@pytest.mark.parametrize("schedule", ["linear", "scaled_linear", "cosine"])
@pytest.mark.parametrize("zero_snr", [True, False])
def test_schedules(schedule, zero_snr):
    cfg = DiffusionConfig(schedule=schedule, zero_terminal_snr=zero_snr, prediction="v")
    abar = GaussianDiffusion(cfg).alphas_cumprod
    betas = make_betas(cfg)
    assert abar.shape == (1000,) and torch.isfinite(abar).all() and torch.isfinite(betas).all()
    assert (abar[1:] <= abar[:-1]).all() and abar[0] > 0.99 and (abar >= 0).all() and (abar <= 1).all()
    if zero_snr:
        assert abar[-1] == 0
    else:
        assert 0 < abar[-1] < 0.05


def test_ddim_timesteps_trailing():
    for k in (1, 2, 4, 8, 25, 50, 1000):
        ts = ddim_timesteps(1000, k)
        assert len(ts) == k and ts[0] == 999 and (ts[1:] < ts[:-1]).all() and ts[-1] >= 0
    for bad in (0, 1001):
        with pytest.raises(ToolkitError, match="DDIM steps"):
            ddim_timesteps(1000, bad)


@pytest.mark.parametrize("prediction,zero_snr", [("v", True), ("v", False), ("eps", False)])
def test_target_algebra(prediction, zero_snr):
    d = GaussianDiffusion(DiffusionConfig(prediction=prediction, zero_terminal_snr=zero_snr))
    x0, eps = torch.randn(6, 4, 5, 5), torch.randn(6, 4, 5, 5)
    t = torch.tensor([0, 10, 300, 700, 990, 998])
    xt = d.q_sample(x0, t, eps)
    target = d.training_target(x0, eps, t)
    torch.testing.assert_close(d.predict_x0(target, xt, t), x0, atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(d.predict_eps(target, xt, t), eps, atol=2e-4, rtol=1e-4)
    a = d.alphas_cumprod[t].sqrt().float().view(-1, 1, 1, 1)
    s = (1 - d.alphas_cumprod[t]).sqrt().float().view(-1, 1, 1, 1)
    torch.testing.assert_close(xt, a * x0 + s * eps)
    if prediction == "v":
        torch.testing.assert_close(target, a * eps - s * x0)
    else:
        assert torch.equal(target, eps)
    assert d.loss(target, x0, eps, t) < 1e-10


def test_zero_snr_last_step_is_pure_noise_and_x0_is_minus_v():
    d = GaussianDiffusion()
    x0, eps = torch.randn(2, 4, 3, 3), torch.randn(2, 4, 3, 3)
    t = torch.tensor([999, 999])
    assert torch.equal(d.q_sample(x0, t, eps), eps)
    v = torch.randn_like(x0)
    torch.testing.assert_close(d.predict_x0(v, eps, t), -v)


def oracle(d: GaussianDiffusion, x0: torch.Tensor):
    """The exact network for a point-mass data distribution at x0: it returns the true target."""
    def model_fn(x, t):
        a, s = d._coef(t, x)
        eps = (x - a * x0) / s.clamp(min=1e-6)
        return d.training_target(x0, eps, t)
    return model_fn


@pytest.mark.parametrize("cfg", [DiffusionConfig(), DiffusionConfig(prediction="eps", zero_terminal_snr=False,
                                                                    schedule="linear")])
def test_ddim_recovers_a_point_mass_for_any_step_count(cfg):
    d = GaussianDiffusion(cfg)
    x0 = torch.randn(2, 4, 4, 4)
    noise = torch.randn_like(x0)
    for k in (1, 2, 4, 8, 25, 50):
        torch.testing.assert_close(d.ddim_sample(oracle(d, x0), noise, k), x0, atol=2e-3, rtol=1e-3)


def test_ddim_one_step_is_deterministic_and_eta_uses_the_generator():
    d = GaussianDiffusion()
    w = torch.randn(4, 4)
    model_fn = lambda x, t: torch.einsum("ij,bjhw->bihw", w, x) * (1 + t.float().view(-1, 1, 1, 1) / 1000)  # noqa: E731
    noise = torch.randn(3, 4, 4, 4)
    a, b = d.ddim_sample(model_fn, noise, 1), d.ddim_sample(model_fn, noise.clone(), 1)
    assert torch.equal(a, b)
    torch.testing.assert_close(a, d.predict_x0(model_fn(noise, torch.full((3,), 999)), noise, torch.full((3,), 999)))
    s1 = d.ddim_sample(model_fn, noise, 8, eta=1.0, generator=torch.Generator().manual_seed(1))
    s2 = d.ddim_sample(model_fn, noise, 8, eta=1.0, generator=torch.Generator().manual_seed(1))
    s3 = d.ddim_sample(model_fn, noise, 8, eta=1.0, generator=torch.Generator().manual_seed(2))
    assert torch.equal(s1, s2) and not torch.allclose(s1, s3)


def test_ddim_multistep_converges_on_gaussian_data():
    """For x0 ~ N(mu, sig^2) the exact denoiser is linear and the DDIM ODE maps noise z to mu + sig z."""
    mu, sig = 0.7, 0.4
    d = GaussianDiffusion()

    def model_fn(x, t):  # the optimal v for Gaussian data, from E[x0 | x_t]
        a, s = d._coef(t, x)
        x0 = mu + a * sig**2 / (a**2 * sig**2 + s**2) * (x - a * mu)
        eps = (x - a * x0) / s.clamp(min=1e-6)
        return a * eps - s * x0

    z = torch.randn(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
    exact = mu + sig * z
    errors = {k: (d.ddim_sample(model_fn, z, k) - exact).abs().mean().item() for k in (1, 2, 8, 50, 250)}
    assert errors[1] == pytest.approx((sig * z).abs().mean().item(), rel=1e-4)  # one step gives the mean
    assert errors[1] > errors[2] > errors[8] > errors[50] > errors[250]
    assert errors[50] < 0.04 and errors[250] < 0.01  # first-order: the error falls about as 1/steps


def test_training_step_keeps_the_graph():
    d = GaussianDiffusion()
    w = torch.zeros(4, 4, requires_grad=True)
    model_fn = lambda x, t: torch.einsum("ij,bjhw->bihw", w, x)  # noqa: E731
    x0 = torch.randn(2, 4, 3, 3)
    out = d.training_step(model_fn, x0, generator=torch.Generator().manual_seed(0))
    assert set(out) >= {"loss", "x0_pred", "x_t", "t", "noise"}
    (out["loss"] + out["x0_pred"].square().mean()).backward()
    assert w.grad.abs().sum() > 0
    again = d.training_step(model_fn, x0, generator=torch.Generator().manual_seed(0))
    assert torch.equal(out["t"], again["t"]) and torch.equal(out["noise"], again["noise"])


def test_sample_timesteps_range():
    d = GaussianDiffusion()
    t = d.sample_timesteps(1000, torch.Generator().manual_seed(0), t_min=10, t_max=20)
    assert t.min() == 10 and t.max() == 20
    with pytest.raises(ToolkitError, match="timestep range"):
        d.sample_timesteps(2, t_max=1000)


@pytest.mark.parametrize("bad,match", [(dict(prediction="eps"), "zero_terminal_snr"),
                                       (dict(schedule="quadratic"), "schedule"),
                                       (dict(num_timesteps=1), "num_timesteps"),
                                       (dict(prediction="x0"), "prediction"),
                                       (dict(beta_end=1.0), "beta_end: expected a beta in"),
                                       (dict(num_timesteps=2.5), r"num_timesteps: expected an integer >= 2, got 2.5"),
                                       (dict(beta_start=0.5, beta_end=0.1),
                                        r"DiffusionConfig: need beta_start <= beta_end .*got beta_start=0.5, beta_end=0.1"),
                                       (dict(schedule="linear", beta_start=0.05),
                                        r"need beta_start <= beta_end .*got beta_start=0.05, beta_end=0.02")])
def test_bad_config(bad, match):
    with pytest.raises(ToolkitError, match=match):
        GaussianDiffusion(DiffusionConfig(**bad))


def test_ddim_refuses_a_non_finite_eta():
    d = GaussianDiffusion()
    noise = torch.randn(1, 2, 2, 2)
    for eta in (float("nan"), float("inf")):
        with pytest.raises(ToolkitError, match=r"DDIM eta: expected a finite number"):
            d.ddim_sample(lambda x, t: torch.zeros_like(x), noise, 2, eta=eta)


def test_an_explicit_zero_beta_is_used_not_replaced_by_the_default():
    betas = make_betas(DiffusionConfig(schedule="linear", beta_start=0.0, zero_terminal_snr=False))
    assert float(betas[0]) == 0.0 and float(make_betas(DiffusionConfig(schedule="linear", zero_terminal_snr=False))[0]) == 1e-4
