"""What the mesh rasterizer (``render.mesh_gl``) is given, checked and turned into float32/int64 numpy arrays,
and the normals it shades with.

Every function raises a ToolkitError naming the argument, its expected shape and what it got. Inputs may be
numpy arrays, torch tensors (any device) or nested sequences.
"""

from __future__ import annotations

import numpy as np
import torch

from toolkit.errors import ToolkitError

DEFAULT_COLOR = (0.8, 0.8, 0.8)
MAX_FACES = 1 << 24  # triangle ids travel through a float32 channel: exact below 2^24


def as_array(x, name: str, dtype) -> np.ndarray:
    """A contiguous numpy array of ``dtype`` from an array, a tensor or a sequence."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        return np.ascontiguousarray(np.asarray(x), dtype=dtype)
    except (TypeError, ValueError) as e:
        raise ToolkitError(f"{name}: expected a numeric array, got {type(x).__name__} ({e})") from e


def check_shape(a: np.ndarray, name: str, shape: tuple) -> None:
    """``a`` has ``shape`` (None: any size on that axis) and, when floating, only finite values."""
    ok = a.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, a.shape, strict=False))
    if not ok:
        want = "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"
        raise ToolkitError(f"{name}: expected shape {want}, got {list(a.shape)}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ToolkitError(f"{name}: contains NaN or inf")


def mesh_arrays(verts, faces) -> tuple[np.ndarray, np.ndarray]:
    """-> verts [V, 3] float32, faces [F, 3] int64 indexing them; a non-empty mesh below ``MAX_FACES`` faces."""
    v = as_array(verts, "verts", np.float32)
    f_raw = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    if f_raw.size and f_raw.dtype.kind not in "iu":
        raise ToolkitError(f"faces: expected integer vertex indices, got dtype {f_raw.dtype}")
    f = np.ascontiguousarray(f_raw, dtype=np.int64)
    check_shape(v, "verts", (None, 3))
    check_shape(f, "faces", (None, 3))
    if v.shape[0] == 0 or f.shape[0] == 0:
        raise ToolkitError(f"mesh is empty ({v.shape[0]} vertices, {f.shape[0]} faces); nothing to render")
    if f.shape[0] >= MAX_FACES:
        raise ToolkitError(f"faces: at most {MAX_FACES - 1} faces supported, got {f.shape[0]}")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ToolkitError(f"faces: indices must be in [0, {v.shape[0] - 1}], got [{f.min()}, {f.max()}]")
    return v, f


def camera_arrays(viewmats, Ks) -> tuple[np.ndarray, np.ndarray]:
    """-> viewmats [C, 4, 4], Ks [C, 3, 3] float32."""
    views = as_array(viewmats, "viewmats", np.float32)
    check_shape(views, "viewmats", (None, 4, 4))
    Kn = as_array(Ks, "Ks", np.float32)
    check_shape(Kn, "Ks", (views.shape[0], 3, 3))
    return views, Kn


def check_render_options(near: float, far: float, ambient: float, background, supersample) -> tuple[np.ndarray, int]:
    """Check the clip range, the ambient share and the supersampling -> (background [3] float32, supersample)."""
    if not (0 < near < far) or not np.isfinite(far):
        raise ToolkitError(f"near/far: expected 0 < near < far < inf, got near={near}, far={far}")
    if not 0.0 <= float(ambient) <= 1.0:
        raise ToolkitError(f"ambient: expected a value in [0, 1], got {ambient}")
    bg = as_array(background, "background", np.float32).reshape(-1)
    if bg.shape != (3,) or not np.isfinite(bg).all():
        raise ToolkitError(f"background: expected 3 finite RGB values, got {list(bg.shape)}")
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) \
            or supersample < 1 or supersample % 2 == 0:
        raise ToolkitError(f"supersample: expected an odd integer >= 1 (samples per pixel side), got {supersample!r}")
    return bg, int(supersample)


def surface_arrays(n_verts: int, colors, uvs, texture) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """-> (albedo [V, 3], uvs [V, 2], texture [h, w, 3] float32 in [0, 1] or None).

    Without ``colors`` every vertex is ``DEFAULT_COLOR``; without ``texture`` the uvs are zeros (unused).
    A uint8 texture is scaled by 1/255.
    """
    if colors is not None:
        col = as_array(colors, "colors", np.float32)
        check_shape(col, "colors", (n_verts, 3))
    else:
        col = np.broadcast_to(np.asarray(DEFAULT_COLOR, np.float32), (n_verts, 3))
    if texture is None:
        return col, np.zeros((n_verts, 2), np.float32), None
    if uvs is None:
        raise ToolkitError("texture given without uvs: pass uvs [V, 2]")
    uv = as_array(uvs, "uvs", np.float32)
    check_shape(uv, "uvs", (n_verts, 2))
    tex = texture.detach().cpu().numpy() if isinstance(texture, torch.Tensor) else np.asarray(texture)
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
        raise ToolkitError(f"texture: expected shape [h, w, 3], got {list(tex.shape)}")
    tex = tex.astype(np.float32) / 255.0 if tex.dtype == np.uint8 else tex.astype(np.float32)
    if not np.isfinite(tex).all():
        raise ToolkitError("texture: contains NaN or inf")
    return col, uv, tex


def light_directions(light_dir, n_views: int) -> np.ndarray:
    """None (a headlight, (0, 0, -1)), [3] (one for all views) or [C, 3] -> [C, 3] unit camera-space directions."""
    if light_dir is None:
        return np.tile(np.array([[0.0, 0.0, -1.0]], np.float32), (n_views, 1))
    lights = as_array(light_dir, "light_dir", np.float32)
    lights = np.tile(lights.reshape(1, -1), (n_views, 1)) if lights.size == 3 else lights
    norms = np.linalg.norm(lights, axis=-1) if lights.ndim == 2 and lights.shape[-1] == 3 else None
    if lights.shape != (n_views, 3) or not np.isfinite(lights).all() or (norms < 1e-12).any():
        raise ToolkitError(f"light_dir: expected finite non-zero 3-vectors, [3] or [{n_views}, 3]")
    return lights / norms[:, None]


def face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3], [F, 3] -> [F, 3] unit normals (right-hand rule over the face's vertex order)."""
    v = verts.astype(np.float64)
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3], [F, 3] -> [V, 3] area-weighted unit vertex normals (zero for unused vertices)."""
    v = verts.astype(np.float64)
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])  # length = 2 * area
    out = np.zeros_like(v)
    for k in range(3):
        np.add.at(out, faces[:, k], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-30)
