"""Signed distances to a closed mesh (open3d ray casting) or to an oriented point cloud, the normals of a
point cloud, and area-uniform samples on a mesh: the targets of the mesh and point-cloud fits.

Negative inside, world units. open3d and scipy are imported inside the functions that use them.
"""

from __future__ import annotations

import numpy as np
import torch

from toolkit.errors import ToolkitError

UNIT_RANGE = (1e-6, 1e6)
"""Mesh extents (world units) measured as given; outside, in the mesh's unit frame (float32's range)."""


def mesh_signed_distance(verts: torch.Tensor, faces: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Signed distance of [P, 3] points to a closed mesh (open3d RaycastingScene; negative inside)."""
    try:
        import open3d as o3d
    except ImportError as e:  # pragma: no cover - open3d is a dependency
        raise ToolkitError(f"open3d is needed for mesh signed distances ({e})") from None
    v, p = verts.detach().cpu().double().numpy(), points.detach().cpu().double().numpy()
    extent = float((v.max(0) - v.min(0)).max()) if len(v) else 1.0
    # open3d works in float32: a mesh far from unit size (its squared distances overflow past ~1e19, its signs get
    # lost near 1e-30) is measured in its own unit frame, the distances scaled back in float64; others as given.
    centre, scale = ((v.max(0) + v.min(0)) / 2, extent) if not UNIT_RANGE[0] <= extent <= UNIT_RANGE[1] else (0.0, 1.0)
    scale = scale if scale > 0 else 1.0
    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(((v - centre) / scale).astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(faces.cpu().numpy().astype(np.int32))
    scene.add_triangles(mesh)
    q = o3d.core.Tensor(((p - centre) / scale).astype(np.float32))
    d = scene.compute_signed_distance(q).numpy()
    return torch.from_numpy(d if scale == 1.0 else d.astype(np.float64) * scale).float()


def point_cloud_signed_distance(points: torch.Tensor, normals: torch.Tensor, queries: torch.Tensor,
                                k: int = 8) -> torch.Tensor:
    """Signed distance of queries to an oriented point cloud: distance to the nearest point, with the sign of
    the mean (query - p_i) . n_i over the k nearest (outward normals; negative inside)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points.detach().cpu().double().numpy())
    if k < 1:
        raise ToolkitError(f"point_cloud_signed_distance: k must be >= 1 neighbour, got {k}")
    k = min(k, points.shape[0])  # a cloud of fewer points than k: cKDTree would answer missing neighbours with N
    d, idx = tree.query(queries.detach().cpu().double().numpy(), k=[*range(1, k + 1)])  # a list: [Q, k] at k = 1 too
    idx = torch.from_numpy(idx)
    diff = queries[:, None, :].double() - points.double()[idx]
    side = (diff * normals.double()[idx]).sum(-1).mean(1)
    return (torch.from_numpy(d[:, 0]) * torch.where(side < 0, -1.0, 1.0)).float()


def estimate_normals(points: torch.Tensor, k: int = 16) -> torch.Tensor:
    """Outward unit normals of a closed-surface point cloud (open3d PCA + consistent orientation), from the ``k``
    nearest neighbours of each point, k in [3, 1000]."""
    import open3d as o3d

    if not 3 <= k <= 1000:  # below 3 neighbours no plane is defined (and open3d crashes the process at 0)
        raise ToolkitError(f"estimate_normals: k must be in [3, 1000] neighbours, got {k}")
    points = check_points(points, "points")

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.detach().cpu().double().numpy()))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    try:
        pc.orient_normals_consistent_tangent_plane(k)
    except RuntimeError:  # qhull's triangulation of points that span no volume (a plane, a line)
        raise ToolkitError("estimate_normals: the points lie on a plane or a line, not around a closed surface; "
                           "give points of a closed surface, or their outward normals") from None
    n = torch.from_numpy(np.asarray(pc.normals)).float()
    # Consistent but maybe globally inward: flip if most normals point towards the centroid.
    if float(((points - points.mean(0)) * n).sum(-1).mean()) < 0:
        n = -n
    return n


def surface_samples(verts: torch.Tensor, faces: torch.Tensor, n: int, g: torch.Generator) -> torch.Tensor:
    """[n, 3] points uniform by area on the mesh verts [V, 3] / faces [F, 3] (drawn from ``g``)."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    area = torch.linalg.cross(b - a, c - a).norm(dim=-1)
    if not (bool(torch.isfinite(area).all()) and bool(area.sum() > 0)) and bool(verts.abs().max() > 0):
        # float32 areas of a mesh in units of 1e12 (1e-12) overflow (underflow) and leave no distribution to
        # draw from: relative areas in float64, on edges divided by the mesh's extent.
        extent = (verts.max(0).values - verts.min(0).values).max().double().clamp_min(torch.finfo(torch.float64).tiny)
        area = torch.linalg.cross((b - a).double() / extent, (c - a).double() / extent).norm(dim=-1)
    if not bool(area.sum() > 0):
        raise ToolkitError("fit_mesh: the mesh has zero surface area")
    f = torch.multinomial(area, n, replacement=True, generator=g)
    u, v = torch.rand(n, 1, generator=g), torch.rand(n, 1, generator=g)
    flip = (u + v) > 1
    u, v = torch.where(flip, 1 - u, u), torch.where(flip, 1 - v, v)
    return a[f] + u * (b[f] - a[f]) + v * (c[f] - a[f])


def check_points(p: torch.Tensor, what: str) -> torch.Tensor:
    """``p`` as float32, once it is a floating-point tensor [N >= 4, 3], finite, with a non-zero extent; else a
    ToolkitError naming ``what`` (numpy and trimesh give float64: it is converted, not refused)."""
    if not isinstance(p, torch.Tensor) or not p.is_floating_point():
        got = f"a {p.dtype} tensor" if isinstance(p, torch.Tensor) else f"a {type(p).__name__}"
        raise ToolkitError(f"fit: {what} must be a floating-point torch tensor [N, 3] (torch.from_numpy for a numpy "
                           f"array), got {got}")
    if p.dim() != 2 or p.shape[1] != 3 or p.shape[0] < 4:
        raise ToolkitError(f"fit: {what} must be [N >= 4, 3], got {list(p.shape)}")
    if not bool(torch.isfinite(p).all()):
        raise ToolkitError(f"fit: {what} contain NaN/inf")
    if float((p.max(0).values - p.min(0).values).max()) <= 0:
        raise ToolkitError(f"fit: {what} have zero extent")
    return p.float()


def check_normals(normals: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``normals`` as float32, once they are a floating-point tensor shaped like ``points``, finite and not all
    zero; else a ToolkitError."""
    if not isinstance(normals, torch.Tensor) or not normals.is_floating_point() or normals.shape != points.shape:
        got = list(normals.shape) if isinstance(normals, torch.Tensor) else type(normals).__name__
        raise ToolkitError(f"fit: normals must be a floating-point tensor {list(points.shape)} like the points, got "
                           f"{got}")
    # A zero normal among others is harmless (a query's side is the mean over its neighbours; trimesh gives
    # unreferenced vertices zero normals); all zero, no side is defined.
    if not bool(torch.isfinite(normals).all()) or not bool((normals.norm(dim=-1) > 0).any()):
        raise ToolkitError("fit: normals must be finite and not all zero (outward directions, one per point)")
    return normals.float()
