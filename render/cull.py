"""The one rule that decides which Gaussians are drawn, shared by both splatters.

``render.splat`` (through ``render.projection.project_gaussians``) and ``render.preview`` both call
:func:`footprints` / :func:`cull_mask`, so they draw the same set. A Gaussian is drawn by camera c only if
all of these hold (``keep[c, n]``):

1. its mean, quaternion and scales are finite;
2. its largest |scale| is at most ``SCALE_MAX`` (1e18): the preview stores the world covariance (scale^2)
   in float32, whose range ends at 3.4e38;
3. its quaternion is zero (the identity, by the project's convention) or its largest |component| lies in
   ``QUAT_RANGE`` [1e-15, 1e15]: beyond, the squared norm leaves float32's normal range and normalizing
   it gives a wrong rotation;
4. its camera depth z satisfies near < z < far;
5. its projected mean is finite and every entry of the EWA factor J W R S (pixels) is finite and below
   ``MAX_FOOTPRINT`` (1e9): the 2x2 minors square the entries twice and 1e9^4 stays inside float32;
6. its dilated 2D covariance has det > 0 (Cauchy-Binet: sum of squared minors plus the dilation terms) and a
   condition bound trace^2 <= ``MAX_CONDITION`` * det (1e5): a needle (one scale ~0, another projecting to
   hundreds of pixels) beyond it has an a c - b^2 that float32 (the preview's shader) cannot resolve.

Everything is computed in the inputs' dtype with the torch splatter's own arithmetic (the factor below *is*
its projection), so on ordinary scenes the torch splatter is unchanged, bit for bit. Whether a kept
Gaussian's box touches the image is not part of the rule: the torch splatter also drops boxes that miss
the image (radius 0), the preview leaves them to GL clipping.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from toolkit.rotations import quat_to_matrix

SCALE_MAX = 1e18
"""Largest |scale| drawn (world units): scale^2 summed over three axes stays below float32's 3.4e38."""
QUAT_RANGE = (1e-15, 1e15)
"""Largest |component| of a non-zero quaternion that float32 normalizes reliably."""
MAX_FOOTPRINT = 1e9
"""Bound on the entries of J W R S (pixels): the 2x2 minors square them twice, and 1e9^4 < 3.4e38."""
MAX_CONDITION = 1e5
"""Bound on trace^2 / det of the dilated 2D covariance (~ its aspect ratio lambda_max / lambda_min)."""
FOV_CLAMP = 0.3
"""The EWA Jacobian is taken at the mean's tangent clamped to 1.3x the half field of view (3DGS / gsplat):
a Gaussian far outside the frustum would otherwise get a huge, meaningless footprint."""

REASONS = {
    "params": "non-finite means, quats or scales",
    "scale": f"a scale above {SCALE_MAX:g}",
    "quat": f"a non-zero quaternion whose largest component lies outside [{QUAT_RANGE[0]:g}, {QUAT_RANGE[1]:g}]",
    "depth": "camera depth outside (near, far)",
    "footprint": f"a projected mean or footprint beyond {MAX_FOOTPRINT:g} pixels",
    "needle": f"a footprint too thin to invert (det <= 0 or trace^2 / det > {MAX_CONDITION:g})",
}
"""Each test of the rule, by name (the keys of :attr:`Footprints.tests`), as a user-facing phrase."""


@dataclass
class Footprints:
    """Per camera and Gaussian: means_cam [C, N, 3], depths [C, N] (camera z), means2d [C, N, 2] pixels,
    factor [C, N, 2, 3] = J W R S (zeroed where not finite or too large), the dilated 2D covariance sxx,
    sxy, syy [C, N] and its determinant det [C, N], ``keep`` [C, N] bool (the rule) and ``tests``: each test's
    pass mask by name (:data:`REASONS`), broadcastable to [C, N]."""

    means_cam: torch.Tensor
    depths: torch.Tensor
    means2d: torch.Tensor
    factor: torch.Tensor
    sxx: torch.Tensor
    sxy: torch.Tensor
    syy: torch.Tensor
    det: torch.Tensor
    keep: torch.Tensor
    tests: dict


def param_tests(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor) -> dict[str, torch.Tensor]:
    """The camera-free tests of the rule (1-3) -> {"params", "scale", "quat"}: [..., N] bool each, True = pass.
    means [..., N, 3], quats [..., N, 4] wxyz, scales [..., N, 3] activated."""
    finite = torch.isfinite(means).all(-1) & torch.isfinite(quats).all(-1) & torch.isfinite(scales).all(-1)
    qmax = quats.abs().amax(-1)  # exact (no rounding), unlike a norm
    quat_ok = (qmax == 0) | ((qmax >= QUAT_RANGE[0]) & (qmax <= QUAT_RANGE[1]))
    return {"params": finite, "scale": scales.abs().amax(-1) <= SCALE_MAX, "quat": quat_ok}


def finite_scales(scales: torch.Tensor) -> torch.Tensor:
    """scales [..., 3] with +inf replaced by the dtype's largest value. A scene's finite log-scale above ~88.7
    activates to inf in float32; the rule culls it either way (above ``SCALE_MAX``), and this way it is culled
    like any other huge Gaussian instead of tripping a splatter's NaN / inf input check."""
    return torch.where(scales == torch.inf, torch.finfo(scales.dtype).max, scales)


def _sanitized(means, quats, scales, tests):
    """The parameters with each field that fails a camera-free test (``tests``: :func:`param_tests`) replaced by
    a harmless value (mean 0, identity, scale 0): those Gaussians are culled anyway, and their NaN / inf must
    not reach any product, where 0 * inf = NaN would turn up in the gradients. Kept fields pass through
    unchanged, bit for bit. (A NaN or inf fails the quat and scale tests: amax propagates it.)"""
    good_m = torch.isfinite(means).all(-1, keepdim=True)
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1
    return (torch.where(good_m, means, torch.zeros_like(means)), torch.where(tests["quat"][..., None], quats, identity),
            torch.where(tests["scale"][..., None], scales, torch.zeros_like(scales)))


def footprints(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmats: torch.Tensor,
               Ks: torch.Tensor, width: int, height: int, *, near_plane: float = 0.01, far_plane: float = 1e10,
               eps2d: float = 0.3) -> Footprints:
    """EWA footprints and the cull rule (module docstring), differentiable where kept.

    means [N, 3], quats [N, 4] wxyz (any norm), scales [N, 3] activated, or each [C, N, ...] (camera c sees
    set c); viewmats [C, 4, 4] world-to-camera (OpenCV axes), Ks [C, 3, 3] pixels; all one dtype.
    Conventions as ``render.projection.project_gaussians``.
    """
    tests = param_tests(means, quats, scales)
    means, quats, scales = _sanitized(means, quats, scales, tests)
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
    with torch.no_grad():  # a mean projecting beyond float32 is culled; its inf must not reach the graph
        on_plane = torch.isfinite(fx * x / zs + Ks[:, 0, 1, None] * y / zs + cx) & torch.isfinite(fy * y / zs + cy)
    x, y = torch.where(on_plane, x, torch.zeros_like(x)), torch.where(on_plane, y, torch.zeros_like(y))
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
    sxx, sxy, syy, det = _dilated_cov2d(F, eps2d)
    tests["depth"] = in_depth
    tests["footprint"] = sane & on_plane
    tests["needle"] = _well_conditioned(sxx, syy, det)
    keep = in_depth
    for ok in tests.values():
        keep = keep & ok
    return Footprints(means_cam=means_c, depths=z, means2d=means2d, factor=F, sxx=sxx, sxy=sxy, syy=syy, det=det,
                      keep=keep, tests=tests)


def _dilated_cov2d(F: torch.Tensor, eps2d: float) -> tuple[torch.Tensor, ...]:
    """F [C, N, 2, 3] -> (sxx, sxy, syy, det) [C, N] of F F^T + eps2d I."""
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
    return sxx, sxy, syy, det


@torch.no_grad()
def _well_conditioned(sxx: torch.Tensor, syy: torch.Tensor, det: torch.Tensor) -> torch.Tensor:
    """[C, N]: det > 0, finite, and trace^2 <= MAX_CONDITION det (trace^2 / det >= lambda_max / lambda_min)."""
    tr = sxx + syy
    return (det > 0) & torch.isfinite(det) & (tr * tr <= MAX_CONDITION * det)


@torch.no_grad()
def cull_mask(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmats: torch.Tensor,
              Ks: torch.Tensor, width: int, height: int, *, near_plane: float = 0.01, far_plane: float = 1e10,
              eps2d: float = 0.3) -> torch.Tensor:
    """The rule (module docstring) -> keep [C, N] bool: True where camera c draws Gaussian n (if its box
    touches the image). Shapes as :func:`footprints`."""
    return footprints(means, quats, scales, viewmats, Ks, width, height, near_plane=near_plane,
                      far_plane=far_plane, eps2d=eps2d).keep


@torch.no_grad()
def cull_counts(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmats: torch.Tensor,
                Ks: torch.Tensor, width: int, height: int, **kw) -> dict[str, int]:
    """How many (camera, Gaussian) pairs each test of the rule culls first, by :data:`REASONS` key (zeros
    left out): what a warning about an empty or thinned frame reports. Shapes as :func:`footprints`."""
    fp = footprints(means, quats, scales, viewmats, Ks, width, height, **kw)
    left = torch.ones_like(fp.keep)
    out = {}
    for name in REASONS:
        failed = left & ~fp.tests[name]
        if bool(failed.any()):
            out[name] = int(failed.sum())
        left = left & ~failed
    return out
