"""CPU side of the preview splatter: checking a frame's inputs, the shared cull rule for one camera
(:func:`drawable`, ``render.cull``'s rule with a cheap float64 pre-check), packing Gaussians into the
data-texture layout and a numpy mirror of the vertex shader's projection (footprint boxes, depths, quad
areas), used to find the screen rectangle a gaze change touches, to build the depth layers and to count
fragment work. Conventions as ``render.preview``."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from toolkit.errors import ToolkitError


def as_float32(x: Any, name: str, shape: tuple) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.ascontiguousarray(np.asarray(x, dtype=np.float32))
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape, strict=False)):
        raise ToolkitError(f"render_preview: {name} must have shape {list(shape)}, got {list(a.shape)}".replace("None", "N"))
    return a


def check_frame_inputs(means, quats, scales, opacities, colors, viewmat, K, may_change=None, *,
                       held: int | None = None) -> tuple[np.ndarray, ...]:
    """One frame's Gaussians and camera -> float32 (means [N, 3], quats [N, 4], scales [N, 3], opacities [N],
    colors [N, 3], viewmat [4, 4], K [3, 3]), finite.

    ``may_change`` (ids) with ``held`` == N (the splatter holds N Gaussians, checked when they came in): only
    those rows are checked for NaN/inf, and each id must lie in [0, N).
    """
    means = as_float32(means, "means", (None, 3))
    n = means.shape[0]
    quats = as_float32(quats, "quats", (n, 4))
    scales = as_float32(scales, "scales", (n, 3))
    opacities = as_float32(opacities, "opacities", (n,))
    colors = as_float32(colors, "colors", (n, 3))
    viewmat = as_float32(viewmat, "viewmat", (4, 4))
    K = as_float32(K, "K", (3, 3))
    rows = None if may_change is None or held != n else np.asarray(may_change, np.int64).reshape(-1)
    if rows is not None and rows.size and (rows.min() < 0 or rows.max() >= n):
        raise ToolkitError(f"render_preview: may_change holds ids outside [0, {n})")
    for name, a in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                    ("colors", colors), ("viewmat", viewmat), ("K", K)):
        part = a if rows is None or a.shape[0] != n or name in ("viewmat", "K") else a[rows]
        if not np.isfinite(part).all():
            raise ToolkitError(f"render_preview: {name} contains NaN or inf")
    return means, quats, scales, opacities, colors, viewmat, K


def dynamic_mask(dynamic, n: int) -> np.ndarray | None:
    """The ``dynamic`` [N] mask (array or tensor) as numpy bool; None when absent or all False."""
    if dynamic is None:
        return None
    dyn = np.asarray(dynamic.detach().cpu() if hasattr(dynamic, "detach") else dynamic).astype(bool)
    if dyn.shape != (n,):
        raise ToolkitError(f"render_preview: dynamic must be a bool mask of shape [{n}], got {list(dyn.shape)}")
    return dyn if dyn.any() else None


def covariances(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz (any norm, zero -> identity), [N, 3] scales -> [N, 6] float32 covariance xx, xy, xz, yy, yz,
    zz. Computed in float64, so any scale the cull rule keeps (<= ``render.cull.SCALE_MAX``) fits float32."""
    q = quats.astype(np.float64)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    ident = np.array([1, 0, 0, 0], np.float64)
    q = np.where(n > 0, q / np.where(n > 0, n, 1.0), ident)  # as toolkit.rotations.normalize_quat
    w, x, y, z = q.T
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)
    M = R * scales.astype(np.float64)[:, None, :]  # columns scaled: Sigma = M M^T, six unique entries
    r0, r1, r2 = M[:, 0], M[:, 1], M[:, 2]
    dot = lambda a, b: (a * b).sum(1)  # noqa: E731
    cov = np.stack([dot(r0, r0), dot(r0, r1), dot(r0, r2), dot(r1, r1), dot(r1, r2), dot(r2, r2)], 1)
    return cov.astype(np.float32)


def camera_free_ok(means: np.ndarray, quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """[N] bool: the camera-free tests of the shared cull rule (``render.cull.param_tests``) on float32
    means [N, 3], quats [N, 4], scales [N, 3]."""
    from render.cull import param_tests

    tests = param_tests(*(float32_tensor(a) for a in (means, quats, scales)))
    return (tests["params"] & tests["scale"] & tests["quat"]).numpy()


def float32_tensor(a: np.ndarray):
    """A numpy array as a float32 CPU tensor (no copy when it already is float32 and contiguous)."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


def pack_gaussians(means, quats, scales, opacities, colors, ok=None) -> np.ndarray:
    """Activated Gaussians -> [N, 16] float32 rows in the data-texture layout of ``render.preview_shaders``.
    Rows that fail the camera-free tests of the cull rule (``ok`` [N], computed when not given) get a zero
    covariance and r_cut 0 (the shader skips them), so nothing overflows."""
    n = means.shape[0]
    out = np.zeros((n, 16), np.float32)
    ok = camera_free_ok(means, quats, scales) if ok is None else ok
    out[:, 0:3] = means
    out[:, 3] = opacities
    out[ok, 4:10] = covariances(quats[ok], scales[ok])
    o = np.clip(opacities.astype(np.float64), 0.0, 1.0)
    # alpha = o exp(-sigma) >= 1/255  <=>  sigma <= ln(255 o): the quad's Mahalanobis half-size.
    out[:, 10] = np.where(ok, np.sqrt(2.0 * np.log(np.maximum(255.0 * o, 1.0))), 0.0)
    out[:, 12:15] = colors
    return out


def drawable(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, viewmat: np.ndarray, K: np.ndarray,
             width: int, height: int, near: float, far: float, eps2d: float, ok: np.ndarray | None = None
             ) -> np.ndarray:
    """The shared cull rule ``render.cull.cull_mask`` for one camera -> keep [M] bool, on float32 means [M, 3],
    quats [M, 4], scales [M, 3], viewmat [4, 4], K [3, 3]; ``ok`` [M]: their :func:`camera_free_ok`, when known.

    Exactly the torch rule, but cheap: a float64 bound first proves most Gaussians kept (depth clear of
    near / far by more than float32's rounding, a footprint too small to be a needle or to overflow) and the
    rule itself runs only on the rest (at a 20k-Gaussian orbit frame, ~0.5 ms instead of ~10 ms).
    """
    from render.cull import cull_mask

    ok = camera_free_ok(means, quats, scales) if ok is None else ok
    sure = ok & _surely_kept(means, scales, viewmat, K, width, height, near, far, eps2d)
    keep = sure.copy()
    rest = np.flatnonzero(ok & ~sure)
    if rest.size:
        t = float32_tensor
        keep[rest] = cull_mask(*(t(a[rest]) for a in (means, quats, scales)), t(viewmat)[None], t(K)[None], width,
                               height, near_plane=near, far_plane=far, eps2d=eps2d)[0].numpy()
    return keep


def _surely_kept(means, scales, viewmat, K, width, height, near, far, eps2d) -> np.ndarray:
    """[M] bool: Gaussians that every test of the cull rule's camera part passes, with margins far above
    float32 rounding (a False only means "run the exact rule")."""
    from render.cull import MAX_CONDITION

    R, t = viewmat[:3, :3].astype(np.float64), viewmat[:3, 3].astype(np.float64)
    m = means.astype(np.float64)
    p = affine_rows(m, R, t)
    with np.errstate(all="ignore"):  # a NaN or inf bound is a False: the exact rule decides
        # float32 z = R m + t rounds by ~1e-7 of the magnitudes summed, whatever z itself is.
        mag = np.abs(m[:, 0]) * abs(R[2, 0]) + np.abs(m[:, 1]) * abs(R[2, 1]) + np.abs(m[:, 2]) * abs(R[2, 2])
        zerr = 1e-5 * (mag + abs(t[2])) + 1e-30
        zlo = np.maximum(p[:, 2] - zerr, 1e-300)
        fx, fy, sk = abs(float(K[0, 0])), abs(float(K[1, 1])), abs(float(K[0, 1]))
        lim = np.abs(tangent_limits(K, width, height).astype(np.float64)) * 1.01
        # ||J||_F with the clamped tangents at their extremes; ||J W R S||_F <= ||J||_F ||W||_2 ||s||.
        jf2 = (fx / zlo) ** 2 * (1 + lim[:2].max() ** 2) + (fy / zlo) ** 2 * (1 + lim[2:].max() ** 2)
        f2 = jf2 * np.linalg.norm(R, 2) ** 2 * (scales.astype(np.float64) ** 2).sum(1) * 1.01
        e = float(eps2d)
        # trace^2 / det <= (f2 + 2 e)^2 / (e f2 + e^2): det >= e ||F||^2 + e^2 by Cauchy-Binet.
        kappa = (f2 + 2 * e) ** 2 / max(e * e, 1e-300) / (f2 / max(e, 1e-300) + 1)
        big = np.maximum(np.maximum(fx * np.abs(p[:, 0]), sk * np.abs(p[:, 1])), fy * np.abs(p[:, 1]))
        return ((p[:, 2] - zerr > near) & (p[:, 2] + zerr < far) & (e > 0) & (kappa <= 0.99 * MAX_CONDITION)
                & (big < 1e30) & (big / zlo < 1e30))


def tangent_limits(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """gsplat's clamp of x/z and y/z: (-x, +x, -y, +y) limits, 0.3 tan-half-fov beyond the image edges."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tx, ty = 0.5 * width / fx, 0.5 * height / fy
    return np.array([cx / fx + 0.3 * tx, (width - cx) / fx + 0.3 * tx,
                     cy / fy + 0.3 * ty, (height - cy) / fy + 0.3 * ty], np.float32)


def affine_rows(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[M, 3] points -> [M, 3] R p + t, elementwise (no BLAS call)."""
    return points[:, 0:1] * R[:, 0] + points[:, 1:2] * R[:, 1] + points[:, 2:3] * R[:, 2] + t


def project_footprints(rows: np.ndarray, viewmat: np.ndarray, K: np.ndarray, width: int, height: int,
                       near: float = 0.01, far: float = 1e10, eps2d: float = 0.3) -> dict[str, np.ndarray]:
    """CPU mirror of the vertex shader for [M, 16] packed rows -> depth [M], valid [M], bbox [M, 4]
    (x0, y0, x1, y1 pixels of the alpha >= 1/255 ellipse) and quad_area [M] (pixels of the cut quad)."""
    # Elementwise products instead of (M x 3) @ (3 x 3) matmuls: tiny matmuls over many rows start BLAS
    # threads, which stall badly on a shared machine.
    R, t = viewmat[:3, :3].astype(np.float64), viewmat[:3, 3].astype(np.float64)
    p = affine_rows(rows[:, 0:3].astype(np.float64), R, t)
    z = p[:, 2]
    c = rows[:, 4:10].astype(np.float64)
    S = c[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    A = (S[:, :, None, :] * R[None, None, :, :]).sum(-1)   # A[m, k, j] = (S R^T)[k, j]
    C = (R[None, :, :, None] * A[:, None, :, :]).sum(2)    # C[m, i, j] = (R S R^T)[i, j]
    fx, fy = float(K[0, 0]), float(K[1, 1])
    lim = tangent_limits(K, width, height)
    zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
    tx = zs * np.clip(p[:, 0] / zs, -lim[0], lim[1])
    ty = zs * np.clip(p[:, 1] / zs, -lim[2], lim[3])
    j00, j02, j11, j12 = fx / zs, -fx * tx / zs**2, fy / zs, -fy * ty / zs**2
    c00, c01, c02, c11, c12, c22 = C[:, 0, 0], C[:, 0, 1], C[:, 0, 2], C[:, 1, 1], C[:, 1, 2], C[:, 2, 2]
    cov_a = j00 * j00 * c00 + 2 * j00 * j02 * c02 + j02 * j02 * c22
    cov_b = j00 * j11 * c01 + j00 * j12 * c02 + j02 * j11 * c12 + j02 * j12 * c22
    cov_c = j11 * j11 * c11 + 2 * j11 * j12 * c12 + j12 * j12 * c22
    a, b, cc = cov_a + eps2d, cov_b, cov_c + eps2d
    det = a * cc - b * b
    mean = np.stack([fx * p[:, 0] / zs + float(K[0, 1]) * p[:, 1] / zs + K[0, 2], fy * p[:, 1] / zs + K[1, 2]], 1)
    r = rows[:, 10].astype(np.float64)
    valid = (z > near) & (z < far) & (r > 0) & (det > 0)
    hx, hy = r * np.sqrt(np.maximum(a, 0)), r * np.sqrt(np.maximum(cc, 0))
    bbox = np.stack([mean[:, 0] - hx, mean[:, 1] - hy, mean[:, 0] + hx, mean[:, 1] + hy], 1)
    on = valid & (bbox[:, 2] > 0) & (bbox[:, 0] < width) & (bbox[:, 3] > 0) & (bbox[:, 1] < height)
    # Cut quad area 4 r^2 sqrt(det), scaled by the on-screen share of the ellipse's bounding box.
    w_in = np.clip(np.minimum(bbox[:, 2], width) - np.maximum(bbox[:, 0], 0), 0, None)
    h_in = np.clip(np.minimum(bbox[:, 3], height) - np.maximum(bbox[:, 1], 0), 0, None)
    share = w_in * h_in / np.maximum(4 * hx * hy, 1e-12)
    area = np.where(on, 4 * r * r * np.sqrt(np.maximum(det, 0)) * np.minimum(share, 1.0), 0.0)
    return {"depth": z, "valid": valid, "on_screen": on, "bbox": bbox, "quad_area": area}


def union_rect(bbox: np.ndarray, width: int, height: int) -> tuple[int, int, int, int] | None:
    """Integer pixel rectangle (x, y, w, h) covering [M, 4] boxes (+1 pixel), clipped; None when empty."""
    if bbox.shape[0] == 0:
        return None
    x0 = max(0, int(math.floor(bbox[:, 0].min())) - 1)
    y0 = max(0, int(math.floor(bbox[:, 1].min())) - 1)
    x1 = min(width, int(math.ceil(bbox[:, 2].max())) + 1)
    y1 = min(height, int(math.ceil(bbox[:, 3].max())) + 1)
    return (x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else None


def merge_rects(a, b):
    if a is None or b is None:
        return a or b
    x0, y0 = min(a[0], b[0]), min(a[1], b[1])
    x1, y1 = max(a[0] + a[2], b[0] + b[2]), max(a[1] + a[3], b[1] + b[3])
    return (x0, y0, x1 - x0, y1 - y0)


def sort_back_to_front(ids: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """ids sorted by decreasing ``depth`` [N] (indexed by id): :func:`back_to_front` of ``depth[ids]``."""
    return back_to_front(ids, depth[ids])


def back_to_front(ids: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``ids`` in drawing order for back-to-front blending, ``d`` their depths: decreasing depth, and among
    equal depths decreasing id, so the lower id ends in front as in ``render.splat.rasterize`` (which blends
    front to back, ties in index order). Any subset sorts like the whole."""
    return ids[np.lexsort((-ids, -d))]


def is_back_to_front(ids: np.ndarray, d: np.ndarray) -> bool:
    """Whether ``ids`` (depths ``d``) are already in :func:`back_to_front` order."""
    if ids.size < 2:
        return True
    ahead = (d[:-1] > d[1:]) | ((d[:-1] == d[1:]) & (ids[:-1] > ids[1:]))
    return bool(ahead.all())
