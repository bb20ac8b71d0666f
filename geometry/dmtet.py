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
"""

from __future__ import annotations

import torch

from geometry.tets import TET_EDGES, edge_keys, unique_inverse
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


def check_sdf(sdf: torch.Tensor, n_verts: int, name: str = "sdf") -> None:
    """Raise a ToolkitError for a wrong shape or NaN/inf values (with a count)."""
    if sdf.dim() != 1 or sdf.shape[0] != n_verts:
        raise ToolkitError(f"marching_tets: {name} must have shape [V={n_verts}], got {list(sdf.shape)}")
    if not sdf.is_floating_point():
        raise ToolkitError(f"marching_tets: {name} must be floating point, got {sdf.dtype}")
    bad = ~torch.isfinite(sdf)
    if bool(bad.any()):
        raise ToolkitError(
            f"marching_tets: {name} has {int(bad.sum())} NaN/inf value(s) of {n_verts}; "
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
    check_sdf(sdf, V)
    if features is not None and (features.dim() != 2 or features.shape[0] != V):
        raise ToolkitError(f"marching_tets: features must have shape [V={V}, C], got {list(features.shape)}")

    with torch.no_grad():
        inside = sdf < 0
        # One flat byte gather for all 4T corners, then each tet's 4 bytes read as one int32: a tet is
        # crossed unless all bytes are 0 (outside) or all are 1 (inside). This single pass over the T
        # tets is the whole cost on large grids, so it avoids per-column ops and int64 temporaries.
        try:
            occ = inside.to(torch.uint8).index_select(0, tets.reshape(-1)).view(-1, 4)
        except (IndexError, RuntimeError):  # checked lazily: a min/max pass over 4T ids costs as much as this
            raise ToolkitError(f"marching_tets: tet vertex ids must be in [0, {V}), got "
                               f"[{int(tets.min())}, {int(tets.max())}]") from None
        word = occ.view(torch.int32).reshape(-1)
        crossing = (word != 0) & (word != 0x01010101)
        if not bool(crossing.any()):
            n_in = int(inside.sum())
            if n_in == 0:
                kind = "all positive (every vertex outside, min sdf %.4g)" % float(sdf.min()) if V else "empty"
            elif n_in == V:
                kind = "all negative (every vertex inside, max sdf %.4g)" % float(sdf.max())
            else:
                kind = f"mixed signs ({n_in} of {V} inside) but no tet has vertices of both signs"
            raise ToolkitError(f"marching_tets: the SDF has no zero crossing on the grid: {kind}; "
                               "the surface is empty or outside the grid box")
        idx = crossing.nonzero().squeeze(1)
        tets_x = tets.index_select(0, idx).long()
        o = occ.index_select(0, idx).long()
        case_x = o[:, 0] | o[:, 1] << 1 | o[:, 2] << 2 | o[:, 3] << 3
        # Only the cut edges (endpoints of both signs) get output vertices; dedupe them by int64 key.
        cut = o[:, TET_EDGES[:, 0]] != o[:, TET_EDGES[:, 1]]  # [Tx, 6]
        e = tets_x[:, TET_EDGES][cut]  # [C, 2]
        keys = edge_keys(e[:, 0], e[:, 1], V)
        uniq, inv = unique_inverse(keys)
        ea, eb = uniq // V, uniq % V
        tet_edge_vert = torch.full(cut.shape, -1, dtype=torch.long, device=verts.device)
        tet_edge_vert[cut] = inv  # [Tx, 6] output vertex per local edge (-1 = not cut)

        tri_local = _TRI_TABLE.to(verts.device)[case_x]  # [Tx, 2, 3]
        n_tri = _TRI_COUNT.to(verts.device)[case_x]
        faces = []
        for t in range(2):
            has = n_tri > t
            loc = tri_local[has, t]  # [n, 3]
            faces.append(torch.gather(tet_edge_vert[has], 1, loc))
        faces = torch.cat(faces, 0)

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
