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

The targets come from ``geometry.silhouettes`` (the visual hull) and ``geometry.surface_distance`` (a mesh
or an oriented point cloud); this module samples them, trains the network and extracts the mesh.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import torch

from geometry.dmtet import grid_bytes
from geometry.mesh_files import check_mesh
from geometry.sdf import SDFNet, SDFNetConfig, SphereInit, extract_mesh, pretrain_sphere
from geometry.silhouettes import Views, hull_bounds, visual_hull_sdf
from geometry.surface_distance import (
    check_normals,
    check_points,
    estimate_normals,
    mesh_signed_distance,
    point_cloud_signed_distance,
    surface_samples,
)
from geometry.tets import GRID_KINDS, MAX_RES
from toolkit.errors import ToolkitError
from toolkit.limits import check_allocation, check_count

# Bounds on the settings: a CPU step on a 1024-point batch takes 10-50 ms, so 100k steps are about an hour;
# each pool point holds ~64 bytes (float32 position and target, sampling temporaries).
MAX_STEPS = 100_000
MAX_BATCH = 1 << 20
MAX_POOL = 50_000_000
POOL_BYTES = 64
MAX_SEED = 2**63 - 2  # the fit seeds torch with seed and seed + 1


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


def _check_real(value, name: str, low: float, high: float, open_low: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not (low < value if open_low else low <= value) or not value <= high:
        raise ToolkitError(f"fit: {name}: expected a number in {'(' if open_low else '['}{low:g}, {high:g}], got {value!r}")


def check_fit_config(cfg: FitConfig) -> None:
    """Refuse counts that would not finish or not fit in memory, and NaN or negative weights, before any work."""
    for name, low, high in (("steps", 0, MAX_STEPS), ("batch", 1, MAX_BATCH), ("pool", 16, MAX_POOL),
                            ("eikonal_batch", 0, MAX_BATCH), ("laplacian_every", 1, MAX_STEPS),
                            ("laplacian_res", 2, MAX_RES), ("extract_res", 2, MAX_RES),
                            ("max_bad_steps", 0, MAX_STEPS), ("pretrain_steps", 0, MAX_STEPS), ("seed", 0, MAX_SEED)):
        check_count(getattr(cfg, name), f"fit: {name}", low, high)
    if cfg.grid_kind not in GRID_KINDS:
        raise ToolkitError(f"fit: grid_kind: expected one of {GRID_KINDS}, got {cfg.grid_kind!r}")
    _check_real(cfg.lr, "lr", 0, 10, open_low=True)
    _check_real(cfg.truncation, "truncation", 0, 1e6, open_low=True)
    _check_real(cfg.grad_clip, "grad_clip", 0, 1e6, open_low=True)
    for name in ("w_sdf", "w_landmarks", "w_eikonal", "w_laplacian"):
        _check_real(getattr(cfg, name), name, 0, 1e6)
    check_allocation(cfg.pool * POOL_BYTES, f"fit: a sample pool of {cfg.pool} points", "lower pool")
    check_allocation(grid_bytes(cfg.grid_kind, cfg.extract_res, cfg.net.feature_dim),
                     f"fit: extracting the mesh on a {cfg.grid_kind} grid of {cfg.extract_res}", "lower extract_res")


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
    check_fit_config(cfg)
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
    check_fit_config(cfg)
    if landmarks is not None:
        landmarks = torch.as_tensor(landmarks, dtype=torch.float32).reshape(-1, 3)
        if not bool(torch.isfinite(landmarks).all()):
            raise ToolkitError("fit_silhouettes: landmarks contain NaN/inf")
    if box is None:
        box = hull_bounds(views, landmarks)
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


# ---------------------------------------------------------------------------------------- mesh / points
def fit_mesh(verts: torch.Tensor, faces: torch.Tensor, cfg: FitConfig | None = None, *,
             landmarks: torch.Tensor | None = None, log=None) -> FitResult:
    """Fit the SDF network to a closed triangle mesh (signed distances from open3d)."""
    cfg = cfg or FitConfig(w_eikonal=0.0)
    check_fit_config(cfg)
    verts = check_points(verts, "mesh vertices")
    check_mesh(verts, faces, "fit_mesh")
    lo, hi = verts.min(0).values, verts.max(0).values
    cfg = _box_config(cfg, lo, hi)
    g = torch.Generator().manual_seed(cfg.seed)
    surface = surface_samples(verts, faces, 20_000, g)
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
    check_fit_config(cfg)
    points = check_points(points, "point cloud")
    normals = estimate_normals(points) if normals is None else check_normals(normals, points)
    lo, hi = points.min(0).values, points.max(0).values
    cfg = _box_config(cfg, lo, hi)
    g = torch.Generator().manual_seed(cfg.seed)
    box = (torch.tensor(cfg.net.box_min), torch.tensor(cfg.net.box_max))
    band = 0.1 * float(hi.sub(lo).max())
    pts, sdf = _sample_pool(*box, lambda q: point_cloud_signed_distance(points, normals, q), cfg.pool, band, g, points)
    c = points.mean(0)
    return fit_sdf_to_targets(pts, sdf, cfg, sphere=SphereInit(tuple(c.tolist()), float((points - c).norm(dim=-1).mean())),
                              log=log)


__all__ = ["FitConfig", "FitResult", "check_fit_config", "fit_silhouettes", "fit_mesh", "fit_points", "fit_sdf_to_targets"]
