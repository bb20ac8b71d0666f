"""Differentiable pure-PyTorch 3D Gaussian splatting (CPU and CUDA from the same code).

Public API (gsplat-style, plain tensors): :func:`rasterize` and :func:`render_scene`.

Conventions (gsplat >= 1.6 / the original 3DGS rasterizer):

- OpenCV camera axes, ``viewmats`` world-to-camera; pixel (row i, column j) is sampled at (j + 0.5, i + 0.5).
- Quaternions wxyz, normalized internally (zero -> identity); Sigma = R S S^T R^T with activated scales.
- EWA projection with the Jacobian taken at the mean's tangent clamped to +-(c/f + 0.3 tan(half fov)) around
  the principal point; cov2d + eps2d I (dilation); conic = inverse of the dilated cov2d; per-axis radius
  ceil(3.33 sqrt(cov2d_ii)); culled (radius 0) where ``render.cull`` drops it (the rule the preview splatter
  shares: non-finite or degenerate parameters, z <= near or z >= far, a footprint too large for float32 or
  too thin to invert) or the box is off-image.
- alpha = min(0.99, o exp(-sigma)), sigma = 0.5 (a dx^2 + c dy^2) + b dx dy, dx = pixel - mean; a Gaussian is
  skipped for a pixel when sigma < 0 or alpha < 1/255; Gaussians are composited front to back by camera
  depth; a pixel stops before the Gaussian that would bring T (1 - alpha) <= 1e-4 (that one excluded).
- render C = sum_i c_i alpha_i T_i + T_final bg; alpha = 1 - T_final; optional depth = sum_i z_i alpha_i T_i.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import torch

from render._raster import ALPHA_MAX, ALPHA_MIN, T_MIN, RasterConfig, RasterizeTiles
from render._tiles import bin_gaussians
from render.cull import finite_scales
from render.gsplat_backend import rasterize_gsplat, use_gsplat
from render.projection import project_gaussians
from render.sh import sh_to_color
from toolkit.errors import ToolkitError

__all__ = ["rasterize", "render_scene", "ALPHA_MIN", "ALPHA_MAX", "T_MIN"]

# Conics whose correlation b^2 / (a c) exceeds this are so thin that float rounding can make sigma < 0;
# only then is the per-pixel sigma < 0 test (one extra pass) switched on.
_THIN_CORRELATION = 1.0 - 1e-3


def _check_shape(name: str, t: Any, shape: Sequence[int | None]) -> None:
    ok = isinstance(t, torch.Tensor) and t.dim() == len(shape) and all(
        s is None or t.shape[i] == s for i, s in enumerate(shape))
    if not ok:
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        got = list(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
        raise ToolkitError(f"rasterize: {name} expected shape {want}, got {got}")
    if not t.is_floating_point():
        raise ToolkitError(f"rasterize: {name} expected a floating-point tensor, got {t.dtype}")


def _check_finite(named: dict[str, torch.Tensor]) -> None:
    # One device sync for all inputs; the per-field scan only runs once something is wrong.
    # Cameras may sit on another device than the Gaussians (rasterize moves them): gather on the first's.
    dev = next(iter(named.values())).device
    flags = torch.stack([torch.isfinite(t).all().to(dev) for t in named.values() if t.numel()] or
                        [torch.tensor(True)])
    if bool(flags.all()):
        return
    for name, t in named.items():
        if t.numel() and not bool(torch.isfinite(t).all()):
            raise ToolkitError(f"rasterize: {name} contains NaN or inf values (pass check_finite=False to skip)")


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    *,
    backgrounds: torch.Tensor | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int = 8,
    sh_degree: int | None = None,
    return_depth: bool = False,
    check_finite: bool = True,
    chunk: int | None = None,
    max_elements: int = 1 << 21,
    alpha_min: float = ALPHA_MIN,
    t_min: float = T_MIN,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Render N Gaussians into C cameras (conventions in the module docstring).

    Args:
        means [N, 3], quats [N, 4] wxyz (any norm), scales [N, 3] activated, opacities [N] in [0, 1]; or each
            with a leading camera axis ([C, N, 3], [C, N, 4], [C, N, 3], [C, N]: camera c renders its own
            Gaussian set c, e.g. a batch of differently posed heads, still in one call and one tile sweep).
        features [N, D] or per camera [C, N, D] (per camera always, with per-camera Gaussians); with
            ``sh_degree`` SH coefficients [N, K, D] evaluated toward each camera as max(SH + 0.5, 0).
        viewmats [C, 4, 4] world-to-camera, Ks [C, 3, 3] pixels, width / height in pixels.
        backgrounds [C, D] (or [D]), default zeros.
        tile_size: square tile edge in pixels; chunk: Gaussians per tile per round (None: ``render._raster.auto_chunk``, longer
            on small images where per-round overhead dominates); max_elements bounds
            tiles x chunk x pixels per batched step (peak memory); alpha_min / t_min: the 1/255 and 1e-4
            thresholds (knobs for benchmarking; the defaults are the reference).
        check_finite: raise ToolkitError on NaN/inf inputs (one check per call).

    Returns:
        render [C, H, W, D], alpha [C, H, W, 1], meta with radii [C, N, 2] int32 (0 = culled), means2d [C, N, 2],
        depths [C, N], conics [C, N, 3], ``depth`` [C, H, W, 1] when ``return_depth`` (sum z_i w_i; divide by
        alpha for the expected depth) and ``counters`` (ints over all cameras: visible, intersections,
        candidate_intersections, tiles_skipped, tiles_terminated, pixels_terminated, and rounds of the one
        sweep that renders every camera's tiles together).
    """
    per_camera, backgrounds = _check_inputs(means, quats, scales, opacities, features, viewmats, Ks, width, height,
                                            backgrounds, sh_degree, tile_size, chunk, alpha_min, t_min, check_finite,
                                            (eps2d, near_plane, far_plane))
    width, height = int(width), int(height)
    C, D = viewmats.shape[0], features.shape[-1]
    dtype = means.dtype

    if use_gsplat(means, features, sh_degree):  # CUDA tensors and gsplat installed: its kernels (gsplat_backend)
        return rasterize_gsplat(means, quats, scales, opacities, features, viewmats, Ks, width, height,
                                backgrounds=backgrounds, per_camera=per_camera, near_plane=near_plane,
                                far_plane=far_plane, eps2d=eps2d, tile_size=tile_size, sh_degree=sh_degree,
                                return_depth=return_depth)
    viewmats, Ks = viewmats.to(means.device, dtype), Ks.to(means.device, dtype)
    proj = project_gaussians(means, quats.to(dtype), scales.to(dtype), viewmats, Ks, width, height, eps2d=eps2d,
                             near_plane=near_plane, far_plane=far_plane)
    colors = _colors(features, sh_degree, means, viewmats)
    opac = opacities.to(dtype)
    cfg = RasterConfig(chunk=None if chunk is None else int(chunk), max_elements=int(max_elements), alpha_min=float(alpha_min),
                       t_min=float(t_min))
    cam, ids = _visible_by_depth(proj, opac, per_camera, cfg.alpha_min)
    m2d, con, op, col = _gather_visible(proj, opac, colors, cam, ids, per_camera, return_depth)
    bg = backgrounds.to(means.device, dtype) if backgrounds is not None else colors.new_zeros(C, D)
    if return_depth:
        bg = torch.cat([bg, bg.new_zeros(C, 1)], -1)
    bins, thin = _tile_bins(proj, cam, ids, m2d, con, op, width, height, tile_size, cfg.alpha_min)
    stats: dict[str, int] = {}
    img, alpha = RasterizeTiles.apply(m2d, con, op, col, bg, bins, width, height, cfg, thin, stats)
    counters = dict(visible=int(ids.numel()), intersections=bins.n_pairs, candidate_intersections=bins.n_candidates,
                    tiles_skipped=int((bins.counts == 0).sum()), **stats)
    meta: dict[str, Any] = dict(radii=proj.radii, means2d=proj.means2d, depths=proj.depths, conics=proj.conics,
                                counters=counters, tile_size=int(tile_size))
    if return_depth:
        meta["depth"] = img[..., D:]
    return img[..., :D], alpha, meta


def _check_inputs(means, quats, scales, opacities, features, viewmats, Ks, width, height, backgrounds, sh_degree,
                  tile_size, chunk, alpha_min, t_min, check_finite, planes) -> tuple[bool, torch.Tensor | None]:
    """Shapes, dtypes and settings of a :func:`rasterize` call, and (``check_finite``) finite inputs ->
    (per-camera Gaussians?, backgrounds [C, D])."""
    _check_shape("viewmats", viewmats, (None, 4, 4))
    C = viewmats.shape[0]
    if C < 1:
        raise ToolkitError("rasterize: viewmats expected at least one camera [C >= 1, 4, 4], got 0")
    _check_shape("Ks", Ks, (C, 3, 3))
    per_camera = isinstance(means, torch.Tensor) and means.dim() == 3
    lead = (C,) if per_camera else ()
    _check_shape("means", means, (*lead, None, 3))
    n = means.shape[-2]
    _check_shape("quats", quats, (*lead, n, 4))
    _check_shape("scales", scales, (*lead, n, 3))
    _check_shape("opacities", opacities, (*lead, n))
    if means.dtype == torch.float16:  # its range (65504) overflows the footprints' pixel radii
        raise ToolkitError("rasterize: means expected float32, float64 or bfloat16, got float16; pass .float()")
    if per_camera and sh_degree is not None:
        raise ToolkitError("rasterize: sh_degree needs one Gaussian set for all cameras (means [N, 3]); with "
                           "per-camera means [C, N, 3] pass per-camera features [C, N, D]")
    if per_camera:
        _check_shape("features", features, (C, n, None))
    elif sh_degree is not None:
        _check_shape("features (SH coefficients)", features, (n, None, None))
    elif features.dim() == 3:
        _check_shape("features", features, (C, n, None))
    else:
        _check_shape("features", features, (n, None))
    D = features.shape[-1]
    if backgrounds is not None:
        if isinstance(backgrounds, torch.Tensor) and backgrounds.dim() == 1:
            _check_shape("backgrounds", backgrounds, (D,))
            backgrounds = backgrounds.expand(C, D)
        _check_shape("backgrounds", backgrounds, (C, D))
    if int(width) < 1 or int(height) < 1:
        raise ToolkitError(f"rasterize: width and height must be >= 1, got {width}x{height}")
    if int(tile_size) < 1 or (chunk is not None and int(chunk) < 1):
        raise ToolkitError(f"rasterize: tile_size and chunk must be >= 1, got {tile_size}, {chunk}")
    if not 0 < alpha_min < ALPHA_MAX or not 0 <= t_min < 1:
        raise ToolkitError(f"rasterize: need 0 < alpha_min < {ALPHA_MAX} and 0 <= t_min < 1")
    eps2d, near_plane, far_plane = planes
    if not 0 <= eps2d < math.inf or not 0 <= near_plane < far_plane:  # NaN fails every comparison
        raise ToolkitError(f"rasterize: need a finite eps2d >= 0 and 0 <= near_plane < far_plane, got eps2d={eps2d}, "
                           f"near_plane={near_plane}, far_plane={far_plane}")
    if check_finite:
        named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "features": features,
                 "viewmats": viewmats, "Ks": Ks, **({} if backgrounds is None else {"backgrounds": backgrounds})}
        _check_finite(named)
    return per_camera, backgrounds


def _colors(features: torch.Tensor, sh_degree: int | None, means: torch.Tensor, viewmats: torch.Tensor
            ) -> torch.Tensor:
    """Per-Gaussian colours in the means' dtype: the features [N, D] / [C, N, D], or with ``sh_degree`` the
    SH coefficients [N, K, D] evaluated toward each camera centre -> [C, N, D]."""
    dtype = means.dtype
    if sh_degree is None:
        return features.to(means.device, dtype)
    centers = -torch.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])
    return sh_to_color(int(sh_degree), features.to(dtype), means, centers)  # [C, N, D]


@torch.no_grad()
def _tile_bins(proj, cam, ids, m2d, con, op, width: int, height: int, tile_size: int, alpha_min: float):
    """(Gaussian-tile pairs of the visible list, whether any conic is so thin that the per-pixel sigma < 0
    test is needed); ``cam``, ``ids`` [M] the visible list, the rest [M, ...] from :func:`_gather_visible`."""
    bins = bin_gaussians(m2d.detach(), con.detach(), proj.cov2d[cam, ids].detach(), op.detach(), width, height,
                         tile_size, alpha_min, image_ids=cam, num_images=proj.depths.shape[0])
    cd = con.detach()
    thin = bool((cd[:, 1] ** 2 > _THIN_CORRELATION * cd[:, 0] * cd[:, 2]).any()) if ids.numel() else False
    return bins, thin


@torch.no_grad()
def _visible_by_depth(proj, opac: torch.Tensor, per_camera: bool, alpha_min: float
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Every camera's visible Gaussians, depth-sorted per camera, in one list (camera after camera) ->
    (camera [M], Gaussian id [M]): one tile sweep then renders the whole batch, and no step loops over cameras.
    Visible: not culled and opacity above ``alpha_min``; ties in depth keep index order."""
    C, n = proj.depths.shape
    opac_c = opac if per_camera else opac[None].expand(C, n)  # [C, N]
    vis = (proj.radii > 0).all(-1) & (opac_c > alpha_min)
    order = torch.argsort(torch.where(vis, proj.depths, torch.full_like(proj.depths, float("inf"))), dim=1,
                          stable=True)  # visible first, by depth, ties in index order
    n_vis = vis.sum(1)
    dev = proj.depths.device  # the means' device
    keep = torch.arange(n, device=dev)[None, :] < n_vis[:, None]
    cam = torch.arange(C, device=dev)[:, None].expand(C, n)[keep]
    return cam, order[keep]


def _gather_visible(proj, opac, colors, cam, ids, per_camera: bool, return_depth: bool):
    """The tile rasterizer's inputs for the visible list (differentiable) -> means2d [M, 2], conics [M, 3],
    opacities [M] and colours [M, D], with the camera depth as channel D + 1 when ``return_depth``."""
    m2d = proj.means2d[cam, ids]
    con = proj.conics[cam, ids]
    op = opac[cam, ids] if per_camera else opac.index_select(0, ids)
    col = colors[cam, ids] if colors.dim() == 3 else colors.index_select(0, ids)
    if return_depth:
        col = torch.cat([col, proj.depths[cam, ids][:, None]], -1)
    return m2d, con, op, col


def render_scene(scene, cameras, *, use_sh: bool | None = None, **kw) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render a ``toolkit.scene.GaussianScene`` into one ``toolkit.cameras.Camera`` or a list of them
    (all the same size). Uses the activated scene fields; SH colours when the scene has ``sh`` (unless
    ``use_sh=False``), else ``features``. ``kw`` goes to :func:`rasterize`. Returns (render, alpha, meta)."""
    from toolkit.cameras import Camera

    cams = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise ToolkitError("render_scene: cameras must be a Camera or a non-empty list of Camera")
    sizes = {(c.width, c.height) for c in cams}
    if len(sizes) != 1:
        raise ToolkitError(f"render_scene: all cameras must share one image size, got {sorted(sizes)}")
    (w, h), = sizes
    dev, dtype = scene.means.device, scene.means.dtype
    viewmats = torch.stack([c.viewmat for c in cams]).to(dev, dtype)
    Ks = torch.stack([c.K for c in cams]).to(dev, dtype)
    sh = scene.sh is not None and use_sh is not False
    if use_sh and scene.sh is None:
        raise ToolkitError("render_scene: use_sh=True but the scene has no 'sh' field")
    feats = scene.sh if sh else scene.features
    # A finite log-scale can still overflow float32 when activated: culled as huge, not refused as inf.
    return rasterize(scene.means, scene.unit_quats, finite_scales(scene.scales), scene.opacities, feats, viewmats,
                     Ks, w, h, sh_degree=scene.sh_degree if sh else None, **kw)
