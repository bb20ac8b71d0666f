"""A named pymeshlab cleanup pipeline for extracted meshes; every step reports what it changed.

Order matters: duplicate vertices are welded **before** duplicate faces are removed (two faces are
duplicates only once they index the same vertices), components are dropped before holes are closed
(so islands do not get capped), and quadric decimation comes last. Decimation is checked: on some
inputs (e.g. fully locked boundaries) pymeshlab silently returns the mesh unchanged, which is reported
as an error instead of a "successful" no-op.

pymeshlab is imported lazily, inside :func:`clean_mesh`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.limits import check_count

# Bounds on the settings, from what the steps cost: pymeshlab's Taubin step takes ~0.1 us per vertex (1000
# steps on a 1 M-vertex mesh: ~2 min) and isotropic remeshing ~6 us per face and iteration (2 M faces x 5
# iterations: ~1 min); decimation and hole filling cost what the mesh holds.
MAX_TAUBIN_STEPS = 1000
MAX_REMESH_ITERATIONS = 100
MAX_REMESH_FACES = 2_000_000
MAX_HOLE_EDGES = 100_000
MAX_TARGET_FACES = 1_000_000_000
FIELD_NAMES = {f: f for f in ("weld_tolerance", "min_component_fraction", "max_hole_edges", "remesh_edge_fraction",
                              "remesh_iterations", "taubin_steps", "taubin_lambda", "taubin_mu", "target_faces")}


@dataclass
class CleanupConfig:
    """Pipeline switches and parameters (defaults suit a DMTet head mesh)."""

    weld_tolerance: float = 1e-6
    """Merge vertices closer than this fraction of the bounding-box diagonal (0: exact duplicates only)."""
    min_component_fraction: float = 0.01
    """Drop connected components with fewer faces than this share of all faces."""
    repair_non_manifold: bool = True
    max_hole_edges: int = 30
    """Close holes bounded by at most this many edges (0 disables)."""
    remesh_edge_fraction: float = 0.0
    """Isotropic remeshing target edge length as a fraction of the bbox diagonal (0 disables)."""
    remesh_iterations: int = 5
    taubin_steps: int = 10
    """Taubin (lambda/mu) smoothing iterations (0 disables); shrink-free, unlike plain Laplacian."""
    taubin_lambda: float = 0.5
    taubin_mu: float = -0.53
    target_faces: int | None = None
    """Quadric edge-collapse decimation to this many faces (None disables)."""


@dataclass
class StepReport:
    """What one pipeline step changed."""

    name: str
    vertices_before: int
    vertices_after: int
    faces_before: int
    faces_after: int
    note: str = ""

    def __str__(self) -> str:
        dv, df = self.vertices_after - self.vertices_before, self.faces_after - self.faces_before
        return (f"{self.name:<24} vertices {self.vertices_before} -> {self.vertices_after} ({dv:+d}), "
                f"faces {self.faces_before} -> {self.faces_after} ({df:+d})" + (f"  [{self.note}]" if self.note else ""))


def _to_numpy(verts, faces) -> tuple[np.ndarray, np.ndarray]:
    v = verts.detach().cpu().numpy() if isinstance(verts, torch.Tensor) else np.asarray(verts)
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ToolkitError(f"clean_mesh: expected verts [V, 3] and faces [F, 3], got {list(v.shape)} and {list(f.shape)}")
    if v.shape[0] == 0 or f.shape[0] == 0:
        raise ToolkitError("clean_mesh: the mesh is empty (no vertices or no faces)")
    if not np.isfinite(v).all():
        raise ToolkitError(f"clean_mesh: {int((~np.isfinite(v)).any(1).sum())} vertices have NaN/inf coordinates")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ToolkitError(f"clean_mesh: face indices must be in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]")
    return v.astype(np.float64), f.astype(np.int32)


def _check_real(value, name: str, low: float, high: float, what: str, open_low: bool = False) -> float:
    """``value`` as a finite float in [low, high] ((low, high] with ``open_low``), else a ToolkitError naming it."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not (low < value if open_low else low <= value) or not value <= high:
        raise ToolkitError(f"{name}: expected {what} in {'(' if open_low else '['}{low:g}, {high:g}], got {value!r}")
    return float(value)


def check_config(cfg: CleanupConfig, names: dict[str, str] | None = None) -> CleanupConfig:
    """Refuse NaN, negative or out-of-range settings before any work; ``names`` maps fields to the names errors
    use (the CLI's flags), by default the field names. Returns the config with its counts as ints (``1e3``)."""
    n = {**FIELD_NAMES, **(names or {})}
    _check_real(cfg.weld_tolerance, n["weld_tolerance"], 0, 0.1, "a fraction of the bounding-box diagonal")
    _check_real(cfg.min_component_fraction, n["min_component_fraction"], 0, 1, "a fraction of the faces")
    holes = check_count(cfg.max_hole_edges, n["max_hole_edges"], 0, MAX_HOLE_EDGES, "a number of edges")
    _check_real(cfg.remesh_edge_fraction, n["remesh_edge_fraction"], 0, 1,
                "an edge length as a fraction of the bounding-box diagonal (0: off)")
    its = check_count(cfg.remesh_iterations, n["remesh_iterations"], 1, MAX_REMESH_ITERATIONS, "a number of iterations")
    steps = check_count(cfg.taubin_steps, n["taubin_steps"], 0, MAX_TAUBIN_STEPS, "a number of smoothing steps")
    _check_real(cfg.taubin_lambda, n["taubin_lambda"], 0, 1, "a smoothing weight", open_low=True)
    _check_real(cfg.taubin_mu, n["taubin_mu"], -1, 0, "a (negative) inflation weight")
    target = cfg.target_faces
    if target is not None:
        target = check_count(target, n["target_faces"], 4, MAX_TARGET_FACES, "a number of faces")
    return replace(cfg, max_hole_edges=holes, remesh_iterations=its, taubin_steps=steps, target_faces=target)


def remeshed_faces(verts, faces, edge_fraction: float) -> float:
    """About how many faces isotropic remeshing makes: the area over an equilateral triangle's of that edge."""
    v, f = _to_numpy(verts, faces)
    edge = edge_fraction * float(np.linalg.norm(v.max(0) - v.min(0)))
    area = 0.5 * float(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())
    return area / (math.sqrt(3) / 4 * edge**2) if edge > 0 else 0.0


def check_remesh_size(verts, faces, edge_fraction: float, name: str = "remesh_edge_fraction") -> None:
    """Refuse a remeshing edge so short that the mesh would get more than ``MAX_REMESH_FACES`` faces."""
    if edge_fraction > 0:
        n = remeshed_faces(verts, faces, edge_fraction)
        if not n <= MAX_REMESH_FACES:
            low = edge_fraction * math.sqrt(n / MAX_REMESH_FACES)
            raise ToolkitError(f"{name}: an edge of {edge_fraction:g} x the diagonal would remesh this mesh into "
                               f"~{n:.3g} faces, more than {MAX_REMESH_FACES}; expected an edge fraction >= {low:.3g}")


def clean_mesh(verts, faces, config: CleanupConfig | None = None, *, log=None
               ) -> tuple[torch.Tensor, torch.Tensor, list[StepReport]]:
    """Run the pipeline on verts [V, 3], faces [F, 3] -> (verts, faces, one StepReport per step run)."""
    import pymeshlab as ml

    cfg = check_config(config or CleanupConfig())
    v, f = _to_numpy(verts, faces)
    check_remesh_size(v, f, cfg.remesh_edge_fraction)
    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(vertex_matrix=v, face_matrix=f))
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    reports: list[StepReport] = []

    def counts() -> tuple[int, int]:
        m = ms.current_mesh()
        return m.vertex_number(), m.face_number()

    def step(name: str, fn, note: str = "") -> StepReport:
        v0, f0 = counts()
        try:
            fn()
        except ml.PyMeshLabException as e:
            raise ToolkitError(f"clean_mesh: step {name!r} failed in pymeshlab ({str(e)[:160]})") from None
        v1, f1 = counts()
        r = StepReport(name, v0, v1, f0, f1, note)
        reports.append(r)
        if log:
            log(str(r))
        return r

    def weld():
        ms.meshing_remove_duplicate_vertices()
        if cfg.weld_tolerance > 0 and diag > 0:
            ms.meshing_merge_close_vertices(threshold=ml.PercentageValue(100 * cfg.weld_tolerance))

    step("weld_vertices", weld, f"tolerance {cfg.weld_tolerance:g} x diag")
    step("remove_duplicate_faces", ms.meshing_remove_duplicate_faces)
    step("remove_null_faces", ms.meshing_remove_null_faces)
    step("remove_unreferenced", ms.meshing_remove_unreferenced_vertices)
    if cfg.min_component_fraction > 0:
        n = max(1, int(round(cfg.min_component_fraction * counts()[1])))
        step("drop_small_components",
             lambda: ms.meshing_remove_connected_component_by_face_number(mincomponentsize=n, removeunref=True),
             f"components with < {n} faces")
    if cfg.repair_non_manifold:
        step("repair_non_manifold_edges", lambda: ms.meshing_repair_non_manifold_edges(method="Remove Faces"))
        step("repair_non_manifold_verts", lambda: ms.meshing_repair_non_manifold_vertices(vertdispratio=0))
        step("remove_unreferenced", ms.meshing_remove_unreferenced_vertices)
    if cfg.max_hole_edges > 0:
        step("close_holes", lambda: ms.meshing_close_holes(maxholesize=cfg.max_hole_edges, newfaceselected=False),
             f"holes of <= {cfg.max_hole_edges} edges")
    if cfg.remesh_edge_fraction > 0:
        step("isotropic_remesh", lambda: ms.meshing_isotropic_explicit_remeshing(
            iterations=cfg.remesh_iterations, targetlen=ml.PercentageValue(100 * cfg.remesh_edge_fraction)),
            f"edge {cfg.remesh_edge_fraction:g} x diag")
    if cfg.taubin_steps > 0:
        step("taubin_smooth", lambda: ms.apply_coord_taubin_smoothing(
            lambda_=cfg.taubin_lambda, mu=cfg.taubin_mu, stepsmoothnum=cfg.taubin_steps), f"{cfg.taubin_steps} steps")
    if cfg.target_faces is not None:
        target = int(cfg.target_faces)
        f_now = counts()[1]
        if f_now <= target:
            reports.append(StepReport("decimate", *(counts()[:1] * 2), f_now, f_now, f"skipped: {f_now} <= target {target}"))
            if log:
                log(str(reports[-1]))
        else:
            r = step("decimate", lambda: ms.meshing_decimation_quadric_edge_collapse(
                targetfacenum=target, preservenormal=True, optimalplacement=True, autoclean=True),
                f"target {target} faces")
            if r.faces_after >= r.faces_before:
                raise ToolkitError(f"clean_mesh: quadric decimation did not reduce the face count "
                                   f"({r.faces_before} -> {r.faces_after}, target {target})")
    m = ms.current_mesh()
    out_v = torch.from_numpy(np.ascontiguousarray(m.vertex_matrix())).float()
    out_f = torch.from_numpy(np.ascontiguousarray(m.face_matrix())).long()
    if out_f.shape[0] == 0:
        raise ToolkitError("clean_mesh: the cleanup removed every face (was the mesh made only of small islands?)")
    return out_v, out_f, reports


def config_dict(cfg: CleanupConfig) -> dict:
    return asdict(cfg)
