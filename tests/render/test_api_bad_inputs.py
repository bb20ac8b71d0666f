"""The torch splatter's public functions given what a user's own values look like (no camera, float16,
NaN or crossed clipping planes, a background as a list): one ToolkitError naming the argument."""

from __future__ import annotations

import pytest
import torch

from render.splat import rasterize, render_scene
from toolkit.errors import ToolkitError
from toolkit.procedural import demo_camera, demo_head_scene


def _gaussians(n=8):
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 2.0])
    quats = torch.tensor([1.0, 0, 0, 0]).expand(n, 4).contiguous()
    return means, quats, torch.full((n, 3), 0.05), torch.full((n,), 0.8), torch.rand(n, 3, generator=g)


def _camera():
    K = torch.tensor([[[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]]])
    return torch.eye(4)[None], K


def test_rasterize_refuses_no_camera_and_float16():
    means, quats, scales, opac, feats = _gaussians()
    V, K = _camera()
    with pytest.raises(ToolkitError, match=r"viewmats expected at least one camera"):
        rasterize(means, quats, scales, opac, feats, V[:0], K[:0], 32, 32)
    with pytest.raises(ToolkitError, match=r"means expected float32, float64 or bfloat16, got float16"):
        rasterize(means.half(), quats.half(), scales.half(), opac.half(), feats.half(), V, K, 32, 32)


@pytest.mark.parametrize("kw", [{"eps2d": float("nan")}, {"eps2d": -1.0}, {"near_plane": float("nan")},
                                {"near_plane": 5.0, "far_plane": 1.0}])
def test_rasterize_refuses_nan_or_crossed_planes(kw):
    means, quats, scales, opac, feats = _gaussians()
    with pytest.raises(ToolkitError, match=r"need a finite eps2d >= 0 and 0 <= near_plane < far_plane"):
        rasterize(means, quats, scales, opac, feats, *_camera(), 32, 32, **kw)


def test_rasterize_names_a_background_given_as_a_list():
    means, quats, scales, opac, feats = _gaussians()
    with pytest.raises(ToolkitError, match=r"backgrounds expected shape \[1, 3\], got list"):
        rasterize(means, quats, scales, opac, feats, *_camera(), 32, 32, backgrounds=[0.0, 0.0, 0.0])


def test_valid_calls_still_render():
    means, quats, scales, opac, feats = _gaussians()
    img, alpha, _ = rasterize(means, quats, scales, opac, feats, *_camera(), 32, 32, near_plane=0.0)
    assert img.shape == (1, 32, 32, 3) and float(alpha.max()) > 0
    img = render_scene(demo_head_scene(200), [demo_camera(32, 32)])[0]
    assert torch.isfinite(img).all()
