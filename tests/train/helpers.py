"""Small shared pieces of the train/ tests: a tiny model on the procedural head, inputs, the rasterizer."""

from __future__ import annotations

import torch

from toolkit.procedural import demo_camera
from train.gaussian_model import GaussianModel, GaussianModelConfig


def rasterizer_for_tests():
    """``render.splat.rasterize`` (the project's torch splatter); TEMPORARY stand-in until branch splat lands."""
    try:
        from render.splat import rasterize

        return rasterize
    except ImportError:
        return _standin


def _standin(means, quats, scales, opacities, features, viewmats, Ks, width, height, *, backgrounds=None):
    renders, alphas = [], []
    ii, jj = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    px = torch.stack([jj.flatten(), ii.flatten()], -1)
    for c in range(viewmats.shape[0]):
        p = means @ viewmats[c, :3, :3].T + viewmats[c, :3, 3]
        z = p[:, 2].clamp_min(1e-4)
        uv = torch.stack([Ks[c, 0, 0] * p[:, 0] / z + Ks[c, 0, 2], Ks[c, 1, 1] * p[:, 1] / z + Ks[c, 1, 2]], -1)
        sigma = (Ks[c, 0, 0] * scales.mean(-1) / z).clamp_min(0.3)
        order = torch.argsort(z.detach())
        d2 = ((px[:, None] - uv[None]) ** 2).sum(-1)
        a = (opacities[None] * torch.exp(-0.5 * d2 / sigma[None] ** 2)).clamp(max=0.99)[:, order]
        T = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), 1 - a[:, :-1]], 1), 1)
        w = a * T
        bg = backgrounds.reshape(-1)[-features.shape[1]:] if backgrounds is not None else features.new_zeros(features.shape[1])
        alpha = w.sum(1, keepdim=True)
        img = w @ features[order] + (1 - alpha) * bg.reshape(1, -1)
        renders.append(img.reshape(height, width, -1))
        alphas.append(alpha.reshape(height, width, 1))
    return torch.stack(renders), torch.stack(alphas), {}


def small_model(scene, **overrides) -> GaussianModel:
    cfg = GaussianModelConfig(hidden=32, depth=3, **overrides)
    torch.manual_seed(0)
    return GaussianModel.from_scene(scene, cfg, rasterizer=rasterizer_for_tests())


def model_inputs(batch: int, seed: int = 0, width: int = 64, height: int = 64):
    """(code [B, 144], pose [B, 6] zeros, gaze [B, 2], viewmats [B, 4, 4], Ks [B, 3, 3]) for a frontal camera."""
    g = torch.Generator().manual_seed(seed)
    code = torch.randn(batch, 144, generator=g) * 0.5
    pose = torch.zeros(batch, 6)
    gaze = (torch.rand(batch, 2, generator=g) - 0.5) * 0.6
    cam = demo_camera(width, height)
    return code, pose, gaze, cam.viewmat.expand(batch, 4, 4).clone(), cam.K.expand(batch, 3, 3).clone()
