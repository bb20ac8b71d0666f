"""GazeGaussian's renderer (ablation baseline): shapes, code conditioning, fitting, the shared interface."""

from __future__ import annotations

import pytest
import torch

from tests.train.threads import single_thread  # noqa: F401  (autouse)
from toolkit import ToolkitError
from train.model.baseline_renderer import AttentionPool, BaselineConfig, BaselineRenderer, blur
from train.model.renderer import make_renderer
from train.model.renderer_interface import Renderer


@pytest.mark.parametrize("upscale", [1, 2, 4, 8])
def test_output_shape_and_range(upscale):
    r = BaselineRenderer(BaselineConfig(upscale=upscale))
    img = r.render(torch.randn(2, 32, 6, 5), torch.randn(2, 144))
    assert img.shape == (2, 3, 6 * upscale, 5 * upscale)
    assert (img > 0).all() and (img < 1).all()
    assert len(r.up) == {1: 0, 2: 1, 4: 2, 8: 3}[upscale]


def test_channels_halve_to_the_floor():
    r = BaselineRenderer(BaselineConfig(feature_channels=64, min_channels=16, upscale=8))
    assert [m.conv.in_channels for m in r.up] == [64, 32, 16]
    assert [m.out_channels for m in r.feat] == [32, 16, 16]
    assert r.render(torch.randn(1, 64, 4, 4), torch.randn(1, 144)).shape == (1, 3, 32, 32)


def test_attention_pool_is_a_softmax_average_over_pixels():
    pool = AttentionPool(4, 6)
    x = torch.randn(2, 4, 3, 5)
    code = torch.randn(2, 6)
    out = pool(x, code)
    tokens = x.flatten(2).transpose(1, 2)
    w = (pool.k_proj(tokens) @ code[:, :, None] / 6**0.5).softmax(dim=1)
    pooled = (w * pool.v_proj(tokens)).sum(1)
    torch.testing.assert_close(out, x + pooled[:, :, None, None])


def test_shape_code_changes_the_image():
    r = BaselineRenderer()
    f = torch.randn(1, 32, 8, 8)
    assert not torch.allclose(r.render(f, torch.randn(1, 144)), r.render(f, torch.randn(1, 144)))


def test_blur_keeps_constants_and_sums():
    x = torch.full((1, 2, 5, 5), 0.3)
    torch.testing.assert_close(blur(x), x)
    # An impulse away from the border spreads into the [1 2 1] x [1 2 1] / 16 kernel, its sum kept.
    impulse = torch.zeros(1, 1, 7, 7)
    impulse[0, 0, 3, 3] = 1.0
    k = torch.tensor([1.0, 2.0, 1.0])
    expect = torch.zeros(1, 1, 7, 7)
    expect[0, 0, 2:5, 2:5] = torch.outer(k, k) / 16
    torch.testing.assert_close(blur(impulse), expect)


def test_it_learns_a_feature_to_image_map():
    torch.manual_seed(0)
    r = BaselineRenderer(BaselineConfig(upscale=2))
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(4, 32, 8, 8, generator=g)
    target = torch.sigmoid(torch.nn.functional.interpolate(feats[:, :3], scale_factor=2.0, mode="bilinear"))
    code = torch.randn(4, 144, generator=g)
    opt = torch.optim.Adam(r.parameters(), lr=1e-2)
    first = None
    for _ in range(40):
        out = r.training_forward(feats, code, target)
        loss = (out.image - target).abs().mean() + out.aux_loss
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first


def test_interface():
    r = make_renderer("baseline")
    assert isinstance(r, Renderer) and r.upscale == 4
    f, c = torch.randn(1, 32, 4, 4), torch.randn(1, 144)
    out = r.training_forward(f, c, torch.rand(1, 3, 16, 16), gaze=torch.zeros(1, 2), pose=torch.zeros(1, 6))
    assert out.image.shape == (1, 3, 16, 16) and out.aux_loss.item() == 0
    torch.testing.assert_close(out.image, r.render(f, c, steps=7, seed=3))  # steps/seed are ignored
    with pytest.raises(ToolkitError, match="target"):
        r.training_forward(f, c, torch.rand(1, 3, 8, 8))
    with pytest.raises(ToolkitError, match="feats"):
        r.render(torch.randn(1, 16, 4, 4), c)
    with pytest.raises(ToolkitError, match="shape_code"):
        r.render(f, torch.randn(2, 144))
    with pytest.raises(ToolkitError, match="upscale"):
        BaselineRenderer(BaselineConfig(upscale=3))
    with pytest.raises(ToolkitError, match=r"renderer feats: expected finite values, found NaN or inf"):
        r.render(torch.full_like(f, float("nan")), c)
