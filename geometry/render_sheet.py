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
from toolkit.limits import check_allocation, check_count

# A contact sheet is for a person to look at: 256 views already make a 4 x 64 grid. 4096 px views fit every
# GL implementation's framebuffer limit (8192 and up).
MAX_VIEWS = 256
MAX_SIZE = 4096


def check_sheet(n_views, size, names: tuple[str, str] = ("views", "size")) -> tuple[int, int]:
    """The view count and size in range, and what the sheet holds (float32 views, the sheet, its PNG bytes)
    within the memory budget -> (n_views, size) as ints."""
    n_views = check_count(n_views, names[0], 1, MAX_VIEWS, "a number of views")
    size = check_count(size, names[1], 8, MAX_SIZE, "a view size in pixels")
    check_allocation(n_views * size * size * 3 * (4 + 4 + 1 + 1), f"a sheet of {n_views} views of {size} px",
                     f"lower {names[0]} or {names[1]}")
    return n_views, size


def _unit_frame(verts: torch.Tensor) -> torch.Tensor:
    """The mesh centred and scaled to a unit bounding-box diagonal (float64 maths): a view of a mesh does not
    depend on its scale, and GL's float32 would lose a 1e-30 or 1e30 mesh."""
    v = verts.detach().double()
    lo, hi = v.min(0).values, v.max(0).values
    diag = float((hi - lo).norm())
    if not (diag > 0 and torch.isfinite(v).all()):
        raise ToolkitError(f"render: the mesh's bounding box has no extent (diagonal {diag:g}); nothing to frame")
    return ((v - (lo + hi) / 2) / diag).float()


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

    n_views, size = check_sheet(n_views, size)
    cols = check_count(cols, "cols", 1, n_views, "a number of columns") if cols else min(n_views, 4)
    verts = _unit_frame(verts)
    viewmats, K = orbit_cameras(verts, n_views, size)
    r = MeshRasterizer(size, size)
    try:
        outs = r.render_views(verts, faces, viewmats, K.expand(n_views, 3, 3), smooth=True)
    finally:
        r.release()
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
