"""The gaussian stage's optimizer: the canonical centres train at their own, scene-scaled rate."""

import pytest
import torch

from tests.train.helpers import small_model
from toolkit.procedural import demo_head_scene
from train.model.baseline_renderer import BaselineRenderer
from train.run_config import GaussianStageConfig
from train.training.trainer import CANONICAL_MEANS, optimizer_groups


def test_optimizer_groups_cover_every_weight_once_with_scaled_centre_rate():
    model = small_model(demo_head_scene(600))
    renderer = BaselineRenderer()
    cfg = GaussianStageConfig(lr=2e-3, means_lr=1e-4, renderer_lr=5e-4)
    groups = optimizer_groups(model, renderer, cfg)
    seen = [id(p) for g in groups for p in g["params"]]
    trainable = [p for m in (model, renderer) for p in m.parameters() if p.requires_grad]
    assert sorted(seen) == sorted(id(p) for p in trainable)  # each weight exactly once
    rate = {id(p): g["lr"] for g in groups for p in g["params"]}
    for name in CANONICAL_MEANS:
        assert rate[id(getattr(model, name))] == pytest.approx(1e-4 * float(model.norm_scale))
    assert rate[id(model.face_features)] == 2e-3 and rate[id(model.face_field.expr_mlp.first.weight)] == 2e-3
    assert all(rate[id(p)] == 5e-4 for p in renderer.parameters())


def test_centres_move_at_most_their_rate_per_step():
    """Adam's first step moves each weight by ~lr whatever the gradient: the centres by means_lr × radius."""
    model = small_model(demo_head_scene(600))
    renderer = BaselineRenderer()
    cfg = GaussianStageConfig(means_lr=1e-4)
    opt = torch.optim.Adam(optimizer_groups(model, renderer, cfg))
    before = model.face_means.detach().clone()
    (model.face_means ** 2).sum().mul(1e6).backward()  # a huge gradient
    opt.step()
    step = (model.face_means.detach() - before).abs().max()
    assert 0 < float(step) <= 1.0001e-4 * float(model.norm_scale)


@pytest.mark.parametrize("fraction", [0.0, 0.5, 1.0])
def test_onestep_fraction_sets_the_share_of_the_inference_timestep(fraction):
    from types import SimpleNamespace

    from train.training.trainer import GaussianTrainer

    T = 1000
    trainer = SimpleNamespace(renderer=SimpleNamespace(diffusion=SimpleNamespace(num_timesteps=T)),
                              cfg=GaussianStageConfig(onestep_fraction=fraction), device=torch.device("cpu"))
    t = GaussianTrainer._timesteps(trainer, 4000, torch.Generator().manual_seed(0))
    share = float((t == T - 1).float().mean())
    assert t.shape == (4000,) and int(t.min()) >= 0 and int(t.max()) <= T - 1
    assert abs(share - fraction) < 0.03
    # Without a diffusion (the U-Net baseline) there is no timestep.
    assert GaussianTrainer._timesteps(SimpleNamespace(renderer=SimpleNamespace()), 4, torch.Generator()) is None


def test_lr_factor_constant_and_cosine():
    from train.training.trainer import lr_factor

    assert all(lr_factor(GaussianStageConfig(steps=10))(s) == 1.0 for s in range(12))
    f = lr_factor(GaussianStageConfig(steps=11, lr_schedule="cosine", lr_final=0.2))
    vals = [f(s) for s in range(11)]
    assert vals[0] == pytest.approx(1.0) and vals[5] == pytest.approx(0.6) and vals[10] == pytest.approx(0.2)
    assert all(a > b for a, b in zip(vals, vals[1:]))
    assert f(50) == pytest.approx(0.2)  # past the end (the time-budgeted benchmark's steps): the final factor
    one = lr_factor(GaussianStageConfig(steps=1, lr_schedule="cosine", lr_final=0.0))
    assert one(0) == pytest.approx(1.0)  # a single step trains at the configured rate


def test_the_intermediate_gaze_sampler_follows_the_trainer_seed():
    """Each run seed draws its own intermediate gazes (not seed 0's for every seed)."""
    from train.training.trainer import GaussianTrainer

    model, renderer = small_model(demo_head_scene(300)), BaselineRenderer()
    estimator = torch.nn.Linear(2, 2)

    def draws(seed):
        t = GaussianTrainer(GaussianStageConfig(), model, renderer, estimator, None, torch.device("cpu"), 10,
                            seed=seed)
        return t.sampler.sample(8, progress=1.0)

    assert torch.equal(draws(1), draws(1))
    assert not torch.allclose(draws(0), draws(1))


def test_the_papers_step_decay():
    """GazeGaussian trainer/gazegaussian_trainer.py L141-143: lr_func = 0.1 ** (epoch / step_decay)."""
    from train.training.trainer import lr_factor

    f = lr_factor(GaussianStageConfig(steps=5000, lr_schedule="step", lr_decay_steps=1000))
    assert f(0) == 1.0 and f(1000) == pytest.approx(0.1) and f(500) == pytest.approx(0.1 ** 0.5)
    assert f(3000) == pytest.approx(1e-3)


def test_the_perceptual_term_trains_with_the_users_vgg_weights(tmp_path):
    """gaussian.vgg_path turns the image loss's VGG16 term on at lambda_perceptual; without it the term is off."""
    from tests.train.losses.test_losses import _fake_torchvision_vgg16_state
    from train.training.trainer import GaussianTrainer

    path = tmp_path / "vgg16.pth"
    torch.save(_fake_torchvision_vgg16_state(), path)
    model, renderer = small_model(demo_head_scene(300)), BaselineRenderer()
    make = lambda **kw: GaussianTrainer(GaussianStageConfig(**kw), model, renderer, torch.nn.Linear(2, 2), None,  # noqa: E731
                                        torch.device("cpu"), 10)
    on, off = make(vgg_path=str(path), lambda_perceptual=0.3).image_loss, make().image_loss
    assert on.perceptual_enabled and on.config.lambda_perceptual == 0.3 and not off.perceptual_enabled
    a, b = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    masks = {r: torch.ones(2, 1, 32, 32) for r in ("head", "face", "eyes")}
    total_on, logs = on(a, b, masks)
    total_off, _ = off(a, b, masks)
    assert float(total_on) > float(total_off) and any("perceptual" in k and v > 0 for k, v in logs.items())
