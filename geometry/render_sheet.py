"""Multi-view contact sheet of a mesh through ``render.mesh_gl`` (``python -m geometry render``)."""

from __future__ import annotations

import io
import math
import os

import numpy as np
import torch

from toolkit.cameras import intrinsics_from_fov, look_at
from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_bytes


def orbit_cameras(verts: torch.Tensor, n_views: int, size: int, fov_deg: float = 30.0):
    """``n_views`` cameras on a ring around the mesh (starting frontal, at -z), framing its bounding sphere."""
    lo, hi = verts.min(0).values, verts.max(0).values
    c = (lo + hi) / 2
    r = float((hi - lo).norm()) / 2
    dist = r / math.sin(math.radians(fov_deg) / 2) * 1.05
    K = intrinsics_from_fov(fov_deg, size, size)
    views = []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        eye = c + dist * torch.tensor([math.sin(a), -0.25, -math.cos(a)])
        views.append(look_at(eye, c))
    return torch.stack(views), K


def contact_sheet(verts: torch.Tensor, faces: torch.Tensor, path: str | os.PathLike, *, n_views: int = 6,
                  size: int = 256, cols: int | None = None) -> np.ndarray:
    """Render ``n_views`` shaded views in a grid and write a PNG atomically; returns the [H, W, 3] uint8 image."""
    import imageio.v3 as iio

    from render.mesh_gl import MeshRasterizer

    if n_views < 1 or size < 8:
        raise ToolkitError(f"render: need views >= 1 and size >= 8, got {n_views} and {size}")
    viewmats, K = orbit_cameras(verts.float(), n_views, size)
    r = MeshRasterizer(size, size)
    try:
        outs = r.render_views(verts.float(), faces, viewmats, K.expand(n_views, 3, 3), smooth=True)
    finally:
        r.release()
    cols = cols or min(n_views, 4)
    rows = math.ceil(n_views / cols)
    sheet = np.ones((rows * size, cols * size, 3), np.float32)
    for i, o in enumerate(outs):
        y, x = divmod(i, cols)
        sheet[y * size:(y + 1) * size, x * size:(x + 1) * size] = o["rgb"]
    img = np.clip(np.rint(sheet * 255), 0, 255).astype(np.uint8)
    buf = io.BytesIO()
    iio.imwrite(buf, img, extension=".png")
    atomic_write_bytes(path, buf.getvalue())
    return img
