"""Mesh pieces of the procedural subjects: the sphere lens warp, the eyeball template, iBUG-68 landmarks.

Pure functions of a ``toolkit.procedural.DemoHeadShape`` (no rendering); ``train.data.synthetic`` builds
subjects from them.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from toolkit.procedural import DemoHeadShape

EYE_SCLERA, EYE_IRIS, EYE_PUPIL = 0, 1, 2


def lens_warp(dirs: np.ndarray, focus: np.ndarray, strength: float, sigma: float) -> np.ndarray:
    """Pull unit directions towards ``focus`` (a bijection of the sphere for strength < 1).

    theta -> theta (1 - strength exp(-theta^2 / sigma^2)) is monotone when strength < 1, so the
    icosphere topology (and watertightness) is kept while vertex density near ``focus`` grows by
    about 1 / (1 - strength)^2.
    """
    cos_t = np.clip(dirs @ focus, -1, 1)
    theta = np.arccos(cos_t)
    new_theta = theta * (1 - strength * np.exp(-(theta / sigma) ** 2))
    perp = dirs - cos_t[:, None] * focus
    n = np.linalg.norm(perp, axis=1, keepdims=True)
    perp = np.where(n > 1e-12, perp / np.maximum(n, 1e-12), 0.0)
    return np.cos(new_theta)[:, None] * focus + np.sin(new_theta)[:, None] * perp


def eyeball_mesh(theta_pupil: float, theta_iris: float, segments: int = 40):
    """Unit sphere around the origin looking along -z, with exact pupil/iris boundary rings.

    Returns (verts [Ve, 3], faces [Fe, 3], region [Fe] int8 (0 sclera, 1 iris, 2 pupil), theta [Ve]).
    Each region has its own rings, so colours do not bleed across boundaries (the rings coincide).
    """
    bands = [
        (EYE_PUPIL, np.linspace(0, theta_pupil, 4)),
        (EYE_IRIS, np.linspace(theta_pupil, theta_iris, 6)),
        (EYE_SCLERA, np.concatenate([np.linspace(theta_iris, theta_iris + 0.3, 4)[:-1],
                                     np.linspace(theta_iris + 0.3, math.pi, 9)])),
    ]
    phi = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    verts, faces, region, thetas = [], [], [], []
    for reg, ths in bands:
        idx = sum(len(v) for v in verts)
        ring_idx = []
        for th in ths:
            if th < 1e-9 or th > math.pi - 1e-9:
                pts = np.array([[0.0, 0.0, -math.cos(th)]])
            else:
                pts = np.stack([math.sin(th) * np.cos(phi), math.sin(th) * np.sin(phi),
                                np.full(segments, -math.cos(th))], -1)
            verts.append(pts)
            thetas.append(np.full(len(pts), th))
            ring_idx.append(np.arange(idx, idx + len(pts)))
            idx += len(pts)
        for a, b in zip(ring_idx[:-1], ring_idx[1:], strict=True):
            for s in range(segments):
                s1 = (s + 1) % segments
                if len(a) == 1:  # fan from the front pole
                    faces.append((a[0], b[s1], b[s]))
                elif len(b) == 1:  # fan to the back pole
                    faces.append((a[s], a[s1], b[0]))
                else:
                    faces += [(a[s], a[s1], b[s1]), (a[s], b[s1], b[s])]
                region += [reg] * (1 if len(a) == 1 or len(b) == 1 else 2)
    v = np.concatenate(verts).astype(np.float64)
    f = np.asarray(faces, np.int64)
    # Outward winding (right-hand rule): flip faces whose normal points inwards.
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = (n * v[f].mean(1)).sum(1) < 0
    f[flip] = f[flip][:, ::-1]
    return v, f, np.asarray(region, np.int8), np.concatenate(thetas)


def smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)


def landmark_base_xy(shape: DemoHeadShape) -> np.ndarray:
    """[68, 2] iBUG-68 landmark positions in base (x, y) coordinates of ``shape`` (metres).

    0-16 jaw (image-left to image-right), 17-21 / 22-26 brows, 27-30 nose bridge, 31-35 nose base,
    36-41 left (image-left) eye from its outer corner clockwise in the image, 42-47 right eye from its
    inner corner, 48-59 outer lips from the left corner, 60-67 inner lips.
    """
    ex, ey = shape.eye_offset_x, shape.eye_y
    aw, _ = shape.eye_opening
    aw = aw if aw > 0 else 0.0135
    pts = np.zeros((68, 2))
    # Jaw: a half ellipse from ear level round the chin.
    t = np.linspace(0, math.pi, 17)
    chin_y = shape.center[1] + shape.semi_axes[1] * 0.93 + 0.008 * shape.mouth_open
    pts[0:17, 0] = -shape.semi_axes[0] * 0.9 * np.cos(t)
    pts[0:17, 1] = ey + (chin_y - ey) * np.sin(t)
    # Brows: outer to inner on the left, inner to outer on the right.
    by = ey - 0.020 - 0.004 * shape.brow_raise
    bx = np.linspace(-0.016, 0.016, 5)
    pts[17:22] = np.stack([-ex + bx, by - 0.004 * (1 - (bx / 0.018) ** 2)], -1)
    pts[22:27] = np.stack([ex + bx, by - 0.004 * (1 - (bx / 0.018) ** 2)], -1)
    # Nose: bridge from between the eyes to the tip, then the base.
    tip_y = shape.center[1] + 0.35 * shape.semi_axes[1]
    pts[27:31] = np.stack([np.zeros(4), np.linspace(ey, tip_y, 4)], -1)
    pts[31:36] = np.stack([np.linspace(-0.013, 0.013, 5), np.full(5, tip_y + 0.010)], -1)
    pts[[31, 35], 1] -= 0.003
    # Eyes: corners and lids just outside the opening (on the outer skin, not the rim wall).
    m = 0.0006

    def lid(dx, upper):
        h = float(shape.opening_half_height(torch.tensor(dx), torch.tensor(upper)))
        return ey - (h + m) if upper else ey + (h + m)

    third = aw / 3
    for sgn, base in ((-1, 36), (1, 42)):
        cx = sgn * ex
        if sgn < 0:  # 36 outer, 37-38 upper (outer->inner), 39 inner, 40-41 lower (inner->outer)
            order = [(-aw - m, None), (-third, True), (third, True), (aw + m, None), (third, False), (-third, False)]
        else:  # 42 inner, 43-44 upper (inner->outer), 45 outer, 46-47 lower (outer->inner)
            order = [(-aw - m, None), (-third, True), (third, True), (aw + m, None), (third, False), (-third, False)]
        for k, (dx, up) in enumerate(order):
            pts[base + k] = (cx + dx, ey if up is None else lid(dx, up))
    # Lips: outer contour 48-59 and inner 60-67, following smile and mouth_open.
    mw = shape.mouth_width

    def yc(x):
        return float(shape.mouth_centerline(torch.tensor(x)))

    def hopen(x):
        return float(shape.mouth_half_opening(torch.tensor(x)))

    def prof(x):
        return math.sqrt(max(0.0, 1 - (x / (mw * 1.05)) ** 2))

    outer_x = [-mw, -0.6 * mw, -0.25 * mw, 0.0, 0.25 * mw, 0.6 * mw, mw, 0.6 * mw, 0.25 * mw, 0.0, -0.25 * mw,
               -0.6 * mw]
    for k, x in enumerate(outer_x):
        if k in (0, 6):
            pts[48 + k] = (x, yc(x))
        elif k < 6:
            pts[48 + k] = (x, yc(x) - hopen(x) - 0.0045 * prof(x) + 0.0004)
        else:
            pts[48 + k] = (x, yc(x) + hopen(x) + 0.0060 * prof(x) - 0.0004)
    inner_x = [-0.85 * mw, -0.4 * mw, 0.0, 0.4 * mw, 0.85 * mw, 0.4 * mw, 0.0, -0.4 * mw]
    for k, x in enumerate(inner_x):
        if k in (0, 4):
            pts[60 + k] = (x, yc(x))
        elif k < 4:
            pts[60 + k] = (x, yc(x) - hopen(x))
        else:
            pts[60 + k] = (x, yc(x) + hopen(x))
    return pts
