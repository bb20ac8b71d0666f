"""Mesh I/O, inspection and comparison (what ``python -m geometry inspect`` / ``compare`` print).

Watertightness and winding come from trimesh (open3d's checks flag slivers as self-intersections).
Distances for :func:`compare_meshes` are exact point-to-triangle distances from open3d's RaycastingScene
(lazily imported) on area-uniform surface samples.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_bytes, check_readable_file

MESH_EXTENSIONS = (".ply", ".obj", ".stl", ".off", ".glb")


def check_mesh(verts: torch.Tensor, faces: torch.Tensor, name: str = "mesh") -> None:
    """Raise a ToolkitError for wrong shapes, an empty mesh, NaN/inf vertices or out-of-range faces."""
    if verts.dim() != 2 or verts.shape[1] != 3 or faces.dim() != 2 or faces.shape[1] != 3:
        raise ToolkitError(f"{name}: expected verts [V, 3] and faces [F, 3], got {list(verts.shape)} and {list(faces.shape)}")
    if verts.shape[0] == 0 or faces.shape[0] == 0:
        raise ToolkitError(f"{name}: empty mesh ({verts.shape[0]} vertices, {faces.shape[0]} faces)")
    bad = ~torch.isfinite(verts).all(1)
    if bool(bad.any()):
        raise ToolkitError(f"{name}: {int(bad.sum())} vertices have NaN/inf coordinates")
    if int(faces.min()) < 0 or int(faces.max()) >= verts.shape[0]:
        raise ToolkitError(f"{name}: face indices must be in [0, {verts.shape[0]}), got [{int(faces.min())}, {int(faces.max())}]")


def load_mesh(path: str | os.PathLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a triangle mesh file -> (verts [V, 3] float32, faces [F, 3] int64), validated."""
    import trimesh

    path = check_readable_file(path, "mesh file")
    try:
        m = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for unknown or garbled files
        raise ToolkitError(f"{path}: not a readable mesh ({type(e).__name__}: {str(e)[:120]})") from None
    if not isinstance(m, trimesh.Trimesh):
        raise ToolkitError(f"{path}: not a triangle mesh (got {type(m).__name__})")
    if len(m.faces) == 0:  # trimesh turns a point cloud into an empty mesh
        raise ToolkitError(f"{path}: no triangles (a point cloud? a Gaussian scene reads with `python -m toolkit info`)")
    verts = torch.tensor(np.asarray(m.vertices), dtype=torch.float32).reshape(-1, 3)
    faces = torch.tensor(np.asarray(m.faces), dtype=torch.long).reshape(-1, 3)
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


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges [E, 2] and how many faces use each [E] (int64 keys, no row-unique)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    e.sort(1)
    n = int(faces.max()) + 1
    keys, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)
    return np.stack([keys // n, keys % n], 1), counts


def inspect_mesh(verts: torch.Tensor, faces: torch.Tensor) -> dict:
    """Topology and geometry statistics of a triangle mesh, as a JSON-able dict."""
    import trimesh

    check_mesh(verts, faces)
    v = verts.detach().cpu().double().numpy()
    f = faces.cpu().numpy().astype(np.int64)
    m = trimesh.Trimesh(v, f, process=False)
    edges, counts = _edges(f)
    lengths = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    lo, hi = v.min(0), v.max(0)
    diag = float(np.linalg.norm(hi - lo))
    area = m.area_faces
    used = np.unique(f)
    n_comp = len(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(f)), min_len=1))
    watertight = bool(m.is_watertight)
    euler = int(len(used) - len(edges) + len(f))
    stats = {
        "vertices": int(v.shape[0]),
        "unreferenced_vertices": int(v.shape[0] - len(used)),
        "faces": int(f.shape[0]),
        "edges": int(len(edges)),
        "components": n_comp,
        "watertight": watertight,
        "winding_consistent": bool(m.is_winding_consistent),
        "boundary_edges": int((counts == 1).sum()),
        "non_manifold_edges": int((counts > 2).sum()),
        "euler_characteristic": euler,
        "genus": int((2 * n_comp - euler) // 2) if watertight else None,
        "area": float(area.sum()),
        "volume": float(m.volume) if watertight else None,
        "orientation": ("outward" if m.volume > 0 else "inward") if watertight and m.is_winding_consistent else None,
        "bbox_min": lo.tolist(),
        "bbox_max": hi.tolist(),
        "bbox_diagonal": diag,
        "edge_length": {"min": float(lengths.min()), "mean": float(lengths.mean()), "max": float(lengths.max())},
        "degenerate_faces": int((area <= 1e-12 * max(diag, 1e-12) ** 2).sum()),
    }
    return stats


def format_stats(stats: dict) -> str:
    """Human-readable lines for :func:`inspect_mesh` output."""
    lines = []
    for k, v in stats.items():
        if isinstance(v, dict):
            v = ", ".join(f"{a} {b:.4g}" for a, b in v.items())
        elif isinstance(v, list):
            v = "[" + ", ".join(f"{x:.4g}" for x in v) + "]"
        elif isinstance(v, float):
            v = f"{v:.6g}"
        lines.append(f"{k:<22} {v}")
    return "\n".join(lines)


def sample_surface(verts: torch.Tensor, faces: torch.Tensor, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Area-uniform surface samples -> (points [n, 3], face normals [n, 3])."""
    a, b, c = (verts[faces[:, i]].double() for i in range(3))
    cr = torch.linalg.cross(b - a, c - a)
    area = cr.norm(dim=-1)
    if not bool(area.sum() > 0):
        raise ToolkitError("mesh has zero surface area")
    g = torch.Generator().manual_seed(seed)
    idx = torch.multinomial(area, n, replacement=True, generator=g)
    u, w = torch.rand(n, 1, generator=g, dtype=torch.float64), torch.rand(n, 1, generator=g, dtype=torch.float64)
    flip = (u + w) > 1
    u, w = torch.where(flip, 1 - u, u), torch.where(flip, 1 - w, w)
    p = a[idx] + u * (b[idx] - a[idx]) + w * (c[idx] - a[idx])
    nrm = cr[idx] / area[idx].clamp_min(1e-30)[:, None]
    return p, nrm


def _closest(verts: torch.Tensor, faces: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact distances from q [P, 3] to the mesh surface and the unit normal of the closest triangle."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(verts.detach().cpu().numpy().astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(faces.cpu().numpy().astype(np.int32))
    scene.add_triangles(mesh)
    res = scene.compute_closest_points(o3d.core.Tensor(q.cpu().numpy().astype(np.float32)))
    pts = torch.from_numpy(res["points"].numpy()).double()
    fid = torch.from_numpy(res["primitive_ids"].numpy().astype(np.int64))
    a, b, c = (verts[faces[:, i]].double() for i in range(3))
    fn = torch.nn.functional.normalize(torch.linalg.cross(b - a, c - a), dim=-1)
    return (pts - q.double()).norm(dim=-1), fn[fid]


def compare_meshes(va: torch.Tensor, fa: torch.Tensor, vb: torch.Tensor, fb: torch.Tensor, n_samples: int = 20000,
                   seed: int = 0) -> dict:
    """Symmetric surface distances between meshes A and B.

    Returns chamfer (mean of the two mean point-to-surface distances), hausdorff (max of both maxima),
    the same relative to A's bbox diagonal, and normal_consistency (mean |n_A . n_B| at closest points,
    1 = identical orientation field, ignoring the sign so inward/outward winding does not matter).
    """
    check_mesh(va, fa, "mesh A")
    check_mesh(vb, fb, "mesh B")
    pa, na = sample_surface(va, fa, n_samples, seed)
    pb, nb = sample_surface(vb, fb, n_samples, seed + 1)
    d_ab, n_ab = _closest(vb, fb, pa)
    d_ba, n_ba = _closest(va, fa, pb)
    diag = float((va.max(0).values - va.min(0).values).norm())
    chamfer = 0.5 * (float(d_ab.mean()) + float(d_ba.mean()))
    haus = max(float(d_ab.max()), float(d_ba.max()))
    nc = 0.5 * (float((na * n_ab).sum(-1).abs().mean()) + float((nb * n_ba).sum(-1).abs().mean()))
    return {"chamfer": chamfer, "hausdorff": haus, "chamfer_rel_diag": chamfer / max(diag, 1e-30),
            "hausdorff_rel_diag": haus / max(diag, 1e-30), "normal_consistency": nc,
            "mean_a_to_b": float(d_ab.mean()), "mean_b_to_a": float(d_ba.mean()), "bbox_diagonal_a": diag,
            "samples": n_samples}
