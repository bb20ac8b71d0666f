"""Triangle-mesh files: strict OBJ / OFF / PLY readers, STL and GLB through trimesh, atomic writes
(:func:`load_mesh`, :func:`save_mesh`) and the checks every mesh passes (:func:`check_mesh`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from geometry.mesh_readers import NO_TRIANGLES, READERS, read_with_trimesh
from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_bytes, check_readable_file

MESH_EXTENSIONS = (".ply", ".obj", ".stl", ".off", ".glb")


def check_mesh(verts: torch.Tensor, faces: torch.Tensor, name: str = "mesh") -> None:
    """Raise a ToolkitError for wrong shapes, an empty mesh, NaN/inf vertices or out-of-range faces."""
    if faces.is_floating_point() or faces.dtype == torch.bool:
        raise ToolkitError(f"{name}: faces must be integer vertex indices, got {faces.dtype}")
    if verts.dim() != 2 or verts.shape[1] != 3 or faces.dim() != 2 or faces.shape[1] != 3:
        raise ToolkitError(f"{name}: expected verts [V, 3] and faces [F, 3], got {list(verts.shape)} and {list(faces.shape)}")
    if verts.shape[0] == 0 or faces.shape[0] == 0:
        raise ToolkitError(f"{name}: empty mesh ({verts.shape[0]} vertices, {faces.shape[0]} faces)")
    bad = ~torch.isfinite(verts).all(1)
    if bool(bad.any()):
        raise ToolkitError(f"{name}: {int(bad.sum())} vertices have NaN/inf coordinates")
    if int(faces.min()) < 0 or int(faces.max()) >= verts.shape[0]:
        raise ToolkitError(f"{name}: face indices must be in [0, {verts.shape[0]}), got [{int(faces.min())}, {int(faces.max())}]")

_F32_MAX = float(np.finfo(np.float32).max)


def load_mesh(path: str | os.PathLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a triangle mesh file -> (verts [V, 3] float32, faces [F, 3] int64), validated: finite vertices in
    float32's range, every face index in range, at least one triangle (polygons are fan-triangulated)."""
    path = check_readable_file(path, "mesh file")
    ext = path.suffix.lower()
    if ext not in MESH_EXTENSIONS:
        raise ToolkitError(f"{path}: unknown mesh extension {ext!r}; expected one of {MESH_EXTENSIONS}")
    data = path.read_bytes()
    v, f, where = READERS.get(ext, read_with_trimesh)(path, data)
    if f.shape[0] == 0:  # a point cloud, or a header with no faces
        raise ToolkitError(f"{path}: {NO_TRIANGLES}")
    bad = np.flatnonzero(~np.isfinite(v).all(1))
    if bad.size:
        raise ToolkitError(f"{path}: {where(int(bad[0]))}: vertex coordinates must be finite, got "
                           f"{v[bad[0]].tolist()} ({bad.size} NaN/inf vertices)")
    big = np.flatnonzero((np.abs(v) > _F32_MAX).any(1))
    if big.size:  # meshes are float32 from here on: such a vertex would become inf
        raise ToolkitError(f"{path}: {where(int(big[0]))}: vertex coordinate {np.abs(v[big[0]]).max():.3g} is "
                           f"outside float32's range (|x| <= {_F32_MAX:.3g})")
    verts, faces = torch.from_numpy(v).float(), torch.from_numpy(np.ascontiguousarray(f, np.int64))
    check_mesh(verts, faces, str(path))
    return verts, faces


def check_mesh_extension(path: str | os.PathLike) -> None:
    """Raise a ToolkitError unless ``path``'s extension is a mesh format :func:`save_mesh` writes."""
    ext = Path(path).suffix.lower()
    if ext not in MESH_EXTENSIONS:
        raise ToolkitError(f"{path}: unknown mesh extension {ext!r}; expected one of {MESH_EXTENSIONS}")


def save_mesh(path: str | os.PathLike, verts: torch.Tensor, faces: torch.Tensor) -> None:
    """Write a mesh atomically; the format follows the extension (.ply binary, .obj, .stl, .off, .glb)."""
    import trimesh

    path = Path(path)
    check_mesh_extension(path)
    check_mesh(verts, faces, str(path))
    m = trimesh.Trimesh(verts.detach().cpu().double().numpy(), faces.cpu().numpy(), process=False)
    data = m.export(file_type=path.suffix.lower()[1:])
    atomic_write_bytes(path, data.encode() if isinstance(data, str) else data)
