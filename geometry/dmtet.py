"""Differentiable marching tetrahedra (DMTet): an SDF on a tet grid -> a triangle mesh.

Output vertices lie on the grid edges whose endpoint SDF values change sign, at the linear zero crossing
``p = (s_b p_a - s_a p_b) / (s_b - s_a)``, so they are differentiable w.r.t. both the grid vertex positions
(deformable tets, as in DMTet) and the SDF values. Conventions:

- SDF negative inside, positive outside; exact zeros count as outside ("nudged" to +0): a vertex with
  sdf == 0 never creates a surface on its own, and interpolation weights are kept ``CLAMP_T`` away from the
  edge ends, so a zero vertex shared by several crossing edges yields distinct output vertices instead of
  several copies of one point (duplicate vertices, zero-area faces).
- Tets must be positively oriented (``geometry.tets`` grids are); faces are then wound counter-clockwise
  seen from outside, i.e. right-hand normals point outward. Each grid edge yields one vertex shared by
  all tets around it, so a closed zero set inside the grid gives a watertight, consistently wound mesh.
- Edges are deduplicated by sorting int64 keys ``min * V + max`` once (``geometry.tets.unique_inverse``);
  ``torch.unique(dim=0)`` sorts rows lexicographically and is many times slower on CPU.

Cost: one lean pass over all T tets finds the crossed ones (chunked byte gather + int32 word test +
a sparse nonzero, see ``_crossing_tets``); everything after it touches only the crossed tets, a few
percent of T. ``benchmarks/dmtet.py`` times it (Kuhn 128: ~0.2 s on the 2-core dev CPU).
"""

from __future__ import annotations

import torch

from geometry.tets import TET_EDGES, unique_inverse
from toolkit.errors import ToolkitError

CLAMP_T = 1e-4  # crossing weights stay in [CLAMP_T, 1 - CLAMP_T] (see module doc)
DENOM_EPS = 1e-20


def _triangle_table() -> tuple[torch.Tensor, torch.Tensor]:
    """[16, 2, 3] local edge ids of up to two triangles per inside-pattern, and [16] triangle counts.

    The pattern index is sum(inside_i << i). Built on the reference tet, with each triangle wound so its
    normal points from the inside vertices to the outside ones; an orientation-preserving affine map
    keeps that true for every positively oriented tet.
    """
    ref = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    edge_id = {tuple(e.tolist()): i for i, e in enumerate(TET_EDGES)}

    def eid(i, j):
        return edge_id[(min(i, j), max(i, j))]

    def mid(e):
        return ref[TET_EDGES[e]].mean(0)

    table = torch.full((16, 2, 3), -1, dtype=torch.long)
    count = torch.zeros(16, dtype=torch.long)
    for case in range(16):
        inside = [i for i in range(4) if case >> i & 1]
        outside = [i for i in range(4) if not case >> i & 1]
        if not inside or not outside:
            continue
        if len(inside) == 2:  # a quad: the 4 crossing edges in cyclic order, split in two triangles
            (i, j), (k, l) = inside, outside
            ring = [eid(i, k), eid(i, l), eid(j, l), eid(j, k)]
            tris = [[ring[0], ring[1], ring[2]], [ring[0], ring[2], ring[3]]]
        else:
            lone = inside[0] if len(inside) == 1 else outside[0]
            others = [v for v in range(4) if v != lone]
            tris = [[eid(lone, v) for v in others]]
        direction = ref[outside].mean(0) - ref[inside].mean(0)
        for t, tri in enumerate(tris):
            p = [mid(e) for e in tri]
            n = torch.linalg.cross(p[1] - p[0], p[2] - p[0])
            if float(n @ direction) < 0:
                tri = [tri[0], tri[2], tri[1]]
            table[case, t] = torch.tensor(tri)
        count[case] = len(tris)
    return table, count


_TRI_TABLE, _TRI_COUNT = _triangle_table()


def _cut_table() -> torch.Tensor:
    """[16, 6] bool: which local edges (TET_EDGES order) have endpoints of both signs, per inside-pattern."""
    case = torch.arange(16)
    bits = (case[:, None] >> torch.arange(4)) & 1  # [16, 4]
    return bits[:, TET_EDGES[:, 0]] != bits[:, TET_EDGES[:, 1]]


_CUT_TABLE = _cut_table()
_E0, _E1 = TET_EDGES[:, 0].contiguous(), TET_EDGES[:, 1].contiguous()
_ALL_INSIDE = 0x01010101  # four inside bytes read as one int32 (same value in either byte order)
# Tets per chunk of the crossing test (16 MiB of corner flags). Small chunks were no faster on one thread
# and, with 2 threads on a busy machine, each chunk's parallel ops wait on the other thread: few chunks.
_CHUNK = 1 << 22


def _nonzero_sparse(mask: torch.Tensor) -> torch.Tensor:
    """``mask.nonzero()[:, 0]`` for a contiguous 1-D bool mask that is mostly False (int64 ids, ascending).

    The mask is first read 8 bytes at a time as int64 words: only the few non-zero words are expanded
    back to bytes. On CPU this is ~3x faster than a plain nonzero over the full mask.
    """
    n = mask.numel()
    n8 = n - n % 8
    words = mask[:n8].view(torch.int64)
    blocks = (words != 0).nonzero().squeeze(1)
    cand = (blocks[:, None] * 8 + torch.arange(8, device=mask.device)).reshape(-1)
    ids = cand[mask.index_select(0, cand)]
    if n8 < n:
        ids = torch.cat([ids, mask[n8:].nonzero().squeeze(1) + n8])
    return ids


def _crossing_tets(inside: torch.Tensor, tets: torch.Tensor, n_verts: int) -> tuple[torch.Tensor, torch.Tensor]:
    """[V] bool, [T, 4] ids -> (ids [Tx] int64 of the tets with corners of both signs, their [Tx, 4] uint8 flags).

    This pass over all T tets is the whole cost on large grids, so it is kept lean: per chunk of tets,
    one flat byte gather of the corners' inside flags into a reused buffer, then each tet's 4 bytes
    read as one int32 word (crossed unless all 0 or all 1). The reused buffer avoids a fresh 4T-byte
    allocation (page faults) per call; no per-column ops or int64 temporaries of size T are made.
    """
    flags = inside.to(torch.uint8)
    T = tets.shape[0]
    buf = torch.empty(min(T, _CHUNK) * 4, dtype=torch.uint8, device=inside.device)
    ids, words = [], []
    for start in range(0, T, _CHUNK):
        stop = min(start + _CHUNK, T)
        try:
            occ = torch.index_select(flags, 0, tets[start:stop].reshape(-1), out=buf[: 4 * (stop - start)])
        except (IndexError, RuntimeError):  # checked lazily: a min/max pass over 4T ids costs as much as this
            raise ToolkitError(f"marching_tets: tet vertex ids must be in [0, {n_verts}), got "
                               f"[{int(tets.min())}, {int(tets.max())}]") from None
        word = occ.view(torch.int32)
        i = _nonzero_sparse((word != 0) & (word != _ALL_INSIDE))
        ids.append(i + start)
        words.append(word.index_select(0, i))
    if not ids:
        return torch.zeros(0, dtype=torch.long, device=inside.device), torch.zeros(0, 4, dtype=torch.uint8, device=inside.device)
    return torch.cat(ids), torch.cat(words).view(torch.uint8).view(-1, 4)


def grid_bytes(kind: str, res: int, feature_dim: int = 0) -> int:
    """Peak bytes of building a ``kind`` grid of ``res`` cubes per axis and extracting a mesh on it: ~160 per tet
    (int64 ids made, concatenated and reoriented) and 64 + 4 x ``feature_dim`` per vertex (positions, the
    network's SDF, offsets and features). Measured: 1.18 GB for Kuhn 96 with 128 features (this says 1.37)."""
    T = (6 if kind == "kuhn" else 12) * res**3
    V = (res + 1) ** 3 + (res**3 if kind != "kuhn" else 0)
    return 160 * T + (64 + 4 * feature_dim) * V


def _check_sdf_shape(sdf: torch.Tensor, n_verts: int, name: str) -> None:
    """Raise a ToolkitError for a wrong shape or a non-float dtype (host-side only: no sync)."""
    if sdf.dim() != 1 or sdf.shape[0] != n_verts:
        raise ToolkitError(f"marching_tets: {name} must have shape [V={n_verts}], got {list(sdf.shape)}")
    if not sdf.is_floating_point():
        raise ToolkitError(f"marching_tets: {name} must be floating point, got {sdf.dtype}")


def _non_finite_sdf_error(sdf: torch.Tensor, n_verts: int, name: str) -> ToolkitError:
    """The NaN/inf error for an ``sdf`` already known to hold some (with a count)."""
    return ToolkitError(
        f"marching_tets: {name} has {int((~torch.isfinite(sdf)).sum())} NaN/inf value(s) of {n_verts}; "
        "the SDF network or its inputs diverged"
    )


def marching_tets(verts: torch.Tensor, tets: torch.Tensor, sdf: torch.Tensor, features: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Extract the zero level set of ``sdf`` on a tet mesh.

    Args:
        verts: [V, 3] float grid vertex positions (may require grad; deformed grids are fine).
        tets: [T, 4] int vertex ids, positively oriented.
        sdf: [V] float SDF, negative inside (may require grad).
        features: optional [V, C] float per-vertex features, interpolated like the positions.
    Returns:
        verts [M, 3], faces [F, 3] int64 (counter-clockwise seen from outside), features [M, C] or None.
    Raises:
        ToolkitError: bad shapes, NaN/inf SDF, or no zero crossing (saying whether the SDF was all
        positive = everything outside, or all negative = everything inside).
    """
    if verts.dim() != 2 or verts.shape[1] != 3:
        raise ToolkitError(f"marching_tets: verts must have shape [V, 3], got {list(verts.shape)}")
    if tets.dim() != 2 or tets.shape[1] != 4 or tets.is_floating_point():
        raise ToolkitError(f"marching_tets: tets must be integer [T, 4], got {list(tets.shape)} {tets.dtype}")
    V = verts.shape[0]
    _check_sdf_shape(sdf, V, "sdf")
    for name, t in (("tets", tets), ("sdf", sdf), ("features", features)):
        if t is not None and t.device != verts.device:
            raise ToolkitError(f"marching_tets: {name} is on {t.device} and verts on {verts.device}; expected one device")
    # Every finiteness flag is computed on device and read back in one host sync; the errors keep their
    # order (the SDF's first, then the features' shape, then the positions' and features' values).
    given = {name: t.detach() for name, t in (("verts", verts), ("features", features)) if t is not None and t.numel()}
    sdf_ok, *given_ok = torch.stack([torch.isfinite(t).all() for t in (sdf.detach(), *given.values())]).tolist()
    if not sdf_ok:
        raise _non_finite_sdf_error(sdf, V, "sdf")
    if features is not None and (features.dim() != 2 or features.shape[0] != V):
        raise ToolkitError(f"marching_tets: features must have shape [V={V}, C], got {list(features.shape)}")
    if bad := next((name for name, ok in zip(given, given_ok) if not ok), None):
        raise ToolkitError(f"marching_tets: {bad} contain NaN/inf")

    with torch.no_grad():
        idx, o = _crossing_tets(sdf < 0, tets, V)
        if idx.numel() == 0:
            n_in = int((sdf < 0).sum())
            if n_in == 0:
                kind = "all positive (every vertex outside, min sdf %.4g)" % float(sdf.min()) if V else "empty"
            elif n_in == V:
                kind = "all negative (every vertex inside, max sdf %.4g)" % float(sdf.max())
            else:
                kind = f"mixed signs ({n_in} of {V} inside) but no tet has vertices of both signs"
            raise ToolkitError(f"marching_tets: the SDF has no zero crossing on the grid: {kind}; "
                               "the surface is empty or outside the grid box")
        # From here on only the Tx crossed tets (a few percent of T) are touched.
        tets_x = tets.index_select(0, idx).long()  # [Tx, 4]
        o = o.long()  # [Tx, 4] inside flags
        case_x = o[:, 0] | o[:, 1] << 1 | o[:, 2] << 2 | o[:, 3] << 3
        # Only the cut edges (endpoints of both signs) get output vertices; their endpoints are read
        # straight from the flat [Tx * 4] ids (no [Tx, 6, 2] table) and deduplicated by int64 key.
        cut = _CUT_TABLE.to(verts.device)[case_x]  # [Tx, 6]
        row, local = cut.nonzero().unbind(1)
        flat, at = tets_x.reshape(-1), row * 4
        a = flat.index_select(0, at + _E0.to(verts.device).index_select(0, local))
        b = flat.index_select(0, at + _E1.to(verts.device).index_select(0, local))
        keys = torch.minimum(a, b).mul_(V).add_(torch.maximum(a, b))  # = edge_keys(a, b, V), in place
        uniq, inv = unique_inverse(keys)
        ea, eb = uniq // V, uniq % V
        tet_edge_vert = torch.full(cut.shape, -1, dtype=torch.long, device=verts.device)
        tet_edge_vert[row, local] = inv  # [Tx, 6] output vertex per local edge (-1 = not cut)

        tri_local = _TRI_TABLE.to(verts.device)[case_x]  # [Tx, 2, 3]
        quad = (_TRI_COUNT.to(verts.device)[case_x] == 2).nonzero().squeeze(1)
        faces = torch.cat([torch.gather(tet_edge_vert, 1, tri_local[:, 0]),
                           torch.gather(tet_edge_vert.index_select(0, quad), 1, tri_local.index_select(0, quad)[:, 1])])

    # Differentiable part: positions (and features) at the linear zero crossing of each cut edge.
    sa, sb = sdf[ea], sdf[eb]
    # sa and sb have opposite classification, so sb - sa != 0; the clamp only guards underflow, where the
    # weight gradient ~ 1 / denom would otherwise overflow to inf.
    denom = sb - sa
    sign = torch.where(sa < 0, torch.ones_like(denom), -torch.ones_like(denom))
    denom = torch.where(denom.abs() < DENOM_EPS, sign * DENOM_EPS, denom)
    t = (-sa / denom).clamp(CLAMP_T, 1 - CLAMP_T)[:, None]  # weight of vertex b
    out_verts = verts[ea] * (1 - t) + verts[eb] * t
    out_feat = None
    if features is not None:
        out_feat = features[ea] * (1 - t.to(features.dtype)) + features[eb] * t.to(features.dtype)
    return out_verts, faces, out_feat
