"""Region image loss, gaze loss, orthogonality loss and the project's VGG16 loader."""

from __future__ import annotations

import logging

import pytest
import torch
import torch.nn as nn

import train.losses.image as losses_mod
from toolkit.errors import ToolkitError
from train.losses import (
    GazeLoss,
    ImageLoss,
    ImageLossConfig,
    OrthogonalityLoss,
    composite_on_white,
    gaze_to_camera,
)
from train.losses.vgg import PERCEPTUAL_LAYERS, VGG16Features, load_vgg16


def _images(b=2, h=32, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, h, w, generator=g), torch.rand(b, 3, h, w, generator=g)


def _box_mask(b, h, w, r0, r1, c0, c1):
    m = torch.zeros(b, 1, h, w)
    m[:, :, r0:r1, c0:c1] = 1
    return m


# ----------------------------------------------------------------------------- image loss
def test_identical_images_give_zero_loss():
    a, _ = _images()
    m = _box_mask(2, 32, 32, 4, 28, 4, 28)
    loss, logs = ImageLoss()(a, a.clone(), {"head": m, "face": m, "eyes": m})
    assert float(loss) == pytest.approx(0.0, abs=1e-5)
    assert logs["head/l1"] == pytest.approx(0.0, abs=1e-6)


def test_pixels_outside_the_region_do_not_count():
    a, b = _images()
    m = _box_mask(2, 32, 32, 8, 24, 8, 24)
    b2 = b.clone()
    b2[:, :, 8:24, 8:24] = a[:, :, 8:24, 8:24]  # equal inside the region, different outside
    loss = ImageLoss().region_loss(a, b2, m)
    assert float(loss["l1"]) == pytest.approx(0.0, abs=1e-6)
    # SSIM windows straddle the border but both sides see white outside: still ~ 0.
    assert float(loss["ssim"]) < 1e-4
    assert float(ImageLoss().region_loss(a, b, m)["l1"]) > 0.1


def test_l1_is_averaged_over_the_region_area():
    a = torch.zeros(1, 3, 32, 32)
    b = torch.ones(1, 3, 32, 32) * 0.5
    small, big = _box_mask(1, 32, 32, 0, 4, 0, 4), _box_mask(1, 32, 32, 0, 32, 0, 32)
    ls = ImageLoss().region_loss(a, b, small)["l1"]
    lb = ImageLoss().region_loss(a, b, big)["l1"]
    assert float(ls) == pytest.approx(0.5, abs=1e-5) and float(lb) == pytest.approx(0.5, abs=1e-5)


def test_composite_on_white():
    img = torch.zeros(1, 3, 4, 4)
    m = _box_mask(1, 4, 4, 0, 2, 0, 4)
    out = composite_on_white(img, m)
    assert torch.equal(out[:, :, :2], torch.zeros(1, 3, 2, 4)) and torch.equal(out[:, :, 2:], torch.ones(1, 3, 2, 4))


def test_ssim_term_and_weights_combine():
    a, b = _images()
    m = torch.ones(2, 1, 32, 32)
    cfg = ImageLossConfig(lambda_l1=2.0, lambda_ssim=0.5, lambda_perceptual=0.0)
    r = ImageLoss(cfg).region_loss(a, b, m)
    assert 0 < float(r["ssim"]) <= 2
    assert float(r["total"]) == pytest.approx(2 * float(r["l1"]) + 0.5 * float(r["ssim"]), rel=1e-5)


def test_low_resolution_prediction_is_compared_with_downsampled_target():
    target = torch.rand(1, 3, 32, 32)
    pred = torch.nn.functional.interpolate(target, size=(8, 8), mode="area")
    m = torch.ones(1, 1, 32, 32)
    assert float(ImageLoss().region_loss(pred, target, m)["l1"]) < 1e-6


def test_per_region_predictions_and_zero_weights_skip_regions():
    a, b = _images()
    m = torch.ones(2, 1, 32, 32)
    loss_fn = ImageLoss()
    # A zero-weight region needs neither a mask nor a prediction.
    total, logs = loss_fn({"face": a}, b, {"face": m}, weights={"head": 0.0, "eyes": 0.0})
    assert set(k.split("/")[0] for k in logs) == {"face", "image"}
    assert float(total) == pytest.approx(float(loss_fn.region_loss(a, b, m)["total"]), rel=1e-6)
    with pytest.raises(ToolkitError, match="masks has no 'eyes'"):
        loss_fn(a, b, {"face": m, "head": m})
    with pytest.raises(ToolkitError, match="unknown region"):
        loss_fn(a, b, {"face": m}, weights={"mouth": 1.0})


def test_gradient_reaches_the_prediction_only_inside_the_region():
    a, b = _images()
    a.requires_grad_(True)
    m = _box_mask(2, 32, 32, 10, 20, 10, 20)
    ImageLoss().region_loss(a, b, m)["total"].backward()
    g = a.grad.abs().sum(1)
    assert torch.isfinite(a.grad).all()
    assert float(g[:, 10:20, 10:20].sum()) > 0
    assert float(g.sum() - g[:, 10:20, 10:20].sum()) == 0.0


def test_bad_shapes_raise():
    a, b = _images()
    with pytest.raises(ToolkitError, match="mask"):
        ImageLoss().region_loss(a, b, torch.ones(2, 1, 16, 16))
    with pytest.raises(ToolkitError, match="pred"):
        ImageLoss().region_loss(a[:, :1], b, torch.ones(2, 1, 32, 32))


def test_perceptual_disabled_without_weights_is_logged_once(caplog, monkeypatch):
    monkeypatch.setattr(losses_mod, "_perceptual_off_logged", False)
    with caplog.at_level(logging.WARNING, logger="train.losses.image"):
        ImageLoss()
        ImageLoss()
    msgs = [r.message for r in caplog.records if "perceptual loss disabled" in r.message]
    assert len(msgs) == 1
    assert not ImageLoss().perceptual_enabled


# ----------------------------------------------------------------------------- VGG16
def _fake_torchvision_vgg16_state(seed=0):
    """A state dict in torchvision's VGG16 layout (random weights; plus classifier keys that must be ignored)."""
    torch.manual_seed(seed)
    feats = VGG16Features().features.state_dict()
    state = {f"features.{k}": torch.randn_like(v) * 0.05 for k, v in feats.items()}
    state["classifier.0.weight"] = torch.zeros(4, 4)
    return state


def test_vgg16_layout_matches_torchvision_names():
    names = set(VGG16Features().features.state_dict())
    convs = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]
    assert names == {f"{i}.{p}" for i in convs for p in ("weight", "bias")}
    assert PERCEPTUAL_LAYERS == (3, 8, 15, 22)


@pytest.mark.parametrize("ext", [".pth", ".safetensors"])
def test_vgg16_loads_local_weights_and_enables_perceptual_term(tmp_path, ext):
    state = _fake_torchvision_vgg16_state()
    path = tmp_path / f"vgg16{ext}"
    if ext == ".pth":
        torch.save(state, path)
    else:
        from toolkit.io import save_tensors

        save_tensors(path, state)
    vgg = load_vgg16(path)
    assert torch.equal(vgg.features[28].bias, state["features.28.bias"])
    assert not any(p.requires_grad for p in vgg.parameters())
    loss_fn = ImageLoss(ImageLossConfig(vgg_path=str(path)))
    assert loss_fn.perceptual_enabled
    a, b = _images()
    a.requires_grad_(True)
    m = torch.ones(2, 1, 32, 32)
    r = loss_fn.region_loss(a, b, m)
    assert float(r["perceptual"].detach()) > 0
    r["total"].backward()
    assert torch.isfinite(a.grad).all() and float(a.grad.abs().sum()) > 0
    assert float(loss_fn.region_loss(b, b, m)["perceptual"]) == pytest.approx(0.0, abs=1e-6)


def test_vgg16_bad_files_raise(tmp_path):
    with pytest.raises(ToolkitError, match="no such"):
        load_vgg16(tmp_path / "missing.pth")
    state = _fake_torchvision_vgg16_state()
    del state["features.10.weight"]
    torch.save(state, tmp_path / "partial.pth")
    with pytest.raises(ToolkitError, match="features.10.weight"):
        load_vgg16(tmp_path / "partial.pth")
    state = _fake_torchvision_vgg16_state()
    state["features.0.weight"] = torch.zeros(64, 1, 3, 3)
    torch.save(state, tmp_path / "wrong.pth")
    with pytest.raises(ToolkitError, match="shape"):
        load_vgg16(tmp_path / "wrong.pth")
    (tmp_path / "garbage.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(ToolkitError, match="weights-only"):
        load_vgg16(tmp_path / "garbage.pth")


# ----------------------------------------------------------------------------- gaze loss
class _GazeFromMean(nn.Module):
    """A tiny deterministic 'estimator': gaze = affine map of the image's per-channel means."""

    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(3, 4)
        torch.nn.init.normal_(self.lin.weight, std=0.5)

    def forward(self, x):
        return self.lin(x.mean(dim=(2, 3)))


def test_gaze_loss_is_angular_error_and_estimator_is_frozen():
    est = _GazeFromMean()
    gl = GazeLoss(est)
    gl.train()
    assert not est.training and not any(p.requires_grad for p in est.parameters())
    a, b = _images()
    render = a.clone().requires_grad_(True)
    loss = gl(render, target_image=b)
    from toolkit.rotations import angular_error_deg

    expect = angular_error_deg(est(a)[:, :2], est(b)[:, :2]).mean()
    assert float(loss.detach()) == pytest.approx(float(expect.detach()), rel=1e-5)
    loss.backward()
    assert torch.isfinite(render.grad).all() and float(render.grad.abs().sum()) > 0
    assert all(p.grad is None for p in est.parameters())


def test_gaze_loss_with_target_gaze_and_zero_error_gradient_is_finite():
    est = _GazeFromMean()
    gl = GazeLoss(est)
    a, _ = _images()
    render = a.clone().requires_grad_(True)
    target = est(a)[:, :2].detach()
    loss = gl(render, target_gaze=target)
    assert float(loss.detach()) < 1e-2
    loss.backward()
    assert torch.isfinite(render.grad).all()
    with pytest.raises(ToolkitError, match="exactly one"):
        gl(render)
    with pytest.raises(ToolkitError, match="target_gaze"):
        gl(render, target_gaze=torch.zeros(2, 3))


def test_gaze_to_camera_frame():
    from toolkit.eyes import gaze_rotation

    phi = torch.tensor([[0.2, -0.3], [0.0, 0.0]])
    assert torch.allclose(gaze_to_camera(phi, torch.eye(3).expand(2, 3, 3)), phi, atol=1e-6)
    # A head turned by yaw 0.4 (a rotation about the vertical axis) adds 0.4 to a level gaze's yaw.
    R = gaze_rotation(torch.tensor([[0.0, 0.4]])).expand(2, 3, 3)
    out = gaze_to_camera(torch.tensor([[0.0, 0.1], [0.0, -0.2]]), R)
    assert torch.allclose(out, torch.tensor([[0.0, 0.5], [0.0, 0.2]]), atol=1e-6)


# ----------------------------------------------------------------------------- orthogonality loss
class _ThreeMLPs(nn.Module):
    """Stand-in for the model's three fields: an upstream learnable code feeding per-Gaussian MLPs."""

    def __init__(self, width=16):
        super().__init__()
        self.code = nn.Parameter(torch.randn(2, 8))  # upstream (auto-decoder code): must get no gradient
        self.gaze_mlp = nn.Sequential(nn.Linear(10, width), nn.ReLU(), nn.Linear(width, 3))
        self.pose_mlp = nn.Sequential(nn.Linear(9, width), nn.ReLU(), nn.Linear(width, 3))
        self.expr_mlp = nn.Sequential(nn.Linear(11, width), nn.ReLU(), nn.Linear(width, 3))

    def forward(self, gaze, pose, pts):
        B, N = gaze.shape[0], pts.shape[0]
        code = self.code[:B]
        g = self.gaze_mlp(torch.cat([gaze[:, None].expand(B, 2, 2), code[:, None].expand(B, 2, 8)], -1))  # per eye
        p = self.pose_mlp(torch.cat([pts[None].expand(B, N, 3), pose[:, None].expand(B, N, 6)], -1))
        e = self.expr_mlp(torch.cat([pts[None].expand(B, N, 3), code[:, None].expand(B, N, 8)], -1))
        return g.sum() + p.sum() + e.sum()


def _three(seed=0):
    torch.manual_seed(seed)
    m = _ThreeMLPs()
    ortho = OrthogonalityLoss(m.gaze_mlp[0], m.pose_mlp[0], m.expr_mlp[0])
    gaze, pose, pts = torch.randn(2, 2), torch.randn(2, 6), torch.randn(50, 3)
    return m, ortho, (gaze, pose, pts)


def test_orthogonality_gradient_reaches_exactly_the_first_layers():
    m, ortho, inputs = _three()
    m(*inputs)
    loss = ortho()
    assert float(loss.detach()) > 0
    loss.backward()
    first = {id(m.gaze_mlp[0].weight), id(m.gaze_mlp[0].bias), id(m.pose_mlp[0].weight), id(m.pose_mlp[0].bias),
             id(m.expr_mlp[0].weight), id(m.expr_mlp[0].bias)}
    for name, p in m.named_parameters():
        if id(p) in first:
            assert p.grad is not None and torch.isfinite(p.grad).all() and float(p.grad.abs().sum()) > 0, name
        else:
            assert p.grad is None, f"{name} must not receive gradient from the orthogonality loss"


def test_orthogonality_pooling_is_the_mean_of_first_layer_outputs():
    m, ortho, (gaze, pose, pts) = _three()
    m(gaze, pose, pts)
    B, N = 2, pts.shape[0]
    x = torch.cat([pts[None].expand(B, N, 3), m.code[:B, None].expand(B, N, 8)], -1)
    expect = m.expr_mlp[0](x).mean(1)
    assert torch.allclose(ortho.pooled("expr"), expect, atol=1e-5)
    c1, c2 = ortho.cosines()
    vg, vp = ortho.pooled("gaze"), ortho.pooled("pose")
    assert torch.allclose(c1, torch.cosine_similarity(vg, expect, dim=-1), atol=1e-5)
    assert torch.allclose(c2, torch.cosine_similarity(vp, expect, dim=-1), atol=1e-5)
    assert float(ortho().detach()) == pytest.approx(float((c1.abs() + c2.abs()).mean().detach()), rel=1e-6)


def test_minimizing_orthogonality_alone_drives_cosines_to_zero():
    m, ortho, inputs = _three(seed=3)
    m(*inputs)
    c1, c2 = (c.detach() for c in ortho.cosines())
    assert float(c1.abs().mean() + c2.abs().mean()) > 0.1  # starts clearly non-orthogonal
    params = [p for layer in ortho.layers.values() for p in layer.parameters()]
    opt = torch.optim.Adam(params, lr=1e-2)
    # |cos| has a kink at 0: a decaying step lets Adam settle there instead of hovering around it.
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.985)
    for _ in range(300):
        opt.zero_grad()
        m(*inputs)
        ortho().backward()
        opt.step()
        sched.step()
    m(*inputs)
    c1, c2 = (c.detach() for c in ortho.cosines())
    assert float(c1.abs().max()) < 0.01 and float(c2.abs().max()) < 0.01


def test_orthogonality_errors_and_removal():
    m = _ThreeMLPs()
    with pytest.raises(ToolkitError, match="widths"):
        OrthogonalityLoss(m.gaze_mlp[0], nn.Linear(9, 7), m.expr_mlp[0])
    with pytest.raises(ToolkitError, match="nn.Linear"):
        OrthogonalityLoss(m.gaze_mlp, m.pose_mlp[0], m.expr_mlp[0])
    ortho = OrthogonalityLoss(m.gaze_mlp[0], m.pose_mlp[0], m.expr_mlp[0])
    with pytest.raises(ToolkitError, match="run the model forward"):
        ortho()
    ortho.remove()
    m(torch.randn(2, 2), torch.randn(2, 6), torch.randn(5, 3))
    assert not ortho.inputs


def test_orthogonality_zero_activations_have_finite_gradient():
    m, ortho, (gaze, pose, pts) = _three()
    for lin in ortho.layers.values():
        nn.init.zeros_(lin.weight)
        nn.init.zeros_(lin.bias)
    m(gaze, pose, pts)
    loss = ortho()
    loss.backward()
    assert torch.isfinite(loss)
    for lin in ortho.layers.values():
        assert torch.isfinite(lin.weight.grad).all()
