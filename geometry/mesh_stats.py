"""Mesh inspection and comparison (what ``python -m geometry inspect`` / ``compare`` print); the files
themselves are read and written by :mod:`geometry.mesh_files`.

Watertightness and winding come from trimesh (open3d's checks flag slivers as self-intersections).
Distances for :func:`compare_meshes` are exact point-to-triangle distances from open3d's RaycastingScene
(lazily imported) on area-uniform surface samples.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from geometry.mesh_files import check_mesh
from toolkit.errors import ToolkitError
from toolkit.limits import check_allocation, check_count

# Surface samples per mesh in compare: open3d answers ~1e6 closest-point queries a second on one core, so
# 10^7 is about a minute; each sample holds ~0.5 KiB at the peak (float64 points, normals and temporaries).
MAX_SAMPLES = 10_000_000
BYTES_PER_SAMPLE = 512


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
        # Relative to the diagonal with no absolute floor: a floor would call every face of a tiny mesh degenerate.
        "degenerate_faces": int((area <= 1e-12 * diag**2).sum()),
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


def sample_surface(verts: torch.Tensor, faces: torch.Tensor, n: int, seed: int = 0, name: str = "mesh"
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Area-uniform surface samples -> (points [n, 3] float64, unit face normals [n, 3])."""
    n = check_count(n, "samples", 1, MAX_SAMPLES, "a number of surface samples")
    a, b, c = (verts[faces[:, i]].double() for i in range(3))
    cr = torch.linalg.cross(b - a, c - a)
    area = cr.norm(dim=-1)
    if not bool(area.sum() > 0):
        raise ToolkitError(f"{name}: zero surface area (every triangle is degenerate)")
    g = torch.Generator().manual_seed(seed)
    if area.shape[0] <= 1 << 24:  # torch.multinomial's limit on categories
        idx = torch.multinomial(area, n, replacement=True, generator=g)
    else:
        cdf = area.cumsum(0)
        idx = torch.searchsorted(cdf, torch.rand(n, generator=g, dtype=torch.float64) * cdf[-1]).clamp_max(len(area) - 1)
    u, w = torch.rand(n, 1, generator=g, dtype=torch.float64), torch.rand(n, 1, generator=g, dtype=torch.float64)
    flip = (u + w) > 1
    u, w = torch.where(flip, 1 - u, u), torch.where(flip, 1 - w, w)
    p = a[idx] + u * (b[idx] - a[idx]) + w * (c[idx] - a[idx])
    # Divided by the area itself, not a floor: at a 1e-30 scale every area is below any fixed floor.
    nrm = cr[idx] / torch.where(area[idx] > 0, area[idx], 1.0)[:, None]
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


def _normalized(va: torch.Tensor, vb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Both meshes' vertices moved by the centre of their joint bounding box and divided by its diagonal
    (float64) -> (A, B, the diagonal). open3d measures in float32: in this frame its ~1e-7 relative precision
    holds at any scale (at 1e-30 the raw squared distances underflow, at 1e30 they overflow)."""
    va, vb = va.detach().double(), vb.detach().double()
    lo = torch.minimum(va.min(0).values, vb.min(0).values)
    hi = torch.maximum(va.max(0).values, vb.max(0).values)
    c, s = (lo + hi) / 2, float((hi - lo).norm())
    s = s if s > 0 else 1.0
    return (va - c) / s, (vb - c) / s, s


def compare_meshes(va: torch.Tensor, fa: torch.Tensor, vb: torch.Tensor, fb: torch.Tensor, n_samples: int = 20000,
                   seed: int = 0, names: tuple[str, str] = ("mesh A", "mesh B")) -> dict:
    """Symmetric surface distances between meshes A and B (``names`` name them in errors).

    Returns chamfer (mean of the two mean point-to-surface distances), hausdorff (max of both maxima),
    the same relative to A's bbox diagonal, and normal_consistency (mean |n_A . n_B| at closest points,
    1 = identical orientation field, ignoring the sign so inward/outward winding does not matter).
    """
    check_mesh(va, fa, names[0])
    check_mesh(vb, fb, names[1])
    n_samples = check_count(n_samples, "samples", 1, MAX_SAMPLES, "a number of surface samples")
    check_allocation(2 * n_samples * BYTES_PER_SAMPLE, f"comparing meshes on {n_samples} samples", "lower --samples")
    na_v, nb_v, scale = _normalized(va, vb)
    pa, na = sample_surface(na_v, fa, n_samples, seed, names[0])
    pb, nb = sample_surface(nb_v, fb, n_samples, seed + 1, names[1])
    d_ab, n_ab = _closest(nb_v, fb, pa)
    d_ba, n_ba = _closest(na_v, fa, pb)
    d_ab, d_ba = d_ab * scale, d_ba * scale
    diag = float((va.double().max(0).values - va.double().min(0).values).norm())
    chamfer = 0.5 * (float(d_ab.mean()) + float(d_ba.mean()))
    haus = max(float(d_ab.max()), float(d_ba.max()))
    nc = 0.5 * (float((na * n_ab).sum(-1).abs().mean()) + float((nb * n_ba).sum(-1).abs().mean()))
    rel = diag if diag > 0 else math.nan  # A has area, so a zero diagonal cannot happen
    return {"chamfer": chamfer, "hausdorff": haus, "chamfer_rel_diag": chamfer / rel,
            "hausdorff_rel_diag": haus / rel, "normal_consistency": nc,
            "mean_a_to_b": float(d_ab.mean()), "mean_b_to_a": float(d_ba.mean()), "bbox_diagonal_a": diag,
            "samples": n_samples}
