"""Vectorized tile binning: which depth-sorted Gaussians may touch which screen tile.

A Gaussian can only reach alpha >= 1/255 where sigma <= ln(255 o) (its "opacity ellipse"). Each Gaussian
gets the tiles of that ellipse's bounding box, then every (Gaussian, tile) pair is tested exactly against
the ellipse (minimum of the quadratic over the tile's pixel centres), so no work is spent on tiles a
Gaussian cannot change. Culling is conservative by a tiny margin: the per-pixel test decides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

ALPHA_MIN = 1.0 / 255.0
# Relative/absolute slack on the ellipse level so rounding never culls a pixel the exact test would keep.
_LEVEL_SLACK = 1e-4


@dataclass
class TileBins:
    """Pairs (tile, Gaussian) sorted by tile then depth rank.

    gids [P + 1] int64 Gaussian index (into the depth-sorted visible set) of each pair, plus one sentinel
    pair at the end pointing at the dummy Gaussian ``num_gaussians`` (padding of partial chunks);
    starts, counts [tiles] int64: each tile's slice of ``gids``. Tiles are row-major, ``tiles_x`` per row.
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    num_gaussians: int
    gids: torch.Tensor
    starts: torch.Tensor
    counts: torch.Tensor
    n_candidates: int  # pairs from the bounding boxes, before the exact ellipse test

    @property
    def n_pairs(self) -> int:
        return int(self.gids.numel()) - 1

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


def opacity_levels(opacities: torch.Tensor) -> torch.Tensor:
    """[M] ln(255 o): the sigma below which alpha = o exp(-sigma) reaches 1/255 (<= 0: never visible)."""
    return torch.log(opacities.clamp_min(1e-30) / ALPHA_MIN)


def _quad(a, b, c, dx, dy):
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


def _rect_min_sigma(a, b, c, xlo, xhi, ylo, yhi):
    """Minimum of sigma(dx, dy) = 0.5 (a dx^2 + c dy^2) + b dx dy over [xlo, xhi] x [ylo, yhi] (a, c > 0)."""
    inside = (xlo <= 0) & (xhi >= 0) & (ylo <= 0) & (yhi >= 0)
    # Off the rectangle the convex minimum lies on an edge: minimise the 1D quadratic on each of the four.
    best = None
    for xe in (xlo, xhi):
        dy = torch.clamp(-b * xe / c.clamp_min(1e-30), min=ylo, max=yhi)
        q = _quad(a, b, c, xe, dy)
        best = q if best is None else torch.minimum(best, q)
    for ye in (ylo, yhi):
        dx = torch.clamp(-b * ye / a.clamp_min(1e-30), min=xlo, max=xhi)
        best = torch.minimum(best, _quad(a, b, c, dx, ye))
    return torch.where(inside, torch.zeros_like(best), best)


@torch.no_grad()
def bin_gaussians(means2d: torch.Tensor, conics: torch.Tensor, cov2d: torch.Tensor, opacities: torch.Tensor,
                  width: int, height: int, tile_size: int) -> TileBins:
    """means2d [M, 2], conics [M, 3], cov2d [M, 3] (dilated xx, xy, yy), opacities [M], all for Gaussians
    already sorted front to back -> TileBins. No Python loop over Gaussians or tiles."""
    device = means2d.device
    ts = int(tile_size)
    tx_n, ty_n = math.ceil(width / ts), math.ceil(height / ts)
    m = means2d.shape[0]
    level = opacity_levels(opacities)
    level_s = level * (1 + _LEVEL_SLACK) + _LEVEL_SLACK
    lvl = level_s.clamp_min(0)
    # Half-extents of the opacity ellipse: max |dx| on {sigma <= L} is sqrt(2 L cov_xx).
    ex = torch.sqrt(2 * lvl * cov2d[:, 0].clamp_min(0))
    ey = torch.sqrt(2 * lvl * cov2d[:, 2].clamp_min(0))
    mx, my = means2d[:, 0], means2d[:, 1]
    # Pixel columns j with centre j + 0.5 in [mx - ex, mx + ex], clipped to the image.
    big = float(2**40)
    jlo = torch.ceil(mx - ex - 0.5).clamp(0, big)
    jhi = torch.floor(mx + ex - 0.5).clamp(-big, width - 1)
    ilo = torch.ceil(my - ey - 0.5).clamp(0, big)
    ihi = torch.floor(my + ey - 0.5).clamp(-big, height - 1)
    ok = (level > 0) & (jlo <= jhi) & (ilo <= ihi) & torch.isfinite(ex + ey + mx + my)
    tx0 = torch.div(jlo, ts, rounding_mode="floor").long()
    tx1 = torch.div(jhi, ts, rounding_mode="floor").long()
    ty0 = torch.div(ilo, ts, rounding_mode="floor").long()
    ty1 = torch.div(ihi, ts, rounding_mode="floor").long()
    nx = (tx1 - tx0 + 1).clamp_min(0)
    ny = (ty1 - ty0 + 1).clamp_min(0)
    n_per = torch.where(ok, nx * ny, torch.zeros_like(nx))
    n_cand = int(n_per.sum())

    gid = torch.repeat_interleave(torch.arange(m, device=device), n_per, output_size=n_cand)
    first = torch.cumsum(n_per, 0) - n_per
    local = torch.arange(n_cand, device=device) - first.index_select(0, gid)
    nxg = nx.index_select(0, gid)
    tile_x = tx0.index_select(0, gid) + local % nxg.clamp_min(1)
    tile_y = ty0.index_select(0, gid) + torch.div(local, nxg.clamp_min(1), rounding_mode="floor")

    # Exact test of each pair against the opacity ellipse over the tile's pixel centres.
    dt = means2d.dtype
    x0 = (tile_x * ts).to(dt) + 0.5
    x1 = torch.clamp_max((tile_x * ts + ts), width).to(dt) - 0.5
    y0 = (tile_y * ts).to(dt) + 0.5
    y1 = torch.clamp_max((tile_y * ts + ts), height).to(dt) - 0.5
    mxg, myg = mx.index_select(0, gid), my.index_select(0, gid)
    cg = conics.index_select(0, gid)
    smin = _rect_min_sigma(cg[:, 0], cg[:, 1], cg[:, 2], x0 - mxg, x1 - mxg, y0 - myg, y1 - myg)
    keep = smin <= level_s.index_select(0, gid)
    gid = gid[keep]
    tile_id = (tile_y * tx_n + tile_x)[keep]

    # Pairs were generated in Gaussian (= depth) order, so a stable sort by tile keeps depth order inside tiles.
    tile_id, order = torch.sort(tile_id, stable=True)
    gid = gid.index_select(0, order)
    counts = torch.bincount(tile_id, minlength=tx_n * ty_n)
    starts = torch.cumsum(counts, 0) - counts
    gids = torch.cat([gid, torch.full((1,), m, dtype=torch.long, device=device)])
    return TileBins(tile_size=ts, tiles_x=tx_n, tiles_y=ty_n, num_gaussians=m, gids=gids, starts=starts,
                    counts=counts, n_candidates=n_cand)
