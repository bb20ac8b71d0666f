"""GPU path of :func:`render.splat.rasterize`: gsplat's CUDA rasterizer, behind the same call.

At the paper's scale (100,000 Gaussians, 512², three renders a step, ~100k steps) the pure-torch tile sweep is
the reference and the CPU path, not what a GPU should train with: on an H100 gsplat 1.5.3 renders and
differentiates 100,000 Gaussians into 4 cameras at 512² in 10.5 ms against 285 ms (docs/results.md,
2026-11-26). ``rasterize`` calls :func:`rasterize_gsplat` when the Gaussians are CUDA tensors, gsplat imports
(the optional extra ``gsplat``; it compiles its kernels on first use where nvcc exists, ~70 s) and the call
is one gsplat renders the same way; otherwise the torch path runs. ``DITGAZE_SPLAT=torch`` forces the torch
path, ``DITGAZE_SPLAT=gsplat`` makes a missing gsplat an error rather than a silent fall-back.

Same conventions: OpenCV cameras, pixel centres at +0.5, wxyz quaternions of any norm, activated scales,
``eps2d`` dilation, alpha skipped below 1/255, a pixel stopping before T drops to 1e-4, depth-sorted
front-to-back, SH as max(SH + 0.5, 0), ``depth`` as the sum of z_i w_i. One difference gsplat's kernels fix:
alpha is clamped at 0.999, the torch path's at 0.99 (graphdeco's value), so the two differ where a Gaussian of
opacity above 0.99 covers a pixel near its centre. ``meta`` has radii, means2d, depths and conics as gsplat
returns them (no ``counters``: the tile sweep's statistics are the torch path's).
"""

from __future__ import annotations

import functools
import os
from typing import Any

import torch

from toolkit.errors import ToolkitError

ENV = "DITGAZE_SPLAT"


@functools.lru_cache(maxsize=1)
def _gsplat_rasterization():
    try:
        from gsplat import rasterization
    except ImportError:
        return None
    return rasterization


def use_gsplat(means: torch.Tensor, features: torch.Tensor, sh_degree: int | None) -> bool:
    """Whether :func:`render.splat.rasterize` should call gsplat for these inputs (module docstring)."""
    choice = os.environ.get(ENV, "auto").strip().lower()
    if choice not in ("auto", "torch", "gsplat"):
        raise ToolkitError(f"environment variable {ENV}: expected auto, torch or gsplat, got {choice!r}")
    if choice == "torch" or means.device.type != "cuda":
        return False
    if _gsplat_rasterization() is None:
        if choice == "gsplat":
            raise ToolkitError(f"{ENV}=gsplat: the gsplat package is not installed (pip install gsplat, the "
                               f"optional extra 'gsplat')")
        return False
    # gsplat evaluates SH for 3 colour channels only; other SH widths stay on the torch path.
    return sh_degree is None or features.shape[-1] == 3


def rasterize_gsplat(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                     features: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, *,
                     backgrounds: torch.Tensor | None, per_camera: bool, near_plane: float, far_plane: float,
                     eps2d: float, tile_size: int, sh_degree: int | None, return_depth: bool
                     ) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """:func:`render.splat.rasterize`'s arguments (checked there) through gsplat -> (render [C, H, W, D],
    alpha [C, H, W, 1], meta). Per-camera Gaussians ([C, N, ...]) become gsplat's batch axis with one camera
    each; a shared set renders into all C cameras in one call."""
    rasterization = _gsplat_rasterization()
    C, D = viewmats.shape[0], features.shape[-1]
    dtype, dev = means.dtype, means.device
    viewmats, Ks = viewmats.to(dev, dtype), Ks.to(dev, dtype)
    if per_camera:  # batch axis C, one camera each
        viewmats, Ks = viewmats[:, None], Ks[:, None]
    bg = None
    if backgrounds is not None:
        bg = backgrounds.to(dev, dtype)
        if return_depth:
            bg = torch.cat([bg, bg.new_zeros(C, 1)], -1)
        bg = bg[:, None] if per_camera else bg
    img, alpha, info = rasterization(
        means, quats.to(dtype), scales.to(dtype), opacities.to(dtype), features.to(dev, dtype), viewmats, Ks,
        int(width), int(height), near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
        packed=False, tile_size=int(tile_size), backgrounds=bg, render_mode="RGB+D" if return_depth else "RGB")
    if per_camera:
        img, alpha = img[:, 0], alpha[:, 0]
    meta: dict[str, Any] = {k: _cameras_first(info[k], per_camera) for k in ("radii", "means2d", "depths", "conics")}
    meta["tile_size"], meta["backend"] = int(tile_size), "gsplat"
    if return_depth:
        meta["depth"] = img[..., D:]
    return img[..., :D], alpha, meta


def _cameras_first(t: torch.Tensor, per_camera: bool) -> torch.Tensor:
    """gsplat's per-(camera, Gaussian) output with the batch axis of per-camera sets folded: [C, 1, N, ...] ->
    [C, N, ...]."""
    return t[:, 0] if per_camera else t
