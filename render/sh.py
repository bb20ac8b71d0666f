"""Real spherical harmonics up to degree 3, evaluated the way the 3DGS reference does (colour = SH + 0.5)."""

from __future__ import annotations

import torch

from toolkit.errors import ToolkitError

# Normalisation constants of the real SH basis (degree 0..3), in the 3DGS ordering.
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH: coeffs [..., K, D] (K >= (degree+1)^2), dirs [..., 3] (any length, normalized here)
    -> [..., D] (raw, without the +0.5 offset)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ToolkitError(f"sh_degree: expected 0..{MAX_SH_DEGREE}, got {degree}")
    if coeffs.shape[-2] < num_sh_bases(degree):
        raise ToolkitError(f"features: sh_degree {degree} needs K >= {num_sh_bases(degree)} coefficients, "
                           f"got K = {coeffs.shape[-2]}")
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = (d[..., i, None] for i in range(3))
    c = coeffs
    out = _C0 * c[..., 0, :]
    if degree >= 1:
        out = out - _C1 * y * c[..., 1, :] + _C1 * z * c[..., 2, :] - _C1 * x * c[..., 3, :]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out = (out + _C2[0] * xy * c[..., 4, :] + _C2[1] * yz * c[..., 5, :]
               + _C2[2] * (2 * zz - xx - yy) * c[..., 6, :] + _C2[3] * xz * c[..., 7, :]
               + _C2[4] * (xx - yy) * c[..., 8, :])
    if degree >= 3:
        out = (out + _C3[0] * y * (3 * xx - yy) * c[..., 9, :] + _C3[1] * xy * z * c[..., 10, :]
               + _C3[2] * y * (4 * zz - xx - yy) * c[..., 11, :]
               + _C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * c[..., 12, :]
               + _C3[4] * x * (4 * zz - xx - yy) * c[..., 13, :] + _C3[5] * z * (xx - yy) * c[..., 14, :]
               + _C3[6] * x * (xx - 3 * yy) * c[..., 15, :])
    return out


def sh_to_color(degree: int, coeffs: torch.Tensor, means: torch.Tensor, camera_centers: torch.Tensor) -> torch.Tensor:
    """View-dependent colours [C, N, D] = max(SH(mean - camera centre) + 0.5, 0) for coeffs [N, K, D],
    means [N, 3], camera_centers [C, 3]."""
    dirs = means[None, :, :] - camera_centers[:, None, :]
    return torch.clamp_min(eval_sh(degree, coeffs[None], dirs) + 0.5, 0.0)
