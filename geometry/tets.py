"""Tetrahedral grids made by code (never downloaded): Kuhn (6 tets per cube) and body-centred cubic.

Every grid covers an axis-aligned box ``[lo, hi]^3`` with ``res`` cubes along each axis, and every tet
``(a, b, c, d)`` is **positively oriented**: ``det[b - a, c - a, d - a] > 0``. With that orientation and
a negative-inside SDF, :func:`geometry.dmtet.marching_tets` emits outward-facing triangles.

- :func:`kuhn_grid`: (res+1)^3 vertices, 6 res^3 tets. Each cube is split along its main diagonal
  into the 6 "path" tets 0 -> e_i -> e_i + e_j -> (1,1,1); all cubes use the same diagonal, so the
  split is conforming (neighbouring cubes agree on every shared face).
- :func:`bcc_grid`: cube corners plus cube centres; each pair of face-adjacent centres and the shared
  square make an octahedron cut into 4 tets around the centre-centre axis; squares on the box boundary
  make half-octahedra (pyramids) cut into 2. Tets are closer to regular than Kuhn's (dihedral angles
  60°/90° instead of 45°/90°), which gives a more even mesh at the same vertex count.
- :func:`subdivide`: midpoint subdivision, 1 tet -> 8 (4 corner tets + the inner octahedron split in 4),
  per-vertex features averaged onto the new edge midpoints.
- :func:`load_grid`: the integer topology is cached on disk by (kind, res) as safetensors, so large
  grids are built once; the box is applied after loading.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from toolkit.errors import ToolkitError

GRID_KINDS = ("kuhn", "bcc")
MAX_RES = 512
# The 6 edges of a tet as local vertex pairs; shared with geometry.dmtet.
TET_EDGES = torch.tensor([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=torch.long)


def default_cache_dir() -> Path:
    """``$DITGAZE_CACHE/tets`` or ``~/.cache/ditgaze/tets``."""
    root = os.environ.get("DITGAZE_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "ditgaze")
    return Path(root) / "tets"


def _check_res(res: int) -> int:
    if not isinstance(res, int) or isinstance(res, bool) or res < 1 or res > MAX_RES:
        raise ToolkitError(f"tet grid res: expected an integer in [1, {MAX_RES}], got {res!r}")
    return res


def _box(lo: float | Sequence[float], hi: float | Sequence[float]) -> tuple[torch.Tensor, torch.Tensor]:
    lo_t = torch.as_tensor(lo, dtype=torch.float64).expand(3).clone()
    hi_t = torch.as_tensor(hi, dtype=torch.float64).expand(3).clone()
    if not (torch.isfinite(lo_t).all() and torch.isfinite(hi_t).all()) or not bool((hi_t > lo_t).all()):
        raise ToolkitError(f"tet grid box: expected finite lo < hi on every axis, got lo={lo_t.tolist()} hi={hi_t.tolist()}")
    return lo_t, hi_t


def _triple(verts: torch.Tensor, tets: torch.Tensor, chunk: int = 1 << 20) -> torch.Tensor:
    """[V, 3], [T, 4] -> [T] det[b-a, c-a, d-a] as an explicit triple product, in chunks of tets.

    In the dtype of ``verts``: exact for integer lattice coordinates. (``torch.linalg.det`` on a
    [T, 3, 3] stack runs a batched LU and needs 9T floats at once: ~10x slower on large grids.)
    """
    out = []
    for start in range(0, tets.shape[0], chunk):
        t = tets[start:start + chunk].long()
        a = verts.index_select(0, t[:, 0])
        u, v, w = (verts.index_select(0, t[:, i]) - a for i in (1, 2, 3))
        out.append((u * torch.linalg.cross(v, w)).sum(-1) if verts.is_floating_point() else
                   (u * _int_cross(v, w)).sum(-1))
    return torch.cat(out) if out else verts.new_zeros(0)


def _int_cross(v: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Row-wise cross product for integer tensors (torch.linalg.cross is float-only on some builds)."""
    return torch.stack([v[:, 1] * w[:, 2] - v[:, 2] * w[:, 1], v[:, 2] * w[:, 0] - v[:, 0] * w[:, 2],
                        v[:, 0] * w[:, 1] - v[:, 1] * w[:, 0]], -1)


def signed_volumes(verts: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """[V, 3], [T, 4] -> [T] signed volumes det[b-a, c-a, d-a] / 6 (positive = positively oriented)."""
    return _triple(verts, tets) / 6.0


def _orient(verts: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Swap the last two vertices of negatively oriented tets (construction-time only).

    ``verts`` are integer lattice coordinates (exact signs) or float64 points.
    """
    neg = _triple(verts, tets) < 0
    if not bool(neg.any()):
        return tets
    tets = tets.clone()
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].clone(), tets[neg, 2].clone()
    return tets


# ---------------------------------------------------------------------------------------- topology
def _kuhn_topology(res: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer lattice coordinates [V, 3] (in units of half a cell) and tets [T, 4] for a Kuhn grid."""
    n = res + 1
    r = torch.arange(n)
    ijk = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    cube = torch.stack(torch.meshgrid(torch.arange(res), torch.arange(res), torch.arange(res), indexing="ij"), -1)
    base = (cube[..., 0] * n * n + cube[..., 1] * n + cube[..., 2]).reshape(-1)
    step = torch.tensor([n * n, n, 1])
    tets = []
    for perm, parity in (((0, 1, 2), 1), ((1, 2, 0), 1), ((2, 0, 1), 1), ((0, 2, 1), -1), ((2, 1, 0), -1), ((1, 0, 2), -1)):
        v1 = step[perm[0]]
        v2 = v1 + step[perm[1]]
        v3 = step.sum()
        t = torch.stack([base, base + v1, base + v2, base + v3], -1)
        if parity < 0:  # odd permutation of the axes -> negative determinant; swap to fix
            t = t[:, [0, 1, 3, 2]]
        tets.append(t)
    return ijk * 2, torch.cat(tets, 0)


def _bcc_topology(res: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Half-cell lattice coordinates [V, 3] and tets [T, 4] for a BCC grid (orientation fixed after)."""
    n = res + 1
    r = torch.arange(n)
    corners = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3) * 2
    rc = torch.arange(res)
    centres = torch.stack(torch.meshgrid(rc, rc, rc, indexing="ij"), -1).reshape(-1, 3) * 2 + 1
    n_corner = corners.shape[0]

    def corner_id(i, j, k):
        return i * n * n + j * n + k

    def centre_id(i, j, k):
        return n_corner + i * res * res + j * res + k

    tets = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        # Every square face orthogonal to `axis`: position p along axis in [0, res], cell (a, b) in the plane.
        p, a, b = torch.meshgrid(torch.arange(n), torch.arange(res), torch.arange(res), indexing="ij")
        p, a, b = p.reshape(-1), a.reshape(-1), b.reshape(-1)

        def at(i_axis, i_u, i_v, axis=axis, u=u, v=v):
            idx = [None, None, None]
            idx[axis], idx[u], idx[v] = i_axis, i_u, i_v
            return idx

        square = [corner_id(*at(p, a + da, b + db)) for da, db in ((0, 0), (1, 0), (1, 1), (0, 1))]  # cyclic order
        has_lo = p > 0  # a cube on the -axis side of this face
        has_hi = p < res
        c_lo = torch.where(has_lo, centre_id(*at(p - 1, a, b)), torch.zeros_like(p))
        c_hi = torch.where(has_hi, centre_id(*at(p, a, b)), torch.zeros_like(p))
        inner = has_lo & has_hi
        for e in range(4):  # octahedron around the centre-centre axis: one tet per square edge
            q0, q1 = square[e], square[(e + 1) % 4]
            tets.append(torch.stack([c_lo, c_hi, q0, q1], -1)[inner])
        for c, has in ((c_lo, has_lo & ~has_hi), (c_hi, has_hi & ~has_lo)):  # boundary pyramids
            tets.append(torch.stack([c, square[0], square[1], square[2]], -1)[has])
            tets.append(torch.stack([c, square[0], square[2], square[3]], -1)[has])
    return torch.cat([corners, centres], 0), torch.cat(tets, 0)


def grid_topology(kind: str, res: int, *, cache_dir: str | os.PathLike | None = None,
                  use_cache: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer half-cell coordinates [V, 3] (0..2 res) and positively oriented tets [T, 4] (int64).

    Read from / written to the disk cache (``cache_dir`` or :func:`default_cache_dir`) when ``use_cache``.
    """
    _check_res(res)
    if kind not in GRID_KINDS:
        raise ToolkitError(f"tet grid kind: expected one of {GRID_KINDS}, got {kind!r}")
    path = Path(cache_dir or default_cache_dir()) / f"{kind}_{res}.safetensors"
    if use_cache and path.exists():
        from toolkit.io import load_tensors

        try:
            t, meta = load_tensors(path)
            if meta.get("kind") == kind and meta.get("res") == res and {"coords", "tets"} <= t.keys():
                return t["coords"].long(), t["tets"].long()
        except ToolkitError:
            pass  # a corrupt cache entry is rebuilt below
    coords, tets = (_kuhn_topology if kind == "kuhn" else _bcc_topology)(res)
    tets = _orient(coords, tets)  # integer half-cell coordinates: exact orientation test
    if use_cache:
        from toolkit.io import save_tensors

        try:  # int32 halves the file; a read-only cache folder only costs the rebuild next time
            save_tensors(path, {"coords": coords.int(), "tets": tets.int()}, {"kind": kind, "res": res})
        except (OSError, ToolkitError):  # atomic_write reports an unwritable folder as a ToolkitError
            pass
    return coords, tets


def tet_grid(kind: str = "kuhn", res: int = 32, lo: float | Sequence[float] = -1.0, hi: float | Sequence[float] = 1.0,
             *, cache_dir: str | os.PathLike | None = None, use_cache: bool = True,
             dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """A tet grid over the box [lo, hi]^3 with ``res`` cubes per axis -> (verts [V, 3], tets [T, 4] int64).

    ``lo``/``hi`` are scalars or 3-sequences (non-cubic boxes give non-cubic cells).
    Kuhn: V = (res+1)^3, T = 6 res^3. BCC: V = (res+1)^3 + res^3, T = 12 res^3.
    """
    lo_t, hi_t = _box(lo, hi)
    coords, tets = grid_topology(kind, res, cache_dir=cache_dir, use_cache=use_cache)
    verts = lo_t + coords.double() * ((hi_t - lo_t) / (2 * res))
    return verts.to(dtype), tets


def kuhn_grid(res: int, lo=-1.0, hi=1.0, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    """Kuhn (6 tets per cube) grid; see :func:`tet_grid`."""
    return tet_grid("kuhn", res, lo, hi, **kw)


def bcc_grid(res: int, lo=-1.0, hi=1.0, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    """Body-centred cubic grid; see :func:`tet_grid`."""
    return tet_grid("bcc", res, lo, hi, **kw)


# ---------------------------------------------------------------------------------------- subdivision
def _subdivision_template() -> torch.Tensor:
    """[8, 4] child tets over local ids 0..3 (corners) and 4..9 (midpoints of TET_EDGES), all positive.

    Orientation is fixed once on a reference tet; an orientation-preserving affine map carries it to
    any positively oriented parent, so children inherit positive orientation combinatorially (no
    per-tet determinants, which would be unreliable on nearly flat deformed tets).
    """
    ref = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    mids = (ref[TET_EDGES[:, 0]] + ref[TET_EDGES[:, 1]]) / 2
    pts = torch.cat([ref, mids])
    m = {tuple(e.tolist()): 4 + i for i, e in enumerate(TET_EDGES)}

    def mid(i, j):
        return m[(min(i, j), max(i, j))]

    children = []
    for c in range(4):  # corner tets: scaled copies of the parent about corner c
        children.append([c if k == c else mid(c, k) for k in range(4)])
    # Inner octahedron split around the diagonal mid(0,2)-mid(1,3).
    d0, d1 = mid(0, 2), mid(1, 3)
    ring = [mid(0, 1), mid(1, 2), mid(2, 3), mid(0, 3)]  # cycle around the diagonal
    for e in range(4):
        children.append([d0, d1, ring[e], ring[(e + 1) % 4]])
    t = _orient(pts, torch.tensor(children))
    assert bool((signed_volumes(pts, t) > 0).all())
    return t


_SUBDIV = _subdivision_template()


def edge_keys(a: torch.Tensor, b: torch.Tensor, n_verts: int) -> torch.Tensor:
    """Undirected edge (a, b) -> one int64 key min * V + max (1-D unique on keys is fast on CPU)."""
    a, b = a.long(), b.long()
    return torch.minimum(a, b) * n_verts + torch.maximum(a, b)


def unique_inverse(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.unique(keys, return_inverse=True)`` for int64 keys (any shape), as one sort plus linear passes.

    (torch.unique with an inverse does extra work on CPU; this is ~2-3x faster on large key sets.) On CPU
    the permutation comes from numpy's argsort (SIMD quicksort, ~2x faster than torch.sort on int64; the
    order of equal keys does not matter here), on other devices from torch.sort.
    """
    shape = keys.shape
    keys = keys.reshape(-1)
    if keys.numel() == 0:
        return keys.clone(), torch.zeros(shape, dtype=torch.long, device=keys.device)
    if keys.device.type == "cpu":
        perm = torch.from_numpy(np.argsort(keys.detach().contiguous().numpy())).long()
        sorted_keys = keys.index_select(0, perm)
    else:
        sorted_keys, perm = torch.sort(keys)
    first = torch.ones_like(sorted_keys, dtype=torch.bool)
    first[1:] = sorted_keys[1:] != sorted_keys[:-1]
    group = torch.cumsum(first, 0) - 1
    inv = torch.empty_like(group)
    inv[perm] = group
    return sorted_keys[first], inv.reshape(shape)


def subdivide(verts: torch.Tensor, tets: torch.Tensor, features: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Midpoint subdivision: every tet -> 8; new vertices at unique edge midpoints (differentiable).

    Args:
        verts [V, 3], tets [T, 4] positively oriented, features [V, C] or [V] (e.g. SDF values), optional.
    Returns:
        verts [V + E, 3] (originals first), tets [8T, 4] positively oriented, features [V + E, C] / [V + E]
        averaged onto midpoints (None when not given).
    """
    if verts.dim() != 2 or verts.shape[1] != 3:
        raise ToolkitError(f"subdivide: verts must be [V, 3], got {list(verts.shape)}")
    if tets.dim() != 2 or tets.shape[1] != 4:
        raise ToolkitError(f"subdivide: tets must be [T, 4], got {list(tets.shape)}")
    if features is not None and features.shape[0] != verts.shape[0]:
        raise ToolkitError(f"subdivide: features must have V={verts.shape[0]} rows, got {list(features.shape)}")
    V = verts.shape[0]
    tets = tets.long()
    e = tets[:, TET_EDGES]  # [T, 6, 2]
    keys = edge_keys(e[..., 0], e[..., 1], V)
    uniq, inv = unique_inverse(keys)
    ea, eb = uniq // V, uniq % V
    new_verts = torch.cat([verts, (verts[ea] + verts[eb]) / 2], 0)
    new_feat = None
    if features is not None:
        new_feat = torch.cat([features, (features[ea] + features[eb]) / 2], 0)
    local = torch.cat([tets, V + inv.reshape(-1, 6)], 1)  # [T, 10] local ids -> global
    new_tets = local[:, _SUBDIV.reshape(-1)].reshape(-1, 4)
    return new_verts, new_tets, new_feat
