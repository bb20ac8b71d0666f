"""Stress tests of the two-stream model, the losses and the gaze estimator: bf16 autocast on CPU, ±89° gazes,
zero and huge codes, a batch of 1, empty masks, tiny images, seed determinism. Finite outputs and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from tests.train.helpers import model_inputs, small_model
from toolkit.procedural import demo_head_scene
from train.estimator.config import GazeEstimatorConfig
from train.estimator.network import GazeEstimator
from train.losses import GazeLoss, ImageLoss, OrthogonalityLoss

TINY_EST = GazeEstimatorConfig(input_size=32, channels=(8, 16), hidden=16)


@pytest.fixture(scope="module")
def scene():
    return demo_head_scene(500)


def _nonzero_fields(model):
    # Zero-initialized last layers would hide non-finite gradients upstream; make every path live.
    g = torch.Generator().manual_seed(5)
    mlps = [model.face_field.expr_mlp, model.face_field.pose_mlp, model.eye_field.mlp]
    if model.eye_appearance is not None:
        mlps.append(model.eye_appearance.mlp)
    for mlp in mlps:
        mlp.last.weight.data = torch.randn(mlp.last.weight.shape, generator=g) * 0.1
    return model


def _check_grads(model):
    """Every trainable weight got a gradient (a detached stream would leave some None), and all are finite."""
    grads = {name: p.grad for name, p in model.named_parameters() if p.requires_grad}
    assert grads and not [n for n, g in grads.items() if g is None], [n for n, g in grads.items() if g is None]
    assert not [n for n, g in grads.items() if not torch.isfinite(g).all()]


def _full_step(model, code, pose, gaze, viewmats, Ks, size=64, autocast=False):
    est = GazeEstimator(TINY_EST)
    ortho = OrthogonalityLoss(*model.orthogonality_layers())
    target = torch.rand(code.shape[0], 3, size, size)
    masks = {k: torch.ones(code.shape[0], 1, size, size) for k in ("head", "face", "eyes")}
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        out = model(code, pose, gaze, viewmats, Ks, size, size)
        img_loss, _ = ImageLoss()({"head": out["rgb"], "face": out["face"][:, :3], "eyes": out["eyes"][:, :3]}, target, masks)
        up = torch.nn.functional.interpolate(out["rgb"].float(), size=(size, size), mode="bilinear")
        loss = img_loss + GazeLoss(est)(up, target_gaze=gaze) + 0.1 * ortho()
    for k, v in out.items():
        assert torch.isfinite(v).all(), k
    assert torch.isfinite(loss)
    loss.backward()
    _check_grads(model)
    ortho.remove()
    return out


@pytest.mark.parametrize("eyes", ["free", "eye_appearance", "eyeball_colours"])
def test_bf16_autocast_forward_backward(scene, eyes):
    model = _nonzero_fields(small_model(scene, **({} if eyes == "free" else {eyes: True})))
    code, pose, gaze, viewmats, Ks = model_inputs(2)
    pose[:, :3] = torch.tensor([0.1, -0.2, 0.05])
    _full_step(model, code, pose, gaze, viewmats, Ks, autocast=True)
    if eyes != "free":  # the image loss reaches every weight of the eyes' colours (finite: _check_grads)
        assert all(p.grad is not None for p in getattr(model, eyes).parameters())


@pytest.mark.parametrize("value", [0.0, 1e4, -1e4])
def test_eyeball_colours_at_extreme_values_and_gazes(scene, value):
    """Saturated colour logits, edge angles far out of their bounds and ±89° gazes: finite renders and gradients."""
    model = _nonzero_fields(small_model(scene, eyeball_colours=True))
    with torch.no_grad():
        for p in model.eyeball_colours.parameters():
            p.fill_(value)
    code, pose, _, viewmats, Ks = model_inputs(4)
    r = math.radians(89.0)
    gaze = torch.tensor([[r, 0.0], [0.0, -r], [r, r], [-r, r]], requires_grad=True)
    _full_step(model, code, pose, gaze, viewmats, Ks)
    assert torch.isfinite(gaze.grad).all()


@pytest.mark.parametrize("deg", [89.0, -89.0])
def test_extreme_gazes(scene, deg):
    model = _nonzero_fields(small_model(scene))
    code, pose, _, viewmats, Ks = model_inputs(4)
    r = math.radians(deg)
    gaze = torch.tensor([[r, 0.0], [0.0, r], [r, r], [-r, r]], requires_grad=True)
    out = _full_step(model, code, pose, gaze, viewmats, Ks)
    assert out["eyes_alpha"].shape[0] == 4
    assert torch.isfinite(gaze.grad).all()


@pytest.mark.parametrize("eye_appearance", [False, True])
@pytest.mark.parametrize("scale", [0.0, 1e6])
def test_zero_and_huge_codes(scene, scale, eye_appearance):
    model = _nonzero_fields(small_model(scene, eye_appearance=eye_appearance))
    _, pose, gaze, viewmats, Ks = model_inputs(2)
    code = torch.ones(2, 144) * scale
    code[1] = -code[1]
    out = _full_step(model, code, pose, gaze, viewmats, Ks)
    # Bounded deltas: even a huge code moves Gaussians by at most max_offset of the head radius.
    g = model.gaussians(code, pose, gaze)
    shift = (g["face"]["means"][0] - model.face_means).abs().max()
    assert float(shift.detach()) <= model.config.max_offset * float(model.norm_scale) + 1e-6
    assert out["head"].abs().max() < 100
    eye_shift = (g["eyes"]["features"] - model.eye_features).abs().max()
    assert float(eye_shift.detach()) <= (model.config.max_feature_delta + 1e-6 if eye_appearance else 0.0)


def test_batch_of_one_and_huge_pose(scene):
    model = _nonzero_fields(small_model(scene))
    code, pose, gaze, viewmats, Ks = model_inputs(1)
    _full_step(model, code, pose, gaze, viewmats, Ks)
    model.zero_grad()
    pose = torch.tensor([[3.0, -3.0, 2.0, 0.0, 0.0, 0.0]])  # a head turned away: few or no visible Gaussians
    _full_step(model, code, pose, gaze, viewmats, Ks)


def test_seed_determinism(scene):
    """The same seed gives the same render; another seed another one (the zero-initialized last layers are
    made live first, else every seed would render alike)."""
    code, pose, gaze, viewmats, Ks = model_inputs(2, seed=7)
    outs = []
    for seed in (11, 11, 12):
        model = _nonzero_fields(small_model(scene, seed=seed))
        with torch.no_grad():
            outs.append(model(code, pose, gaze, viewmats, Ks, 64, 64)["head"])
    assert torch.equal(outs[0], outs[1])
    assert not torch.allclose(outs[0], outs[2], atol=1e-4)


def test_losses_with_empty_masks_and_tiny_images():
    loss_fn = ImageLoss()
    pred = torch.rand(2, 3, 4, 4, requires_grad=True)
    target = torch.rand(2, 3, 4, 4)
    empty = torch.zeros(2, 1, 4, 4)
    r = loss_fn.region_loss(pred, target, empty)
    assert float(r["total"].detach()) == 0.0
    r = loss_fn.region_loss(pred, target, torch.ones(2, 1, 4, 4))  # smaller than the SSIM window
    r["total"].backward()
    assert torch.isfinite(pred.grad).all()
    pred1 = torch.zeros(1, 3, 8, 8, requires_grad=True)  # batch of one, all-black
    with torch.autocast("cpu", dtype=torch.bfloat16):
        total, _ = loss_fn(pred1, torch.ones(1, 3, 8, 8), {k: torch.ones(1, 1, 8, 8) for k in ("head", "face", "eyes")})
    assert total.dtype == torch.float32
    total.backward()
    assert torch.isfinite(pred1.grad).all()


@pytest.mark.parametrize("fill", [0.0, 1.0, None])
def test_estimator_bf16_and_degenerate_images(fill):
    torch.manual_seed(0)
    est = GazeEstimator(TINY_EST)
    x = torch.rand(1, 3, 40, 40) if fill is None else torch.full((1, 3, 40, 40), fill)
    x.requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = est(x)
    assert torch.isfinite(y).all()
    y.float().sum().backward()
    assert torch.isfinite(x.grad).all()
    for p in est.parameters():
        assert torch.isfinite(p.grad).all()
