"""Fit the SDF network to multi-view silhouettes (+ 3D landmarks) or directly to a mesh / point cloud.

**Silhouette term: carving on sampled points, not a soft silhouette of the extracted mesh.** Each view's
mask gives a 2D signed distance (pixels, positive outside); lifted to the sample's depth it bounds the
distance to that view's silhouette cone, and the maximum over views is an approximate SDF of the visual
hull. The network regresses that (truncated) target on batches of points drawn from a precomputed pool.
Why this and not the soft-silhouette IoU of the DMTet mesh:

- cost: a step evaluates the MLP on a few thousand points; a soft silhouette needs the whole grid through
  the MLP plus a differentiable rasterizer per view (render/mesh_gl is OpenGL and not differentiable,
  and a SoftRas-style torch rasterizer is O(pixels x faces)) - far outside a 5-minute CPU budget;
- gradients everywhere: every sample gets a target, not only the mesh vertices near silhouette edges, so
  the fit cannot stall on an empty or inverted intermediate mesh (no "marching tets returned nothing");
- the targets are computed once per fit (all views projected once), so steps do not touch the images.

What silhouettes cannot see (concavities such as the eye sockets) is pulled in by the landmark term
(SDF = 0 at the 3D landmarks). A uniform-Laplacian smoothness term on the (differentiably) extracted DMTet
mesh and an optional eikonal term keep the surface regular. Every step checks that the loss and the
gradients are finite (a non-finite step is skipped and counted; too many in a row is a ToolkitError naming
the term) and clips the gradient norm.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
import torch

from geometry.sdf import SDFNet, SDFNetConfig, SphereInit, extract_mesh, pretrain_sphere
from toolkit.errors import ToolkitError


@dataclass
class FitConfig:
    """Optimisation settings shared by the silhouette and the mesh/point-cloud fits."""

    steps: int = 300
    """Optimiser steps after the sphere pre-training."""
    batch: int = 1024
    """Sample points per step."""
    lr: float = 1e-3
    pool: int = 60_000
    """Precomputed labelled sample points (uniform in the box + concentrated near the surface)."""
    truncation: float = 0.1
    """SDF targets are clamped to +-truncation x box half-size: the fit focuses on the surface band."""
    w_sdf: float = 1.0
    w_landmarks: float = 1.0
    w_eikonal: float = 0.02
    """0 disables the eikonal term (|grad sdf| = 1, on ``eikonal_batch`` of the step's points)."""
    eikonal_batch: int = 256
    w_laplacian: float = 0.0
    """Uniform-Laplacian smoothness of the extracted DMTet mesh, applied every ``laplacian_every`` steps."""
    laplacian_every: int = 10
    laplacian_res: int = 32
    grad_clip: float = 1.0
    max_bad_steps: int = 20
    """Consecutive non-finite steps tolerated (skipped) before raising."""
    extract_res: int = 64
    """Grid resolution of the final mesh."""
    grid_kind: str = "kuhn"
    pretrain_steps: int = 100
    seed: int = 0
    net: SDFNetConfig = field(default_factory=SDFNetConfig)


@dataclass
class FitResult:
    net: SDFNet
    verts: torch.Tensor
    faces: torch.Tensor
    history: list[dict]
    seconds: float
    skipped_steps: int


# ---------------------------------------------------------------------------------------- silhouettes
def mask_signed_distance(mask: np.ndarray) -> np.ndarray:
    """[H, W] bool mask -> [H, W] float32 signed distance in pixels to its boundary (positive outside)."""
    import cv2

    m = np.ascontiguousarray(mask.astype(np.uint8))
    if not m.any():
        raise ToolkitError("mask_signed_distance: a head mask is empty")
    d_out = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
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


# ---------------------------------------------------------------------------------------- core loop
def _sample_pool(box_min: torch.Tensor, box_max: torch.Tensor, target: Callable[[torch.Tensor], torch.Tensor],
                 n: int, band: float, g: torch.Generator, surface: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform points in the box plus points jittered around the surface (given or found by the target)."""
    n_uni = n // 3
    uni = box_min + torch.rand(n_uni, 3, generator=g) * (box_max - box_min)
    d_uni = target(uni)
    if surface is None:  # near-surface seeds: uniform samples inside the band
        seeds = uni[d_uni.abs() < band]
        if seeds.shape[0] < 16:
            seeds = uni[d_uni.abs().argsort()[:256]]
    else:
        seeds = surface
    k = n - n_uni
    pick = torch.randint(0, seeds.shape[0], (k,), generator=g)
    sigma = torch.where(torch.rand(k, 1, generator=g) < 0.5, torch.tensor(band * 0.1), torch.tensor(band * 0.5))
    near = seeds[pick] + torch.randn(k, 3, generator=g) * sigma
    near = torch.maximum(torch.minimum(near, box_max), box_min)
    pts = torch.cat([uni, near])
    return pts, torch.cat([d_uni, target(near)])


def _laplacian_loss(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Mean squared uniform-Laplacian of a triangle mesh's vertices."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = torch.cat([e, e.flip(1)])
    n = verts.shape[0]
    nb_sum = torch.zeros_like(verts).index_add_(0, e[:, 0], verts[e[:, 1]])
    deg = torch.zeros(n, dtype=verts.dtype).index_add_(0, e[:, 0], torch.ones(e.shape[0], dtype=verts.dtype))
    lap = verts - nb_sum / deg.clamp_min(1)[:, None]
    return lap.square().sum(-1).mean()


def fit_sdf_to_targets(pool_pts: torch.Tensor, pool_sdf: torch.Tensor, cfg: FitConfig, *,
                       landmarks: torch.Tensor | None = None, sphere: SphereInit | None = None,
                       log: Callable[[str], None] | None = None) -> FitResult:
    """Train an SDFNet on (points [P, 3], target sdf [P]) pairs + landmarks; extract the final mesh."""
    t0 = time.perf_counter()
    if pool_pts.shape[0] != pool_sdf.shape[0] or not bool(torch.isfinite(pool_sdf).all()):
        raise ToolkitError("fit: sample targets must be finite, one per point")
    torch.manual_seed(cfg.seed)
    net = SDFNet(cfg.net)
    if sphere is not None and cfg.pretrain_steps > 0:
        sphere.steps = cfg.pretrain_steps
        sphere.batch = cfg.batch
        sphere.lr = max(sphere.lr, cfg.lr)
        if log is not None:  # the first fit step's line comes only after this
            log(f"pre-training the SDF on a sphere: {sphere.steps} steps of {sphere.batch} points")
        pretrain_sphere(net, sphere)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(cfg.steps, 1), eta_min=cfg.lr * 0.05)
    g = torch.Generator().manual_seed(cfg.seed + 1)
    tau = cfg.truncation * float(net.scale)
    target_all = pool_sdf.clamp(-tau, tau)
    history, bad, skipped = [], 0, 0
    for step in range(cfg.steps):
        idx = torch.randint(0, pool_pts.shape[0], (cfg.batch,), generator=g)
        sdf = net.sdf(pool_pts[idx])
        terms = {"sdf": (sdf.clamp(-tau, tau) - target_all[idx]).abs().mean() / net.scale}
        if landmarks is not None and cfg.w_landmarks > 0:
            terms["landmarks"] = net.sdf(landmarks).abs().mean() / net.scale
        if cfg.w_eikonal > 0:  # on a small subset: the double backward costs ~3 forward passes per point
            x = pool_pts[idx[: cfg.eikonal_batch]].clone().requires_grad_(True)
            (grad,) = torch.autograd.grad(net.sdf(x).sum(), x, create_graph=True)
            terms["eikonal"] = (grad.norm(dim=-1) - 1).square().mean()
        if cfg.w_laplacian > 0 and step % cfg.laplacian_every == 0:
            try:
                mv, mf, _ = extract_mesh(net, cfg.laplacian_res, cfg.grid_kind, differentiable=True)
                terms["laplacian"] = _laplacian_loss(mv / net.scale, mf) * cfg.laplacian_res**2
            except ToolkitError:
                pass  # no surface yet at this resolution: the SDF term will create one
        weights = {"sdf": cfg.w_sdf, "landmarks": cfg.w_landmarks, "eikonal": cfg.w_eikonal, "laplacian": cfg.w_laplacian}
        loss = sum(weights[k] * v for k, v in terms.items())
        opt.zero_grad(set_to_none=True)
        bad_terms = [k for k, v in terms.items() if not bool(torch.isfinite(v))]
        if not bad_terms:
            loss.backward()
            gnorm = torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.grad_clip)
            if not bool(torch.isfinite(gnorm)):
                bad_terms = ["gradient"]
        if bad_terms:
            bad += 1
            skipped += 1
            if bad > cfg.max_bad_steps:
                raise ToolkitError(f"fit: {bad} consecutive non-finite steps (terms {bad_terms}) at step {step}; "
                                   "lower the learning rate or check the input data")
            opt.zero_grad(set_to_none=True)
            continue
        bad = 0
        opt.step()
        sched.step()
        if step % 50 == 0 or step == cfg.steps - 1:
            rec = {"step": step, "loss": float(loss.detach()), **{k: float(v.detach()) for k, v in terms.items()}}
            history.append(rec)
            if log:
                log(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in rec.items()))
    verts, faces, _ = extract_mesh(net, cfg.extract_res, cfg.grid_kind)
    return FitResult(net, verts.detach(), faces, history, time.perf_counter() - t0, skipped)


def _box_config(cfg: FitConfig, lo: torch.Tensor, hi: torch.Tensor, margin: float = 0.15) -> FitConfig:
    """Copy of cfg whose network box is the (cubic) bounds lo..hi grown by ``margin`` of their size."""
    c = (lo + hi) / 2
    h = float((hi - lo).max()) / 2 * (1 + margin)
    net = SDFNetConfig(**{**asdict(cfg.net), "box_min": tuple((c - h).tolist()), "box_max": tuple((c + h).tolist()),
                          "grid_res": cfg.extract_res})
    return FitConfig(**{**{k: getattr(cfg, k) for k in cfg.__dataclass_fields__}, "net": net})


def fit_silhouettes(views: Views, cfg: FitConfig | None = None, *, landmarks: torch.Tensor | None = None,
                    box: tuple[torch.Tensor, torch.Tensor] | None = None, log=None) -> FitResult:
    """Fit to calibrated silhouettes (+ optional [L, 3] landmarks on the surface, world frame).

    ``box`` (lo [3], hi [3]) bounds the object; by default it is found by carving a coarse grid around
    the landmarks / the cameras' common target.
    """
    cfg = cfg or FitConfig()
    if landmarks is not None:
        landmarks = torch.as_tensor(landmarks, dtype=torch.float32).reshape(-1, 3)
        if not bool(torch.isfinite(landmarks).all()):
            raise ToolkitError("fit_silhouettes: landmarks contain NaN/inf")
    if box is None:
        box = _hull_bounds(views, landmarks)
    cfg = _box_config(cfg, torch.as_tensor(box[0]).float(), torch.as_tensor(box[1]).float())
    lo, hi = torch.tensor(cfg.net.box_min), torch.tensor(cfg.net.box_max)
    g = torch.Generator().manual_seed(cfg.seed)
    band = 0.1 * float((hi - lo).max())
    pts, sdf = _sample_pool(lo, hi, lambda p: visual_hull_sdf(p, views), cfg.pool, band, g)
    inside = sdf < 0
    if not bool(inside.any()):
        raise ToolkitError("fit_silhouettes: no sample lies inside every silhouette; the cameras or masks disagree")
    c = pts[inside].mean(0)
    r = float((pts[inside] - c).norm(dim=-1).mean())
    return fit_sdf_to_targets(pts, sdf, cfg, landmarks=landmarks, sphere=SphereInit(tuple(c.tolist()), r), log=log)


def _hull_bounds(views: Views, landmarks: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
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


# ---------------------------------------------------------------------------------------- mesh / points
def mesh_signed_distance(verts: torch.Tensor, faces: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Signed distance of [P, 3] points to a closed mesh (open3d RaycastingScene; negative inside)."""
    try:
        import open3d as o3d
    except ImportError as e:  # pragma: no cover - open3d is a dependency
        raise ToolkitError(f"open3d is needed for mesh signed distances ({e})") from None
    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(verts.detach().cpu().numpy().astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(faces.cpu().numpy().astype(np.int32))
    scene.add_triangles(mesh)
    q = o3d.core.Tensor(points.detach().cpu().numpy().astype(np.float32))
    return torch.from_numpy(scene.compute_signed_distance(q).numpy()).float()


def point_cloud_signed_distance(points: torch.Tensor, normals: torch.Tensor, queries: torch.Tensor,
                                k: int = 8) -> torch.Tensor:
    """Signed distance of queries to an oriented point cloud: distance to the nearest point, with the sign of
    the mean (query - p_i) . n_i over the k nearest (outward normals; negative inside)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points.detach().cpu().double().numpy())
    d, idx = tree.query(queries.detach().cpu().double().numpy(), k=k)
    idx = torch.from_numpy(idx)
    diff = queries[:, None, :].double() - points.double()[idx]
    side = (diff * normals.double()[idx]).sum(-1).mean(1)
    return (torch.from_numpy(d[:, 0]) * torch.where(side < 0, -1.0, 1.0)).float()


def fit_mesh(verts: torch.Tensor, faces: torch.Tensor, cfg: FitConfig | None = None, *,
             landmarks: torch.Tensor | None = None, log=None) -> FitResult:
    """Fit the SDF network to a closed triangle mesh (signed distances from open3d)."""
    cfg = cfg or FitConfig(w_eikonal=0.0)
    _check_points(verts, "mesh vertices")
    lo, hi = verts.min(0).values, verts.max(0).values
    cfg = _box_config(cfg, lo, hi)
    g = torch.Generator().manual_seed(cfg.seed)
    surface = _surface_samples(verts, faces, 20_000, g)
    box = (torch.tensor(cfg.net.box_min), torch.tensor(cfg.net.box_max))
    band = 0.1 * float(hi.sub(lo).max())
    pts, sdf = _sample_pool(*box, lambda p: mesh_signed_distance(verts, faces, p), cfg.pool, band, g, surface)
    c = verts.mean(0)
    return fit_sdf_to_targets(pts, sdf, cfg, landmarks=landmarks,
                              sphere=SphereInit(tuple(c.tolist()), float((verts - c).norm(dim=-1).mean())), log=log)


def fit_points(points: torch.Tensor, normals: torch.Tensor | None = None, cfg: FitConfig | None = None, *,
               log=None) -> FitResult:
    """Fit to a point cloud [P, 3]; normals [P, 3] (outward) are estimated with open3d when absent."""
    cfg = cfg or FitConfig()
    _check_points(points, "point cloud")
    if normals is None:
        normals = estimate_normals(points)
    lo, hi = points.min(0).values, points.max(0).values
    cfg = _box_config(cfg, lo, hi)
    g = torch.Generator().manual_seed(cfg.seed)
    box = (torch.tensor(cfg.net.box_min), torch.tensor(cfg.net.box_max))
    band = 0.1 * float(hi.sub(lo).max())
    pts, sdf = _sample_pool(*box, lambda q: point_cloud_signed_distance(points, normals, q), cfg.pool, band, g, points)
    c = points.mean(0)
    return fit_sdf_to_targets(pts, sdf, cfg, sphere=SphereInit(tuple(c.tolist()), float((points - c).norm(dim=-1).mean())),
                              log=log)


def estimate_normals(points: torch.Tensor, k: int = 16) -> torch.Tensor:
    """Outward unit normals of a closed-surface point cloud (open3d PCA + consistent orientation)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.detach().cpu().double().numpy()))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    pc.orient_normals_consistent_tangent_plane(k)
    n = torch.from_numpy(np.asarray(pc.normals)).float()
    # Consistent but maybe globally inward: flip if most normals point towards the centroid.
    if float(((points - points.mean(0)) * n).sum(-1).mean()) < 0:
        n = -n
    return n


def _surface_samples(verts: torch.Tensor, faces: torch.Tensor, n: int, g: torch.Generator) -> torch.Tensor:
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    area = torch.linalg.cross(b - a, c - a).norm(dim=-1)
    if not bool(area.sum() > 0):
        raise ToolkitError("fit_mesh: the mesh has zero surface area")
    f = torch.multinomial(area, n, replacement=True, generator=g)
    u, v = torch.rand(n, 1, generator=g), torch.rand(n, 1, generator=g)
    flip = (u + v) > 1
    u, v = torch.where(flip, 1 - u, u), torch.where(flip, 1 - v, v)
    return a[f] + u * (b[f] - a[f]) + v * (c[f] - a[f])


def _check_points(p: torch.Tensor, what: str) -> None:
    if p.dim() != 2 or p.shape[1] != 3 or p.shape[0] < 4:
        raise ToolkitError(f"fit: {what} must be [N >= 4, 3], got {list(p.shape)}")
    if not bool(torch.isfinite(p).all()):
        raise ToolkitError(f"fit: {what} contain NaN/inf")
    if float((p.max(0).values - p.min(0).values).max()) <= 0:
        raise ToolkitError(f"fit: {what} have zero extent")


__all__ = ["FitConfig", "FitResult", "Views", "fit_silhouettes", "fit_mesh", "fit_points", "fit_sdf_to_targets",
           "visual_hull_sdf", "mask_signed_distance", "mesh_signed_distance", "silhouette_iou"]
