"""The depth-layer plan of the preview splatter's gaze-only frames (``render.preview``), on the CPU.

When only the dynamic Gaussians (the eyes) change under one camera, the splatter composites three layers
inside the screen rectangle they touch: the static Gaussians behind the dynamic depth range (drawn once per
camera), those inside it (re-sorted each frame, with the dynamic ones) and those in front (drawn once).
"Over" is associative, so this equals a full redraw to float rounding. These functions decide the range,
the rectangle and which Gaussian goes to which layer; the splatter does the drawing.

Rows are the packed [N, 16] rows of ``render.preview_footprints.pack_gaussians``; depths are camera z.
"""

from __future__ import annotations

import math

import numpy as np

from render.preview_footprints import sort_back_to_front

Rect = tuple[int, int, int, int]  # x, y, w, h in pixels


def dynamic_depth_range(dz: np.ndarray, spheres, viewmat: np.ndarray) -> tuple[float, float]:
    """Camera-depth range [lo, hi] that the dynamic Gaussians (visible depths ``dz`` [M]) keep.

    With ``spheres`` [(centre [3], radius)], the range covers every sphere, so it holds for every gaze (each
    eye Gaussian's mean stays on its sphere). Without, it is the current range padded by a quarter.
    """
    lo, hi = (float(dz.min()), float(dz.max())) if dz.size else (0.0, 0.0)
    if spheres:
        R, t = viewmat[:3, :3], viewmat[:3, 3]
        cz = [float(R[2] @ c + t[2]) for c, _ in spheres]
        s_lo = min(z - r for z, (_, r) in zip(cz, spheres, strict=True))
        s_hi = max(z + r for z, (_, r) in zip(cz, spheres, strict=True))
        return (min(lo, s_lo), max(hi, s_hi)) if dz.size else (s_lo, s_hi)
    pad = 0.25 * (hi - lo) + 1e-6 * max(abs(lo), abs(hi)) + 1e-9
    return lo - pad, hi + pad


def sphere_zone(dynamic_rows: np.ndarray, spheres, viewmat: np.ndarray, K: np.ndarray, width: int, height: int,
                near: float, eps2d: float) -> Rect | None:
    """Pixel rectangle that holds every footprint of the dynamic Gaussians (rows [M, 16]) for any rotation
    about their spheres' centres, or None when a sphere reaches the near plane."""
    cov = dynamic_rows[:, 4:10]
    # r_cut * sqrt(trace) bounds the alpha ellipse of any 3D covariance along any direction.
    margin3d = float((dynamic_rows[:, 10] * np.sqrt(np.maximum(cov[:, 0] + cov[:, 3] + cov[:, 5], 0))).max())
    R, t = viewmat[:3, :3].astype(np.float64), viewmat[:3, 3].astype(np.float64)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    xs, ys = [], []
    for c, r in spheres:
        p = R @ np.asarray(c, np.float64) + t
        rr = r + margin3d
        if p[2] - rr <= near:
            return None
        skew = float(K[0, 1])
        for zz in (p[2] - rr, p[2] + rr):  # x/z and y/z over the sphere's box peak at its corners
            for sx in (-rr, rr):
                for sy in (-rr, rr):
                    xs.append(fx * (p[0] + sx) / zz + skew * (p[1] + sy) / zz + cx)
                    ys.append(fy * (p[1] + sy) / zz + cy)
    pad = 3.33 * math.sqrt(eps2d) + 3.0  # the 2D dilation and rounding
    x0, x1 = max(0, int(min(xs) - pad)), min(width, int(max(xs) + pad) + 1)
    y0, y1 = max(0, int(min(ys) - pad)), min(height, int(max(ys) + pad) + 1)
    return (x0, y0, max(x1 - x0, 1), max(y1 - y0, 1))


def split_layers(depth: np.ndarray, visible: np.ndarray, dynamic: np.ndarray, lo: float, hi: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Visible static Gaussians by layer -> (back ids, front ids, both back to front; mid ids ascending).

    depth [N] camera z, visible [N] and dynamic [N] bool; the mid layer is the static ones inside [lo, hi].
    """
    static = visible & ~dynamic
    back = sort_back_to_front(np.flatnonzero(static & (depth > hi)), depth)
    front = sort_back_to_front(np.flatnonzero(static & (depth < lo)), depth)
    mid_static = np.flatnonzero(static & (depth >= lo) & (depth <= hi))
    return back, front, mid_static


def boxes_touching(bbox: np.ndarray, rect: Rect) -> np.ndarray:
    """[M] bool: which footprint boxes [M, 4] (x0, y0, x1, y1) touch the rectangle (x, y, w, h)."""
    x, y, w, h = rect
    return (bbox[:, 2] >= x) & (bbox[:, 0] <= x + w) & (bbox[:, 3] >= y) & (bbox[:, 1] <= y + h)


def rect_within(rect: Rect, zone: Rect) -> bool:
    """Whether ``rect`` lies inside ``zone`` (both x, y, w, h)."""
    x0, y0, w, h = zone
    return not (rect[0] < x0 or rect[1] < y0 or rect[0] + rect[2] > x0 + w or rect[1] + rect[3] > y0 + h)
