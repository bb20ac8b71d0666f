"""The latent DiT: adaLN-Zero identity at init, zero-initialized feature channels, shapes, configs, errors."""

from __future__ import annotations

import pytest
import torch

from tests.train.threads import single_thread  # noqa: F401  (autouse)
from toolkit import ToolkitError
from train.model.dit import DIT_MODELS, DiT, DiTConfig, get_2d_sincos_pos_embed, make_dit


def tiny(**kw) -> DiT:
    return make_dit("DiT-Gaze-tiny", input_size=8, **kw)


def inputs(B=2, C=4, H=8, W=8, h=16, w=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, C, H, W, generator=g), torch.randint(0, 1000, (B,), generator=g),
            torch.randn(B, 32, h, w, generator=g), torch.randn(B, 144, generator=g))


def test_blocks_are_identity_at_init():
    model = tiny()
    tokens = torch.randn(2, 16, model.config.hidden_size)
    c = torch.randn(2, model.config.hidden_size) * 3  # a nonzero conditioning vector
    for block in model.blocks:
        assert torch.equal(block(tokens, c), tokens)
    x, t, f, s = inputs()
    assert torch.equal(model(x, t, f, s), torch.zeros_like(x))  # zero final layer


def test_feature_channels_zero_at_init_then_learned():
    torch.manual_seed(0)
    model = tiny()
    C = model.config.latent_channels
    w = model.x_embedder.proj.weight
    assert torch.count_nonzero(w[:, C:]) == 0 and torch.count_nonzero(w[:, :C]) > 0
    x, t, f, s = inputs()
    f2 = torch.randn_like(f)
    # Make the rest of the network nonzero (as after some training) -- the features still cannot matter.
    with torch.no_grad():
        for p in model.parameters():
            if p is not w:
                p.add_(0.05 * torch.randn_like(p))
        w[:, :C].add_(0.05 * torch.randn_like(w[:, :C]))
    assert torch.allclose(model(x, t, f, s), model(x, t, f2, s))
    # ... but the zero weights get gradients from a loss that needs the features, and learn to use them.
    target = f[:, :4, ::2, ::2]
    opt = torch.optim.SGD(model.parameters(), lr=0.05)
    loss = ((model(x, t, f, s) - target) ** 2).mean()
    loss.backward()
    assert w.grad[:, C:].abs().sum() > 0
    assert model.feature_encoder.conv_in.weight.grad is not None
    opt.step()
    opt.zero_grad()
    assert not torch.allclose(model(x, t, f, s), model(x, t, f2, s))


@pytest.mark.parametrize("patch,grid", [(1, 8), (2, 8), (4, 8), (2, 12), (4, 16)])
def test_shapes_for_patch_sizes_and_grids(patch, grid):
    model = make_dit("DiT-Gaze-tiny", input_size=8, patch_size=patch)
    x, t, f, s = inputs(H=grid, W=grid, h=2 * grid, w=2 * grid)
    with torch.no_grad():
        model.final_layer.linear.weight.normal_()  # a nonzero output to check the unpatchify layout below
    out = model(x, t, f, s)
    assert out.shape == x.shape and torch.isfinite(out).all()


def test_unpatchify_inverts_the_patch_layout():
    model = tiny(patch_size=2)
    C, p = 4, 2
    img = torch.randn(1, C, 6, 4)
    tokens = img.reshape(1, C, 3, p, 2, p).permute(0, 2, 4, 3, 5, 1).reshape(1, 6, p * p * C)
    assert torch.equal(model.unpatchify(tokens, 3, 2), img)


def test_non_square_grid_and_pixel_space_latent():
    model = make_dit("DiT-Gaze-tiny", input_size=16, latent_channels=3, patch_size=4)
    x = torch.randn(1, 3, 16, 32)
    out = model(x, torch.tensor([3]), torch.randn(1, 32, 4, 8), torch.randn(1, 144))
    assert out.shape == x.shape


def test_pos_embed_is_fixed_sincos():
    pe = get_2d_sincos_pos_embed(64, 4, 4)
    assert pe.shape == (16, 64) and pe.abs().max() <= 1
    assert torch.unique(pe, dim=0).shape[0] == 16  # every token position distinct
    model = tiny()
    assert "pos_embed" not in model.state_dict()  # a pure function of the grid: not a learned weight
    assert torch.equal(model.pos_embed, get_2d_sincos_pos_embed(64, 4, 4))


def test_conditioning_depends_on_timestep_and_codes():
    model = tiny(gaze_dim=2, pose_dim=6)
    s = torch.randn(2, 144)
    gz, ps = torch.randn(2, 2), torch.randn(2, 6)
    c0 = model.conditioning(torch.tensor([0, 0]), s, gz, ps)
    assert not torch.allclose(c0, model.conditioning(torch.tensor([500, 500]), s, gz, ps))
    assert not torch.allclose(c0, model.conditioning(torch.tensor([0, 0]), s, gz + 0.3, ps))
    assert not torch.allclose(c0, model.conditioning(torch.tensor([0, 0]), s, gz, ps + 0.3))
    assert not torch.allclose(c0, model.conditioning(torch.tensor([0, 0]), s + 0.3, gz, ps))
    with pytest.raises(ToolkitError, match="gaze"):
        model.conditioning(torch.tensor([0, 0]), s, None, ps)


def test_named_configs():
    assert set(DIT_MODELS) >= {"DiT-Gaze-paper", "DiT-Gaze-tiny"}
    paper = make_dit("DiT-Gaze-paper", input_size=16)
    assert (paper.config.depth, paper.config.num_heads, paper.config.latent_channels) == (6, 8, 4)
    assert len(paper.blocks) == 6
    with pytest.raises(ToolkitError, match="unknown"):
        make_dit("DiT-XL/2")


@pytest.mark.parametrize("bad", [dict(hidden_size=66, num_heads=4), dict(input_size=9, patch_size=2),
                                 dict(gaze_dim=3), dict(depth=0), dict(feature_hidden=0)])
def test_bad_config(bad):
    with pytest.raises(ToolkitError, match="DiTConfig"):
        DiT(DiTConfig(**{**dict(hidden_size=64, num_heads=4, depth=1, input_size=8), **bad}))


@pytest.mark.parametrize("bad, match", [
    (dict(hidden_size=0), r"DiTConfig.hidden_size: expected a positive integer, got 0"),
    (dict(input_size=-4), r"DiTConfig.input_size: expected a positive integer, got -4"),
    (dict(num_heads=0), r"DiTConfig.num_heads: expected a positive integer, got 0"),
    (dict(mlp_ratio=-1), r"DiTConfig.mlp_ratio: expected a number > 0"),
    (dict(mlp_ratio=float("nan")), r"DiTConfig.mlp_ratio: expected a number > 0"),
    (dict(pose_dim=5), r"DiTConfig.pose_dim: expected 0 or 6 \(axis-angle \+ translation\), got 5"),
    (dict(feature_embed_channels=-1), r"DiTConfig.feature_embed_channels: expected >= 0, got -1")])
def test_bad_config_values_are_named_before_any_layer_is_built(bad, match):
    """Not a ZeroDivisionError or a negative-dimension error from torch's layers, nor (pose_dim) a matmul shape
    error at the first render."""
    with pytest.raises(ToolkitError, match=match):
        DiT(DiTConfig(**{**dict(hidden_size=64, num_heads=4, depth=1, input_size=8), **bad}))


def test_bad_inputs():
    model = tiny()
    x, t, f, s = inputs()
    with pytest.raises(ToolkitError, match="DiT input x"):
        model(x[:, :3], t, f, s)
    with pytest.raises(ToolkitError, match="patch_size"):
        model(torch.randn(2, 4, 7, 8), t, f, s)
    with pytest.raises(ToolkitError, match="feats"):
        model(x, t, f[:, :16], s)
    with pytest.raises(ToolkitError, match="shape_code"):
        model(x, t, f, s[:, :100])
    with pytest.raises(ToolkitError, match="t:"):
        model(x, t[:1], f, s)


def test_precomputed_feature_embedding_matches_and_is_checked():
    model = tiny()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    x, t, f, s = inputs()
    emb = model.encode_features(f, (8, 8))
    assert torch.equal(model(x, t, f, s, feature_embedding=emb), model(x, t, f, s))
    with pytest.raises(ToolkitError, match="feature_embedding"):
        model(x, t, f, s, feature_embedding=emb[:, :, :4])


def test_feature_hidden_sets_the_encoder_width_and_the_model_still_runs():
    m = tiny(feature_hidden=16)
    assert m.feature_encoder.conv_in.out_channels == 16 and m.feature_encoder.conv_out.in_channels == 16
    assert tiny().feature_encoder.conv_in.out_channels == 64  # the default
    x, t, feats, code = inputs()
    out = m(x, t, feats, code)
    assert out.shape == x.shape and torch.isfinite(out).all()
