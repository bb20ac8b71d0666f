"""EWA projection of 3D Gaussians into pinhole cameras (gsplat >= 1.6 / original 3DGS conventions).

Plain differentiable torch (autograd handles the backward): the per-Gaussian work is O(C * N) and small
next to rasterization, so it needs no custom kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from toolkit.rotations import quat_to_matrix

# Radius of the screen-space box in standard deviations of the dilated 2D covariance, per axis (gsplat).
# sqrt(2 ln 255) = 3.3290 < 3.33, so no pixel outside the box can reach alpha >= 1/255: culling is exact.
RADIUS_SIGMAS = 3.33
# The EWA Jacobian is evaluated at the mean clamped to 1.3x the half field of view (3DGS / gsplat):
# a Gaussian far outside the frustum would otherwise get a huge, meaningless 2D footprint.
FOV_CLAMP = 0.3
MAX_FOOTPRINT = 1e9
"""Culling bound on the entries of J W R S (pixels): the 2x2 minors square them twice, and 1e9^4 stays well
inside float32's range (3.4e38)."""


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
    ceil(3.33 sqrt(cov2d_ii)). Culled (radius 0): z <= near or z >= far, det <= 0, box fully off-image, and
    a footprint so large that float32 would overflow (an entry of J W R S >= ``MAX_FOOTPRINT`` pixels).
    means2d = K[:2] @ (x/z, y/z, 1) uses the unclamped mean (skew K[0, 1] included, ignored in J as gsplat).
    """
    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, :3, 3]  # [C, 3]
    per_camera = means.dim() == 3
    means_c = torch.einsum("cij,cnj->cni" if per_camera else "cij,nj->cni", R, means) + t[:, None, :]  # [C, N, 3]
    x, y, z = means_c.unbind(-1)

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    in_depth = (z > near_plane) & (z < far_plane)
    # Culled Gaussians still flow through the graph: divide by a safe z so their gradients stay finite (zero).
    zs = torch.where(in_depth, z, torch.ones_like(z))
    u = fx * x / zs + Ks[:, 0, 1, None] * y / zs + cx
    v = fy * y / zs + cy
    means2d = torch.stack([u, v], -1)

    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    tx = torch.clamp(x / zs, min=-(cx / fx + FOV_CLAMP * tan_x), max=(width - cx) / fx + FOV_CLAMP * tan_x)
    ty = torch.clamp(y / zs, min=-(cy / fy + FOV_CLAMP * tan_y), max=(height - cy) / fy + FOV_CLAMP * tan_y)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / zs, zero, fy / zs, -fy * ty / zs], -1).view(*zs.shape, 2, 3)

    # cov2d = (J W R S)(J W R S)^T: built from a factor, so it is PSD to rounding for any scale.
    M = quat_to_matrix(quats) * scales[..., None, :]  # [(C,) N, 3, 3] = R S
    F = J @ torch.einsum("cij,cnjk->cnik" if per_camera else "cij,njk->cnik", R, M)  # [C, N, 2, 3]
    # A footprint beyond ~1e9 px would overflow float32 in the minors below (and 0 * inf = NaN in their
    # backward even when culled): such Gaussians are culled, with their F zeroed before any product.
    sane = torch.isfinite(F).all(-1).all(-1) & (F.abs().amax((-2, -1)) < MAX_FOOTPRINT)
    F = torch.where(sane[..., None, None], F, torch.zeros_like(F))
    f0, f1 = F[..., 0, :], F[..., 1, :]
    sxx = (f0 * f0).sum(-1) + eps2d
    sxy = (f0 * f1).sum(-1)
    syy = (f1 * f1).sum(-1) + eps2d
    # det by Cauchy-Binet (sum of squared 2x2 minors of F) plus the dilation terms: never negative, and
    # accurate where sxx * syy - sxy^2 would cancel catastrophically (needles, huge blobs).
    minors = torch.stack([f0[..., 0] * f1[..., 1] - f0[..., 1] * f1[..., 0],
                          f0[..., 0] * f1[..., 2] - f0[..., 2] * f1[..., 0],
                          f0[..., 1] * f1[..., 2] - f0[..., 2] * f1[..., 1]], -1)
    det = (minors * minors).sum(-1) + eps2d * ((f0 * f0).sum(-1) + (f1 * f1).sum(-1)) + eps2d * eps2d
    valid = in_depth & sane & (det > 0) & torch.isfinite(det)
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([syy / det_s, -sxy / det_s, sxx / det_s], -1)
    cov2d = torch.stack([sxx, sxy, syy], -1)

    with torch.no_grad():
        rx = torch.ceil(RADIUS_SIGMAS * torch.sqrt(sxx.clamp_min(0)))
        ry = torch.ceil(RADIUS_SIGMAS * torch.sqrt(syy.clamp_min(0)))
        inside = (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
        keep = valid & inside & torch.isfinite(rx) & torch.isfinite(ry)
        radii = torch.stack([torch.where(keep, rx, 0.0), torch.where(keep, ry, 0.0)], -1)
        radii = radii.clamp_max(2**30).to(torch.int32)
    return Projection(radii=radii, means2d=means2d, depths=z, conics=conics, cov2d=cov2d, means_cam=means_c)
