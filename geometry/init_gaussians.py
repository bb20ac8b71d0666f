"""Neutral head mesh (+ 68 iBUG landmarks) -> the initial two-stream GaussianScene.

- Points: the mesh vertices (or ``n_points`` area-uniform surface samples).
- Eyes, each on its own (GazeGaussian's reference code used the left set for both eyes, a bug):
  left = landmarks 36–41 (the eye on the image's left, part 1), right = 42–47 (part 2). Each eyeball's
  centre and radius are fitted (``toolkit.eyes.fit_sphere``) to the mesh points inside that eye's lid
  polygon; when those points do not determine a plausible sphere, an anatomical prior is used (radius
  0.4 x eye width, centre behind the lid centroid along the head's inward axis). Gaze rotates each eye
  about this centre, so it is stored in ``metadata["eyes"]`` in the format of ``toolkit.eyes``.
- Partition: a point is eye when it lies on its eyeball's shell and near that eye's landmarks.
- Features: the SDF network's 128-d feature at each point (``feature_kind = "neural"``); without a
  network, mid-grey RGB.
- Scales: from the mean distance to the 3 nearest neighbours of the same part. Face Gaussians are
  anisotropic: per axis, the RMS neighbour offset along that axis (rotations stay identity, so the axes
  are the head frame's; a patch of the flat front of the face gets thin along z), clamped to
  [0.2, 1] x the mean distance. Eye Gaussians are isotropic.
- Lids (``lid_points`` > 0): face Gaussians on a shell just in front of each eyeball, outside the lid
  landmarks' polygon, opacity 0.9 and half the neighbour rule's scale (neighbours among the lids, so the
  mesh points' scales do not change).
- Opacity 0.3 face / 0.9 eye; identity rotations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.eyes import fit_sphere
from toolkit.limits import check_allocation, check_count
from toolkit.procedural import knn_spacing
from toolkit.scene import PART_FACE, PART_LEFT_EYE, PART_RIGHT_EYE, GaussianScene

PART_LID = -1  # lid points while the scene is assembled; they become face Gaussians
LEFT_EYE = list(range(36, 42))
RIGHT_EYE = list(range(42, 48))
INWARD = torch.tensor([0.0, 0.0, 1.0])  # the face looks towards -z (README conventions)
# Gaussians a count setting may ask for: a head scene is ~10^5; each point costs ~0.5 KiB while the scene is
# built (float32 fields, the neighbour search's float64 copies and index arrays).
MAX_POINTS = 10_000_000  # also geometry.mesh_stats.MAX_SAMPLES, the most surface samples drawn
BYTES_PER_POINT = 512


@dataclass
class InitConfig:
    """Gaussian initialization parameters."""

    n_points: int | None = None
    """None: one Gaussian per mesh vertex; else area-uniform surface samples."""
    opacity_face: float = 0.3
    opacity_eye: float = 0.9
    eye_radius_ratio: float = 0.4
    """Prior eyeball radius as a fraction of the eye width (corner 36-39 / 42-45 distance): ~12 mm / 30 mm."""
    shell_tolerance: float = 0.35
    """A point is on the eyeball shell when | |p - c| - r | < tolerance x r."""
    min_eye_points: int = 32
    """Eyes with fewer mesh points are topped up with samples on the eyeball's front cap."""
    eye_points: int = 0
    """> 0: each eye is exactly this many Gaussians spread evenly (Fibonacci lattice) over its eyeball's front
    cap of half-angle ``eye_cap_deg``; the mesh points on that eye's shell are dropped. A mesh samples the
    eyes as sparsely as the cheeks (~40 points per eye from 6000 on a head), too coarse to carry an iris
    and a pupil; gaze can only be read off an eyeball whose colours resolve them."""
    eye_cap_deg: float = 60.0
    lid_points: int = 0
    """> 0 (with ``eye_points``): each eye's lids as face Gaussians, this many lattice points on a shell
    ``lid_offset`` x radius in front of the eyeball's cap of half-angle ``lid_cap_deg``, less those inside
    the eye's landmark polygon (the opening; head-frame x, y). The mesh points dropped with the eyeball's
    shell band include the lids, and without them every eyeball shows as a full round disc where the data
    shows an almond opening."""
    lid_offset: float = 0.1
    lid_cap_deg: float = 75.0
    lid_opening: float = 1.15
    """the opening: the lid landmarks' polygon scaled by this about its centroid (six landmarks cut the
    almond's curves short)."""
    lid_scale: float = 0.5
    """lid Gaussians' scales x this after the neighbour rule (among the lids) and the mesh face's floor: at
    the rule's size their tails close most of the opening."""
    opacity_lid: float = 0.9
    seed: int = 0


def _polygon_contains(poly: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Even-odd test of [P, 2] points in a closed [K, 2] polygon."""
    inside = torch.zeros(pts.shape[0], dtype=torch.bool)
    k = poly.shape[0]
    for i in range(k):
        a, b = poly[i], poly[(i + 1) % k]
        cond = (a[1] > pts[:, 1]) != (b[1] > pts[:, 1])
        xint = a[0] + (pts[:, 1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1] + 1e-30)
        inside ^= cond & (pts[:, 0] < xint)
    return inside


def lid_polygon(eye_lmk: torch.Tensor, scale: float) -> torch.Tensor:
    """[6, 2] the lid landmarks' polygon [6, 3] in the head's frontal (x, y) plane, scaled about its centroid."""
    xy = eye_lmk[:, :2]
    return (xy - xy.mean(0)) * scale + xy.mean(0)


def fit_eyeball(points: torch.Tensor, eye_lmk: torch.Tensor, cfg: InitConfig) -> dict:
    """Eyeball {"center", "radius", "fit"} for one eye from mesh points and its 6 lid landmarks [6, 3]."""
    width = float((eye_lmk[0] - eye_lmk[3]).norm())
    if not width > 0:
        raise ToolkitError("init_gaussians: eye corner landmarks coincide; cannot size the eyeball")
    r_prior = cfg.eye_radius_ratio * width
    lid_c = eye_lmk.mean(0)
    poly = lid_polygon(eye_lmk, 1.2)  # dilated by 20 %
    near = (points[:, 2] - lid_c[2]).abs() < r_prior
    cand = points[near & _polygon_contains(poly, points[:, :2])]
    prior_c = lid_c + INWARD * (r_prior * 0.8)  # the cornea bulges ~0.2 r in front of the lid plane
    if cand.shape[0] >= 8:
        try:
            c, r = fit_sphere(cand)
            ok = (0.5 * r_prior < float(r) < 2.0 * r_prior) and float((c - lid_c) @ INWARD) > 0
            if ok:
                return {"center": c, "radius": r, "fit": f"sphere to {cand.shape[0]} points"}
        except ToolkitError:
            pass
    return {"center": prior_c, "radius": torch.tensor(r_prior), "fit": f"prior ({cand.shape[0]} points in the lids)"}


def _cap_points(center: torch.Tensor, radius: float, cap_fraction: torch.Tensor, ang: torch.Tensor,
                cap_deg: float) -> torch.Tensor:
    """Points on the eyeball's front (-z) cap of half-angle ``cap_deg``: ``cap_fraction`` in [0, 1] is the
    share of the cap's area nearer the front (equal steps are equal areas), ``ang`` the turn about the axis."""
    cos_t = 1 - cap_fraction * (1 - np.cos(np.radians(cap_deg)))
    sin_t = torch.sqrt((1 - cos_t**2).clamp_min(0))
    d = torch.stack([sin_t * torch.cos(ang), sin_t * torch.sin(ang), -cos_t], -1).float()
    return center + radius * d


def _front_cap(center: torch.Tensor, radius: float, n: int, g: torch.Generator, cap_deg: float = 40.0) -> torch.Tensor:
    u = torch.rand(n, generator=g)
    return _cap_points(center, radius, u, torch.rand(n, generator=g) * 2 * np.pi, cap_deg)


def _fibonacci_cap(center: torch.Tensor, radius: float, n: int, cap_deg: float) -> torch.Tensor:
    """``n`` points spread evenly over the front cap (a Fibonacci lattice: golden-angle turns), deterministic."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    return _cap_points(center, radius, i / n, i * np.pi * (3 - np.sqrt(5)), cap_deg)


def lid_shell(center: torch.Tensor, radius: float, eye_lmk: torch.Tensor, cfg: InitConfig) -> torch.Tensor:
    """[P, 3] lid points of one eye: the ``cfg.lid_points`` lattice on the shell of radius (1 + lid_offset) x
    ``radius`` over the front cap, without the points inside the lid polygon (landmarks [6, 3], head x, y)."""
    shell = _fibonacci_cap(center, radius * (1 + cfg.lid_offset), cfg.lid_points, cfg.lid_cap_deg)
    return shell[~_polygon_contains(lid_polygon(eye_lmk, cfg.lid_opening), shell[:, :2])]


def _anisotropic_scales(p: torch.Tensor, k: int = 3) -> torch.Tensor:
    from scipy.spatial import cKDTree

    pts = p.detach().double().numpy()
    d, idx = cKDTree(pts).query(pts, k=k + 1)
    mean_d = torch.from_numpy(d[:, 1:].mean(1)).float().clamp_min(1e-7)
    off = p[torch.from_numpy(idx[:, 1:])] - p[:, None, :]  # [P, k, 3]
    per_axis = off.square().mean(1).sqrt()
    return torch.maximum(torch.minimum(per_axis, mean_d[:, None]), 0.2 * mean_d[:, None])


def init_gaussians(verts: torch.Tensor, faces: torch.Tensor, landmarks: torch.Tensor, net=None,
                   config: InitConfig | None = None) -> GaussianScene:
    """Mesh verts [V, 3] / faces [F, 3] (head frame) + landmarks [68, 3] (+ SDFNet) -> GaussianScene."""
    cfg = config or InitConfig()
    landmarks = _check_inputs(verts, faces, landmarks, cfg)
    g = torch.Generator().manual_seed(cfg.seed)
    pts = _mesh_points(verts, faces, cfg)
    part, drop, extra, eyes_meta = _place_eyes(pts, landmarks, cfg, g)
    pts, part, lid = _with_extra_points(pts[~drop], part[~drop], extra)
    scales = _initial_scales(pts, part, lid, eyes_meta, cfg)
    if net is not None:
        with torch.no_grad():
            feats = net.evaluate(pts.to(net.center.device))[2].float().cpu()
        kind = "neural"
    else:
        feats = torch.full((pts.shape[0], 3), 0.5)
        kind = "rgb"
    face = part == PART_FACE
    opac = torch.where(face, torch.tensor(cfg.opacity_face), torch.tensor(cfg.opacity_eye))
    opac[lid] = cfg.opacity_lid
    scene = GaussianScene.from_activated(
        means=pts, scales=scales, opacities=opac, features=feats, part=part,
        metadata={"units": "m", "feature_kind": kind, "source": "geometry.init_gaussians",
                  "frame": "head: x image-right, y down, face towards -z; canonical gaze (0, 0, -1)",
                  "eyes": eyes_meta},
    )
    return scene.validate()


def _check_inputs(verts: torch.Tensor, faces: torch.Tensor, landmarks, cfg: InitConfig) -> torch.Tensor:
    """The mesh, the landmarks and the eye / lid settings of :func:`init_gaussians` -> landmarks [68, 3] float."""
    from geometry.mesh_files import check_mesh

    check_mesh(verts, faces, "init_gaussians mesh")
    landmarks = torch.as_tensor(landmarks, dtype=torch.float32)
    if landmarks.shape != (68, 3) or not bool(torch.isfinite(landmarks).all()):
        raise ToolkitError(f"init_gaussians: landmarks must be finite [68, 3] (iBUG order), got {list(landmarks.shape)}")
    _check_counts(cfg)
    if cfg.eye_points < 0 or 0 < cfg.eye_points < 4 or not 0 < cfg.eye_cap_deg <= 180:
        raise ToolkitError(f"init_gaussians: eye_points must be 0 or >= 4 and eye_cap_deg in (0, 180], got "
                           f"{cfg.eye_points} and {cfg.eye_cap_deg}")
    if cfg.lid_points < 0 or (cfg.lid_points > 0 and cfg.eye_points == 0):
        raise ToolkitError(f"init_gaussians: lid_points must be 0, or > 0 with eye_points > 0 (the lids replace the "
                           f"mesh points dropped with the eyes' shells), got {cfg.lid_points} with eye_points {cfg.eye_points}")
    if cfg.lid_points > 0 and not (cfg.lid_offset > 0 and 0 < cfg.lid_cap_deg <= 90 and cfg.lid_opening > 0
                                   and cfg.lid_scale > 0 and 0 < cfg.opacity_lid < 1):
        raise ToolkitError(f"init_gaussians: expected lid_offset > 0, lid_cap_deg in (0, 90], lid_opening > 0, "
                           f"lid_scale > 0 and opacity_lid in (0, 1), got {cfg.lid_offset}, {cfg.lid_cap_deg}, "
                           f"{cfg.lid_opening}, {cfg.lid_scale}, {cfg.opacity_lid}")
    return landmarks


def _check_counts(cfg: InitConfig) -> None:
    """The count settings in range and what they ask for within the memory budget; NaN or out-of-range
    opacities and eyeball priors refused (a NaN opacity would make every Gaussian NaN)."""
    if cfg.n_points is not None:
        check_count(cfg.n_points, "init_gaussians: n_points", 16, MAX_POINTS, "a number of points (or None)")
    for name in ("eye_points", "lid_points", "min_eye_points"):
        check_count(getattr(cfg, name), f"init_gaussians: {name}", 0, MAX_POINTS, "a number of points")
    check_count(cfg.seed, "init_gaussians: seed", 0, 2**63 - 1, "a seed")
    total = (cfg.n_points or 0) + 2 * (cfg.eye_points + cfg.lid_points + cfg.min_eye_points)
    check_allocation(total * BYTES_PER_POINT, f"init_gaussians: {total} Gaussians", "lower the point counts")
    for name in ("opacity_face", "opacity_eye"):
        if not 0 < getattr(cfg, name) < 1:
            raise ToolkitError(f"init_gaussians: {name}: expected an opacity in (0, 1), got {getattr(cfg, name)!r}")
    if not (0 < cfg.eye_radius_ratio <= 10 and 0 < cfg.shell_tolerance <= 10):
        raise ToolkitError(f"init_gaussians: expected eye_radius_ratio and shell_tolerance in (0, 10], got "
                           f"{cfg.eye_radius_ratio!r} and {cfg.shell_tolerance!r}")


def _mesh_points(verts: torch.Tensor, faces: torch.Tensor, cfg: InitConfig) -> torch.Tensor:
    """[P, 3] the used mesh vertices, or ``cfg.n_points`` area-uniform surface samples; at least 16."""
    from geometry.mesh_stats import sample_surface

    verts = verts.detach().float()
    if cfg.n_points is None:
        pts = verts[torch.unique(faces)]
    else:
        pts = sample_surface(verts, faces, cfg.n_points, cfg.seed, "init_gaussians mesh")[0].float()
    if pts.shape[0] < 16:
        raise ToolkitError(f"init_gaussians: the mesh gives only {pts.shape[0]} points; need at least 16")
    return pts


def _place_eyes(pts: torch.Tensor, landmarks: torch.Tensor, cfg: InitConfig, g: torch.Generator):
    """Fit both eyeballs and decide which mesh points are eye -> (part [P] int8, drop [P] bool: mesh points
    the eye caps replace, extra [(points [M, 3], part id or PART_LID)], the eyes' metadata by name)."""
    part = torch.full((pts.shape[0],), PART_FACE, dtype=torch.int8)
    eyes_meta, extra = {}, []
    drop = torch.zeros(pts.shape[0], dtype=torch.bool)  # mesh points replaced by the eye_points caps
    dist_to_eye = []
    for ids in (LEFT_EYE, RIGHT_EYE):
        dist_to_eye.append((pts - landmarks[ids].mean(0)).norm(dim=-1))
    nearest_left = dist_to_eye[0] <= dist_to_eye[1]
    for name, ids, pid, mine in (("left", LEFT_EYE, PART_LEFT_EYE, nearest_left), ("right", RIGHT_EYE, PART_RIGHT_EYE, ~nearest_left)):
        eye = fit_eyeball(pts, landmarks[ids], cfg)
        c, r = eye["center"], float(eye["radius"])
        width = float((landmarks[ids[0]] - landmarks[ids[3]]).norm())
        on_shell = ((pts - c).norm(dim=-1) - r).abs() < cfg.shell_tolerance * r
        near = (pts - landmarks[ids].mean(0)).norm(dim=-1) < 0.6 * width
        in_front = ((pts - c) @ INWARD) < 0
        sel = on_shell & near & in_front & mine
        if cfg.eye_points > 0:
            drop |= sel
            extra.append((_fibonacci_cap(c, r, cfg.eye_points, cfg.eye_cap_deg), pid))
            if cfg.lid_points > 0:
                extra.append((lid_shell(c, r, landmarks[ids], cfg), PART_LID))
        else:
            part[sel] = pid
            n_have = int(sel.sum())
            if n_have < cfg.min_eye_points:
                extra.append((_front_cap(c, r, cfg.min_eye_points - n_have, g), pid))
        eyes_meta[name] = {"center": [float(x) for x in c], "radius": r, "part": pid, "fit": eye["fit"]}
    return part, drop, extra, eyes_meta


def _with_extra_points(pts: torch.Tensor, part: torch.Tensor, extra) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Append the eye caps and lids -> (points [P', 3], part [P'] int8, lid [P'] bool); lids are face points."""
    lid = torch.zeros(pts.shape[0], dtype=torch.bool)
    for p, pid in extra:
        pts = torch.cat([pts, p])
        lid = torch.cat([lid, torch.full((p.shape[0],), pid == PART_LID)])
        pid = PART_FACE if pid == PART_LID else pid  # lids are face Gaussians: the face field deforms them
        part = torch.cat([part, torch.full((p.shape[0],), pid, dtype=torch.int8)])
    return pts, part, lid


def _initial_scales(pts: torch.Tensor, part: torch.Tensor, lid: torch.Tensor, eyes_meta: dict,
                    cfg: InitConfig) -> torch.Tensor:
    """[P, 3] activated scales from each point's neighbours of its own kind (module docstring)."""
    scales = torch.zeros(pts.shape[0], 3)
    mesh_face = (part == PART_FACE) & ~lid
    # Lids and the mesh's face points take their neighbours among their own kind, so adding lids leaves every
    # mesh point's scale as it was.
    if int(mesh_face.sum()) > 3:
        scales[mesh_face] = _anisotropic_scales(pts[mesh_face])
    if int(lid.sum()) > 3:
        scales[lid] = _anisotropic_scales(pts[lid])
    for pid in (PART_LEFT_EYE, PART_RIGHT_EYE):
        m = part == pid
        if int(m.sum()) > 3:
            scales[m] = knn_spacing(pts[m])[:, None].expand(-1, 3)
        elif int(m.sum()):
            scales[m] = float(eyes_meta["left" if pid == PART_LEFT_EYE else "right"]["radius"]) * 0.2
    # DMTet meshes can have vertices a hair apart (where the surface grazes a grid vertex): floor each
    # part's scales at 0.2 x its median so no Gaussian collapses to a point.
    for m in (mesh_face, part == PART_LEFT_EYE, part == PART_RIGHT_EYE):
        if int(m.sum()):
            scales[m] = scales[m].clamp_min(0.2 * float(scales[m].median()))
    if int(lid.sum()):  # floored as the mesh's face (few lids: the floor alone), then made smaller
        floor = 0.2 * float(scales[mesh_face].median()) if int(mesh_face.sum()) else 1e-4
        scales[lid] = scales[lid].clamp_min(floor) * cfg.lid_scale
    return scales
