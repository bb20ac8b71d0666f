"""Calibrated silhouettes: the views, the 2D signed distance of a mask, the approximate SDF of their visual
hull, its bounds, and the IoU of a mesh's silhouettes against them.

Cameras as ``toolkit.cameras``: OpenCV axes, viewmats world-to-camera [4, 4], Ks [3, 3] in pixels, pixel
(i, j) centred at (j + 0.5, i + 0.5). Distances are positive outside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from toolkit.errors import ToolkitError


def mask_signed_distance(mask: np.ndarray) -> np.ndarray:
    """[H, W] bool mask -> [H, W] float32 signed distance in pixels to its boundary (positive outside)."""
    import cv2

    m = np.ascontiguousarray(mask.astype(np.uint8))
    if not m.any():
        raise ToolkitError("mask_signed_distance: a head mask is empty")
    d_out = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    if m.all():  # no boundary inside the image: the nearest one known is just beyond the image's edge
        d_in = cv2.distanceTransform(np.pad(m, 1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    else:
        d_in = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # The boundary lies half a pixel between the last inside and the first outside pixel centre.
    return np.where(m > 0, 0.5 - d_in, d_out - 0.5).astype(np.float32)


@dataclass
class Views:
    """Calibrated silhouettes: masks [N, H, W] bool, Ks [N, 3, 3], viewmats [N, 4, 4] (world -> camera)."""

    masks: torch.Tensor
    Ks: torch.Tensor
    viewmats: torch.Tensor

    def __post_init__(self) -> None:
        n = self.masks.shape[0] if self.masks.dim() == 3 else -1
        if n < 1 or self.Ks.shape != (n, 3, 3) or self.viewmats.shape != (n, 4, 4):
            raise ToolkitError(f"Views: expected masks [N, H, W], Ks [N, 3, 3], viewmats [N, 4, 4]; got "
                               f"{list(self.masks.shape)}, {list(self.Ks.shape)}, {list(self.viewmats.shape)}")
        if not (torch.isfinite(self.Ks).all() and torch.isfinite(self.viewmats).all()):
            raise ToolkitError("Views: camera matrices contain NaN/inf")
        self.masks = self.masks.bool()
        self.Ks = self.Ks.float()
        self.viewmats = self.viewmats.float()

    def __len__(self) -> int:
        return self.masks.shape[0]

    def subset(self, idx) -> "Views":
        return Views(self.masks[idx], self.Ks[idx], self.viewmats[idx])


def visual_hull_sdf(points: torch.Tensor, views: Views, chunk: int = 65536) -> torch.Tensor:
    """[P, 3] world points -> [P] approximate signed distance to the visual hull (world units, + outside).

    Per view: the mask's 2D signed distance at the projection (bilinear; beyond the image border the
    distance keeps growing, as the masks are assumed to contain the whole head), times depth / focal length.
    Views that see a point behind the camera ignore it, and so do views whose mask touches the border,
    for points beyond it. Max over views = intersection of the cones.
    """
    sds = [torch.from_numpy(mask_signed_distance(m.numpy())) for m in views.masks]
    # A mask that touches the image border may have cut the head off: beyond such a border the view
    # has no evidence (the point is not carved by it); otherwise the distance keeps growing out there.
    cut = [bool(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()) for m in views.masks]
    H, W = views.masks.shape[1:]
    out = []
    for i in range(0, points.shape[0], chunk):
        p = points[i:i + chunk].float()
        best = torch.full((p.shape[0],), -float("inf"))
        for v in range(len(views)):
            R, t = views.viewmats[v, :3, :3], views.viewmats[v, :3, 3]
            pc = p @ R.T + t
            z = pc[:, 2]
            K = views.Ks[v]
            zs = z.clamp_min(1e-6)
            u = K[0, 0] * pc[:, 0] / zs + K[0, 1] * pc[:, 1] / zs + K[0, 2]
            w = K[1, 1] * pc[:, 1] / zs + K[1, 2]
            # Pixel centres are at +0.5: continuous coordinate u maps to column u - 0.5.
            cu, cw = (u - 0.5).clamp(0, W - 1), (w - 0.5).clamp(0, H - 1)
            beyond = torch.sqrt((u - 0.5 - cu) ** 2 + (w - 0.5 - cw) ** 2)
            d_px = _bilinear(sds[v], cu, cw) + beyond
            world_per_px = zs / (0.5 * (K[0, 0] + K[1, 1])) / R.det().abs().pow(1 / 3).clamp_min(1e-12)
            seen = z > 1e-6
            if cut[v]:
                seen &= beyond == 0
            d = torch.where(seen, d_px * world_per_px, torch.full_like(z, -float("inf")))
            best = torch.maximum(best, d)
        out.append(best)
    d = torch.cat(out)
    if bool(torch.isinf(d).any()):  # behind every camera: no evidence; call it outside
        d = torch.where(torch.isinf(d), torch.full_like(d, float(d[torch.isfinite(d)].abs().max()) if torch.isfinite(d).any() else 1.0), d)
    return d


def _bilinear(img: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Sample [H, W] at continuous column x, row y (already clamped to the image)."""
    H, W = img.shape
    x0 = x.floor().long().clamp(0, W - 1)
    y0 = y.floor().long().clamp(0, H - 1)
    x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
    fx, fy = x - x0, y - y0
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def silhouette_iou(verts: torch.Tensor, faces: torch.Tensor, views: Views) -> list[float]:
    """IoU of the mesh's silhouette (rendered with render.mesh_gl, exact pixel-centre coverage) per view."""
    from render.mesh_gl import MeshRasterizer

    H, W = views.masks.shape[1:]
    r = MeshRasterizer(W, H)
    try:
        outs = r.render_views(verts.detach().float(), faces, views.viewmats, views.Ks)
    finally:
        r.release()
    ious = []
    for out, gt in zip(outs, views.masks):
        m = torch.from_numpy(np.asarray(out["mask"])).bool()
        ious.append(float((m & gt).sum()) / max(float((m | gt).sum()), 1.0))
    return ious


def hull_bounds(views: Views, landmarks: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds of the visual hull, carved on a coarse grid around a guessed centre."""
    if landmarks is not None and landmarks.shape[0] >= 2:
        c = landmarks.mean(0)
        size = float((landmarks.max(0).values - landmarks.min(0).values).max()) * 3
    else:  # the point closest to all optical axes
        A = torch.zeros(3, 3)
        b = torch.zeros(3)
        for V in views.viewmats:
            R, t = V[:3, :3], V[:3, 3]
            o = -R.T @ t / R.det().abs().pow(1 / 3)
            d = torch.nn.functional.normalize(R[2], dim=0)
            P = torch.eye(3) - torch.outer(d, d)
            A += P
            b += P @ o
        c = torch.linalg.lstsq(A, b[:, None]).solution[:, 0]
        size = float(min((-(V[:3, :3].T @ V[:3, 3]) - c).norm() for V in views.viewmats))
    for _ in range(4):  # grow the search box until the hull does not touch it
        r = torch.linspace(-size / 2, size / 2, 48)
        grid = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3) + c
        inside = visual_hull_sdf(grid, views) < 0
        if not bool(inside.any()):
            raise ToolkitError("fit_silhouettes: the visual hull is empty near the cameras' target")
        p = grid[inside]
        lo, hi = p.min(0).values, p.max(0).values
        touches = bool(((lo - grid.min(0).values) < size / 47 * 1.5).any() or ((grid.max(0).values - hi) < size / 47 * 1.5).any())
        if not touches:
            break
        size *= 1.6
    step = size / 47
    return lo - step, hi + step
