"""Vectorized tile binning: which depth-sorted Gaussians may touch which screen tile.

A Gaussian can only reach alpha >= 1/255 where sigma <= ln(255 o) (its "opacity ellipse"). Each Gaussian
gets the tiles of that ellipse's bounding box, then every (Gaussian, tile) pair is tested exactly against
the ellipse (minimum of the quadratic over the tile's pixel centres), so no work is spent on tiles a
Gaussian cannot change. Culling is conservative by a tiny margin: the per-pixel test decides.

Several images are binned at once: each Gaussian belongs to one image, and image i's tiles are numbered after
those of images 0 .. i-1, so one sweep over all tiles renders every camera of a batch with the same few
tensor ops (what keeps a GPU busy is the number of kernel launches, not their size).
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
    starts, counts [tiles] int64: each tile's slice of ``gids``. Tiles are row-major, ``tiles_x`` per row,
    image after image (``num_images`` of them, ``tiles_per_image`` each).
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    num_gaussians: int
    gids: torch.Tensor
    starts: torch.Tensor
    counts: torch.Tensor
    n_candidates: int  # pairs from the bounding boxes, before the exact ellipse test
    num_images: int = 1

    @property
    def n_pairs(self) -> int:
        return int(self.gids.numel()) - 1

    @property
    def tiles_per_image(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def num_tiles(self) -> int:
        return self.num_images * self.tiles_per_image


def opacity_levels(opacities: torch.Tensor, alpha_min: float = ALPHA_MIN) -> torch.Tensor:
    """[M] ln(o / alpha_min): the sigma below which alpha = o exp(-sigma) reaches alpha_min (<= 0: never)."""
    return torch.log(opacities.clamp_min(1e-30) / alpha_min)


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


_CANDIDATE_BUDGET = 1 << 21


def _test_candidates(g0, g1, n_per, tx0, ty0, nx, means2d, conics, level_s, width, height, ts, tx_n, tile_base):
    """Expand Gaussians g0 .. g1 - 1 into their candidate tiles and keep the pairs whose opacity ellipse
    reaches the tile's pixel centres -> (gid [K], tile_id [K]) in Gaussian order; ``tile_base`` [M] is the
    first tile id of each Gaussian's image."""
    device = means2d.device
    n_sub = n_per[g0:g1]
    total = int(n_sub.sum())
    gid = torch.repeat_interleave(torch.arange(g0, g1, device=device), n_sub, output_size=total)
    first = torch.cumsum(n_sub, 0) - n_sub
    local = torch.arange(total, device=device) - first.index_select(0, gid - g0)
    nxg = nx.index_select(0, gid).clamp_min(1)
    tile_x = tx0.index_select(0, gid) + local % nxg
    tile_y = ty0.index_select(0, gid) + torch.div(local, nxg, rounding_mode="floor")
    dt = means2d.dtype
    x0 = (tile_x * ts).to(dt) + 0.5
    x1 = torch.clamp_max((tile_x * ts + ts), width).to(dt) - 0.5
    y0 = (tile_y * ts).to(dt) + 0.5
    y1 = torch.clamp_max((tile_y * ts + ts), height).to(dt) - 0.5
    mxg, myg = means2d[:, 0].index_select(0, gid), means2d[:, 1].index_select(0, gid)
    cg = conics.index_select(0, gid)
    smin = _rect_min_sigma(cg[:, 0], cg[:, 1], cg[:, 2], x0 - mxg, x1 - mxg, y0 - myg, y1 - myg)
    keep = smin <= level_s.index_select(0, gid)
    return gid[keep], (tile_base.index_select(0, gid) + tile_y * tx_n + tile_x)[keep]


@torch.no_grad()
def bin_gaussians(means2d: torch.Tensor, conics: torch.Tensor, cov2d: torch.Tensor, opacities: torch.Tensor,
                  width: int, height: int, tile_size: int, alpha_min: float = ALPHA_MIN, *,
                  image_ids: torch.Tensor | None = None, num_images: int = 1) -> TileBins:
    """means2d [M, 2], conics [M, 3], cov2d [M, 3] (dilated xx, xy, yy), opacities [M], all for Gaussians
    already sorted front to back within each image -> TileBins. ``image_ids`` [M] int64 (default all 0) says
    which of ``num_images`` images (all ``width`` x ``height``) each Gaussian is drawn into. No Python loop
    over Gaussians, tiles or images (only over groups of ~2M candidate pairs, to bound memory)."""
    device = means2d.device
    ts = int(tile_size)
    tx_n, ty_n = math.ceil(width / ts), math.ceil(height / ts)
    m = means2d.shape[0]
    if image_ids is None:
        image_ids = torch.zeros(m, dtype=torch.long, device=device)
    tile_base = image_ids * (tx_n * ty_n)
    level = opacity_levels(opacities, alpha_min)
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

    # Candidates are expanded and tested in groups of consecutive Gaussians so the per-candidate temporaries
    # stay bounded (a few hundred MB at most) however many pairs a scene has.
    cum = torch.cumsum(n_per, 0)
    gids_kept, tiles_kept = [], []
    g0 = 0
    while g0 < m and n_cand:
        before = int(cum[g0 - 1]) if g0 else 0
        g1 = int(torch.searchsorted(cum, torch.tensor(before + _CANDIDATE_BUDGET, device=device), right=True))
        g1 = max(g1, g0 + 1)
        gid, tile_id = _test_candidates(g0, g1, n_per, tx0, ty0, nx, means2d, conics, level_s, width, height, ts,
                                        tx_n, tile_base)
        gids_kept.append(gid)
        tiles_kept.append(tile_id)
        g0 = g1
    gid = torch.cat(gids_kept) if gids_kept else torch.zeros(0, dtype=torch.long, device=device)
    tile_id = torch.cat(tiles_kept) if tiles_kept else torch.zeros(0, dtype=torch.long, device=device)

    # Pairs were generated in Gaussian (= depth) order, so a stable sort by tile keeps depth order inside tiles.
    tile_id, order = torch.sort(tile_id, stable=True)
    gid = gid.index_select(0, order)
    counts = torch.bincount(tile_id, minlength=num_images * tx_n * ty_n)
    starts = torch.cumsum(counts, 0) - counts
    gids = torch.cat([gid, torch.full((1,), m, dtype=torch.long, device=device)])
    return TileBins(tile_size=ts, tiles_x=tx_n, tiles_y=ty_n, num_gaussians=m, gids=gids, starts=starts,
                    counts=counts, n_candidates=n_cand, num_images=int(num_images))
