"""The GPU path of ``render.splat.rasterize`` through gsplat.

On CPU: when it is chosen, and that ``rasterize_gsplat`` maps the call onto gsplat's (batch axes, backgrounds,
depth channel, meta) -- checked with a stand-in for ``gsplat.rasterization`` that renders each of its images
with the torch path, so the mapped call must give the torch path's own result.
On CUDA with gsplat installed: gsplat and the torch path agree on image, alpha and gradients, within the
tolerances gsplat's own tests allow between its CUDA kernels and its torch reference (gsplat
tests/test_basic.py, ``test_rasterize_to_pixels``: means2d 5e-3, colors 1e-3, opacities 8e-3 rtol / 6e-3 atol;
its eval3d test allows alpha_threshold + 5e-3 where one side skips a pixel the other draws).
"""

from __future__ import annotations

import pytest
import torch

import render.gsplat_backend as gb
from render.splat import rasterize
from tests.render import dense_reference as ref
from toolkit.errors import ToolkitError


def test_cpu_tensors_take_the_torch_path(monkeypatch):
    means = torch.zeros(4, 3)
    for choice in ("auto", "gsplat", "torch"):
        monkeypatch.setenv(gb.ENV, choice)
        assert not gb.use_gsplat(means, torch.zeros(4, 3), None)
    monkeypatch.setenv(gb.ENV, "cuda-please")
    with pytest.raises(ToolkitError, match=r"^environment variable DITGAZE_SPLAT: expected auto, torch or gsplat"):
        gb.use_gsplat(means, torch.zeros(4, 3), None)


def _stand_in(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, backgrounds=None,
              render_mode="RGB", sh_degree=None, near_plane, far_plane, eps2d, tile_size, packed):
    """gsplat.rasterization's shapes ([B, C, ...] batches or [C, ...]), rendered by the torch path."""
    assert packed is False
    if viewmats.dim() == 4:  # a batch of per-camera sets, one camera each
        outs = [_stand_in(means[b], quats[b], scales[b], opacities[b], colors[b], viewmats[b], Ks[b], width, height,
                          backgrounds=None if backgrounds is None else backgrounds[b], render_mode=render_mode,
                          sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
                          tile_size=tile_size, packed=packed) for b in range(viewmats.shape[0])]
        return (torch.stack([o[0] for o in outs]), torch.stack([o[1] for o in outs]),
                {k: torch.stack([o[2][k] for o in outs]) for k in ("radii", "means2d", "depths", "conics")})
    depth = render_mode == "RGB+D"
    bg = None if backgrounds is None else backgrounds[..., :colors.shape[-1] if sh_degree is None else 3]
    img, alpha, meta = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                 backgrounds=bg, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
                                 tile_size=tile_size, sh_degree=sh_degree, return_depth=depth)
    return (torch.cat([img, meta["depth"]], -1) if depth else img), alpha, meta


@pytest.mark.parametrize("per_camera", [False, True])
@pytest.mark.parametrize("depth", [False, True])
def test_the_call_is_mapped_onto_gsplats(monkeypatch, per_camera, depth):
    monkeypatch.setattr(gb, "_gsplat_rasterization", lambda: _stand_in)
    means, quats, scales, opac, feats = ref.random_cloud(60, 5, seed=3)
    V, K = ref.camera(24, 20)
    V, K = torch.cat([V, ref.camera(24, 20, yaw=0.3)[0]]), torch.cat([K, K])
    bg = torch.rand(2, 5)
    args = (means, quats, scales, opac, feats)
    if per_camera:
        args = tuple(torch.stack([a, a.flip(0)]) for a in args)
    want = rasterize(*args, V, K, 24, 20, backgrounds=bg, return_depth=depth)
    got = gb.rasterize_gsplat(*args, V, K, 24, 20, backgrounds=bg, per_camera=per_camera, near_plane=0.01,
                              far_plane=1e10, eps2d=0.3, tile_size=8, sh_degree=None, return_depth=depth)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    for k in ("radii", "means2d", "depths", "conics") + (("depth",) if depth else ()):
        assert torch.equal(got[2][k], want[2][k]), k
    assert got[2]["backend"] == "gsplat"


def _gsplat_or_skip():
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    if gb._gsplat_rasterization() is None:
        pytest.skip("needs gsplat (the optional extra 'gsplat')")


@pytest.mark.gpu
@pytest.mark.parametrize("per_camera", [False, True])
def test_gsplat_agrees_with_the_torch_path(monkeypatch, per_camera):
    _gsplat_or_skip()
    # Opacities below 0.99: gsplat clamps alpha at 0.999, the torch path at 0.99 (render/gsplat_backend.py).
    means, quats, scales, opac, feats = ref.random_cloud(400, 8, seed=11, opacity=(0.2, 0.9))
    V, K = ref.camera(64, 48)
    V, K = torch.cat([V, ref.camera(64, 48, yaw=0.25)[0]]), torch.cat([K, K])
    base = (means, quats, scales, opac, feats)
    if per_camera:
        base = tuple(torch.stack([a, a.flip(0)]) for a in base)
    bg = torch.rand(2, 8)
    runs = {}
    for choice in ("torch", "gsplat"):
        monkeypatch.setenv(gb.ENV, choice)
        params = [t.cuda().requires_grad_(True) for t in base]
        img, alpha, meta = rasterize(*params, V.cuda(), K.cuda(), 64, 48, backgrounds=bg.cuda())
        assert (meta.get("backend") == "gsplat") == (choice == "gsplat")
        g = torch.Generator(device="cuda").manual_seed(0)
        w_img, w_alpha = torch.randn(img.shape, generator=g, device="cuda"), torch.randn(alpha.shape, generator=g,
                                                                                        device="cuda")
        grads = torch.autograd.grad((img * w_img).sum() + (alpha * w_alpha).sum(), params)
        runs[choice] = (img.detach(), alpha.detach(), grads)
    (ti, ta, tg), (gi, ga, gg) = runs["torch"], runs["gsplat"]
    band = 1 / 255 + 5e-3
    assert (ti - gi).abs().max() <= band and (ta - ga).abs().max() <= band
    assert (ti - gi).abs().mean() <= 1e-4 and (ta - ga).abs().mean() <= 1e-4
    for name, a, b in zip(("means", "quats", "scales", "opacities", "features"), tg, gg):
        rel = float((a - b).norm() / a.norm().clamp_min(1e-12))
        assert rel <= 1e-2, f"{name}: relative gradient difference {rel:.3g}"
