"""EWA projection of 3D Gaussians into pinhole cameras (gsplat >= 1.6 / original 3DGS conventions).

Plain differentiable torch (autograd handles the backward): the per-Gaussian work is O(C * N) and small
next to rasterization, so it needs no custom kernel. The footprints and which Gaussians are culled come from
``render.cull`` (the rule the preview splatter shares); this module adds conics and screen-space boxes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from render.cull import FOV_CLAMP, MAX_FOOTPRINT, footprints

__all__ = ["Projection", "project_gaussians", "RADIUS_SIGMAS", "FOV_CLAMP", "MAX_FOOTPRINT"]

# Radius of the screen-space box in standard deviations of the dilated 2D covariance, per axis (gsplat).
# sqrt(2 ln 255) = 3.3290 < 3.33, so no pixel outside the box can reach alpha >= 1/255: culling is exact.
RADIUS_SIGMAS = 3.33


@dataclass
class Projection:
    """Per camera and Gaussian screen-space quantities; all [C, N, ...] tensors.

    radii [C, N, 2] int32 (0 = culled), means2d [C, N, 2] pixels, depths [C, N] camera z,
    conics [C, N, 3] (a, b, c) of the inverse dilated covariance, cov2d [C, N, 3] (xx, xy, yy) dilated,
    means_cam [C, N, 3] camera-space means.
    """

    radii: torch.Tensor
    means2d: torch.Tensor
    depths: torch.Tensor
    conics: torch.Tensor
    cov2d: torch.Tensor
    means_cam: torch.Tensor


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    *,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> Projection:
    """Project Gaussians: means [N, 3], quats [N, 4] wxyz (any norm), scales [N, 3] activated (one set seen
    by every camera), or [C, N, ...] (camera c sees its own set c: a batch of posed heads),
    viewmats [C, 4, 4] world-to-camera (OpenCV axes), Ks [C, 3, 3] pixels.

    Conventions: Sigma = R S S^T R^T; cov2d = J W Sigma W^T J^T with the Jacobian J of the pinhole map taken
    at the mean whose tangent x/z is clamped to [-(cx/fx + 0.3 t), (W - cx)/fx + 0.3 t], t = W / (2 fx)
    (same for y); then cov2d + eps2d * I ("dilation"); conic = inverse of the dilated cov2d; per-axis radius
    ceil(3.33 sqrt(cov2d_ii)). Culled (radius 0): exactly where ``render.cull.cull_mask`` is False (non-finite
    or degenerate parameters, z outside (near, far), a footprint too large for float32 or too thin to
    invert), and where the box misses the image.
    means2d = K[:2] @ (x/z, y/z, 1) uses the unclamped mean (skew K[0, 1] included, ignored in J as gsplat).
    """
    fp = footprints(means, quats, scales, viewmats, Ks, width, height, near_plane=near_plane,
                    far_plane=far_plane, eps2d=eps2d)
    sxx, sxy, syy, det = fp.sxx, fp.sxy, fp.syy, fp.det
    valid = fp.keep
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([syy / det_s, -sxy / det_s, sxx / det_s], -1)
    cov2d = torch.stack([sxx, sxy, syy], -1)
    u, v = fp.means2d.unbind(-1)

    with torch.no_grad():
        rx = torch.ceil(RADIUS_SIGMAS * torch.sqrt(sxx.clamp_min(0)))
        ry = torch.ceil(RADIUS_SIGMAS * torch.sqrt(syy.clamp_min(0)))
        inside = (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
        keep = valid & inside & torch.isfinite(rx) & torch.isfinite(ry)
        radii = torch.stack([torch.where(keep, rx, 0.0), torch.where(keep, ry, 0.0)], -1)
        radii = radii.clamp_max(2**30).to(torch.int32)
    return Projection(radii=radii, means2d=fp.means2d, depths=fp.depths, conics=conics, cov2d=cov2d,
                      means_cam=fp.means_cam)
