"""An independent, naive dense 3DGS reference for the tests: every pixel x every Gaussian, plain autograd.

Written from the stated conventions (the ``render.splat`` module docstring), not from render/'s code;
deliberately slow and obvious.
"""

from __future__ import annotations

import math

import torch


def quat_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def project(means, quats, scales, viewmat, K, width, height, eps2d=0.3, near=0.01, far=1e10):
    """One camera -> (means2d [N, 2], conics [N, 3], depths [N], valid [N] bool, cov2d [N, 2, 2])."""
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ Rw.T + tw
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ok = (z > near) & (z < far)
    zs = torch.where(ok, z, torch.ones_like(z))
    u = fx * x / zs + K[0, 1] * y / zs + cx
    v = fy * y / zs + cy
    limx = (float(-(cx / fx) - 0.3 * width / 2 / fx), float((width - cx) / fx + 0.3 * width / 2 / fx))
    limy = (float(-(cy / fy) - 0.3 * height / 2 / fy), float((height - cy) / fy + 0.3 * height / 2 / fy))
    txz = torch.clamp(x / zs, *limx)
    tyz = torch.clamp(y / zs, *limy)
    J = torch.zeros(means.shape[0], 2, 3, dtype=means.dtype)
    J = torch.stack([torch.stack([fx / zs, 0 * zs, -fx * txz / zs], -1),
                     torch.stack([0 * zs, fy / zs, -fy * tyz / zs], -1)], -2)
    R = quat_matrix(quats)
    S = torch.diag_embed(scales)
    Sigma = R @ S @ S @ R.transpose(-1, -2)
    cov = J @ Rw @ Sigma @ Rw.T @ J.transpose(-1, -2) + eps2d * torch.eye(2, dtype=means.dtype)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    ok = ok & (det > 0)
    dets = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([cov[:, 1, 1] / dets, -cov[:, 0, 1] / dets, cov[:, 0, 0] / dets], -1)
    rx = torch.ceil(3.33 * torch.sqrt(cov[:, 0, 0].detach()))
    ry = torch.ceil(3.33 * torch.sqrt(cov[:, 1, 1].detach()))
    inside = (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
    return torch.stack([u, v], -1), conics, z, ok & inside, cov


def composite(means2d, conics, opacities, colors, depths, valid, width, height, background,
              alpha_min=1 / 255, t_min=1e-4):
    """Front-to-back dense compositing -> (image [H, W, D], alpha [H, W, 1])."""
    dt = means2d.dtype
    jj, ii = torch.meshgrid(torch.arange(width, dtype=dt), torch.arange(height, dtype=dt), indexing="xy")
    px, py = (jj + 0.5).reshape(-1), (ii + 0.5).reshape(-1)
    T = torch.ones(px.shape[0], dtype=dt)
    done = torch.zeros(px.shape[0], dtype=torch.bool)
    out = torch.zeros(px.shape[0], colors.shape[1], dtype=dt)
    idx = torch.nonzero(valid).flatten()
    idx = idx[torch.argsort(depths.detach()[idx], stable=True)]
    for g in idx.tolist():
        a, b, c = conics[g]
        dx, dy = px - means2d[g, 0], py - means2d[g, 1]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp(opacities[g] * torch.exp(-sigma), max=0.99)
        use = (sigma >= 0) & (alpha >= alpha_min) & ~done
        T_next = T * (1 - alpha)
        stop = use & (T_next <= t_min)
        done = done | stop
        use = use & ~stop
        out = out + torch.where(use, alpha * T, torch.zeros_like(T))[:, None] * colors[g]
        T = torch.where(use, T_next, T)
    out = out + T[:, None] * background
    return out.view(height, width, -1), (1 - T).view(height, width, 1)


def render(means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds=None, **kw):
    """Multi-camera dense reference -> (render [C, H, W, D], alpha [C, H, W, 1])."""
    imgs, alphas = [], []
    for ci in range(viewmats.shape[0]):
        m2d, con, z, ok, _ = project(means, quats, scales, viewmats[ci], Ks[ci], width, height)
        ok = ok & (opacities > 1 / 255)
        bg = backgrounds[ci] if backgrounds is not None else torch.zeros(colors.shape[-1], dtype=means.dtype)
        col = colors[ci] if colors.dim() == 3 else colors
        im, al = composite(m2d, con, opacities, col, z, ok, width, height, bg, **kw)
        imgs.append(im)
        alphas.append(al)
    return torch.stack(imgs), torch.stack(alphas)


def random_cloud(n, d=3, *, seed=0, dtype=torch.float32, opacity=(0.2, 0.9), log_scale=(-3.2, -2.0)):
    """A random Gaussian cloud in front of the camera from :func:`camera` (z in [2, 4])."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.6, 2.0], dtype=torch.float64)
    means = means - torch.tensor([1.0, 0.8, -2.0], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    lo, hi = log_scale
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64))
    opac = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    feats = torch.rand(n, d, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, scales, opac, feats)]


def camera(width, height, *, f=None, dtype=torch.float32, yaw=0.0):
    """viewmats [1, 4, 4], Ks [1, 3, 3]: looking down +z from the origin (optionally turned by yaw)."""
    f = f or 0.9 * max(width, height)
    K = torch.tensor([[f, 0, width / 2], [0, f * 1.05, height / 2 + 0.3], [0, 0, 1]], dtype=dtype)
    V = torch.eye(4, dtype=dtype)
    c, s = math.cos(yaw), math.sin(yaw)
    V[:3, :3] = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=dtype)
    V[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=dtype)
    return V[None], K[None]
