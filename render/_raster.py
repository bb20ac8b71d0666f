"""Tile rasterization of projected Gaussians as one custom autograd Function.

Work is organised in *rounds*: in each round every still-active tile takes its next chunk of Gaussians
from its depth-sorted list (``chunk`` entries, more once few tiles are left), so one round is a handful of
large batched tensor ops over [tiles, chunk, pixels-per-tile]. A tile leaves the sweep when its list is
exhausted or when every one of its pixels has terminated (T (1 - alpha) <= T_MIN), so empty tiles and
finished pixels cost nothing more. The tiles of all cameras of a call are swept together (``TileBins`` numbers
them image after image), so a batch of C images takes the rounds of its longest tile list, not C times as
many: on a GPU the cost is the number of kernel launches, which does not grow with C.

Memory-lean backward: nothing of size [pixels x Gaussians] is saved (only the final colour and T per pixel).
The backward re-runs the same rounds (bit-identical alphas and transmittances, hence the same stops) and
gets the colour seen *behind* each Gaussian from the saved final colour: R_i = C - sum_{j <= i} w_j c_j
(which includes T_final * background). This is the quantity the 3DGS back-to-front pass accumulates; going
front to back from T = 1 instead of dividing T_final by (1 - alpha) step after step avoids that recurrence's
error growth and costs the same memory. Projecting on dL/dC first keeps the running sums [tiles, chunk,
pixels] instead of [..., D].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from render._tiles import TileBins

ALPHA_MAX = 0.99  # 3DGS clamps alpha below 1 so 1 - alpha stays invertible
ALPHA_MIN = 1.0 / 255.0  # contributions below one 8-bit level are skipped
T_MIN = 1e-4  # a pixel stops before the Gaussian that would bring T (1 - alpha) to <= T_MIN
# exp() of arguments below ~-87 produces float32 denormals and runs 10-40x slower on CPU; anything
# below this floor is far under ALPHA_MIN anyway.
EXP_FLOOR = -30.0
_DUMMY_LOGO = -1e4  # log-opacity of the padding Gaussian: alpha = 0 exactly after the floor + threshold


@dataclass(frozen=True)
class RasterConfig:
    """Knobs of the sweep (defaults are the reference 3DGS thresholds)."""

    chunk: int | None = None  # Gaussians per tile per round; None: auto_chunk()
    max_elements: int = 1 << 21  # bound on tiles x chunk x pixels per batched step (peak memory)
    alpha_min: float = ALPHA_MIN
    alpha_max: float = ALPHA_MAX
    t_min: float = T_MIN


MIN_CHUNK = 32
ROUND_ELEMENTS = 1 << 18


def auto_chunk(active_tiles: int, pixels_per_tile: int) -> int:
    """Gaussians per tile per round when none is given: at least ``MIN_CHUNK``, and long enough that a round
    covers ``ROUND_ELEMENTS`` (tile, Gaussian, pixel) triples. Each round costs ~20 small tensor ops whatever
    its size, so on a small image (few tiles) short chunks are all overhead: at 32x32 with 6000 Gaussians,
    chunk 32 takes 94 ms per forward + backward and the auto chunk (256) 50 ms. Images with >= 128 tiles of
    8x8 keep ``MIN_CHUNK``."""
    return max(MIN_CHUNK, ROUND_ELEMENTS // max(1, active_tiles * pixels_per_tile))


def _gaussian_table(means2d, conics, opacities, dtype):
    """[M + 1, 9] per-Gaussian constants of the alpha exponent; the last row is the padding dummy."""
    a, b, c = conics.unbind(-1)
    logo = torch.log(opacities)
    tab = torch.stack([means2d[:, 0], means2d[:, 1], -0.5 * a, -b, -0.5 * c, logo, a, b, c], -1).to(dtype)
    dummy = torch.zeros(1, 9, dtype=dtype, device=tab.device)
    dummy[0, 5] = _DUMMY_LOGO
    return torch.cat([tab, dummy], 0)


class _Sweep:
    """Front-to-back state of every pixel (tile layout [tiles, ts*ts]) and the round schedule."""

    def __init__(self, bins: TileBins, width: int, height: int, cfg: RasterConfig, dtype, device):
        self.bins, self.cfg, self.dtype = bins, cfg, dtype
        ts = bins.tile_size
        nt, P = bins.num_tiles, ts * ts
        self.device = device
        self.ar_t = torch.arange(ts, device=device)
        self.T = torch.ones(nt, P, dtype=dtype, device=device)
        # Pixels of edge tiles that lie outside the image start terminated, so they never hold a tile back.
        ty, tx = torch.meshgrid(torch.arange(bins.tiles_y, device=device), torch.arange(bins.tiles_x, device=device),
                                indexing="ij")
        col = (tx.reshape(-1, 1, 1) * ts + self.ar_t.view(1, 1, ts))
        row = (ty.reshape(-1, 1, 1) * ts + self.ar_t.view(1, ts, 1))
        self.inside = ((col < width) & (row < height)).view(bins.tiles_per_image, P).repeat(bins.num_images, 1)
        self.done = ~self.inside
        self.log_amax = math.log(cfg.alpha_max)
        # threshold() keeps x > thr: the largest value below alpha_min (in this dtype) keeps alpha >= alpha_min.
        amin = torch.tensor(cfg.alpha_min, dtype=dtype)
        self.alpha_thr = float(torch.nextafter(amin, torch.zeros_like(amin)))
        self.rounds_run = 0
        self.tiles_terminated = 0

    def rounds(self):
        """Yield (pos, B, A): list offset, chunk length and a slice of active tile ids; the state is updated
        by :meth:`transmit` between yields. As tiles leave the sweep the chunk grows (up to 8x ``chunk``) so
        a round stays about as large as the first one: long-tailed tile lists then take few rounds."""
        bins, P = self.bins, self.bins.tile_size ** 2
        active = torch.nonzero(bins.counts > 0).flatten()
        # The chunk of one image's share of the active tiles: batching images must not shorten it (more rounds).
        B0 = self.cfg.chunk or auto_chunk(-(-active.numel() // bins.num_images), P)
        target = active.numel() * B0
        pos = 0
        while active.numel() > 0:
            longest = int(bins.counts.index_select(0, active).max()) - pos
            B = max(1, min(longest, max(B0, min(8 * B0, target // active.numel()))))
            for A in active.split(max(1, self.cfg.max_elements // (B * P))):
                yield pos, B, A
            pos += B
            self.rounds_run += 1
            more = active[bins.counts.index_select(0, active) > pos]
            left = ~self.done.index_select(0, more).all(1)
            self.tiles_terminated += int(more.numel() - int(left.sum()))
            active = more[left]

    def alphas(self, table: torch.Tensor, A: torch.Tensor, pos: int, B: int, check_sigma: bool,
               want_unclamped: bool = False):
        """Alphas [nA, B, P] of list entries pos .. pos + B - 1 of tiles A, with the gathered Gaussian ids and
        pixel offsets (and, when asked, the mask of alphas below the alpha_max clamp, where dalpha/dt = alpha)."""
        bins, ts = self.bins, self.bins.tile_size
        nA = A.numel()
        start = bins.starts.index_select(0, A)
        end = start + bins.counts.index_select(0, A)
        idx = (start + pos)[:, None] + torch.arange(B, device=self.device)[None, :]
        idx = torch.where(idx < end[:, None], idx, torch.full_like(idx, bins.n_pairs))
        g = bins.gids.index_select(0, idx.view(-1))
        prm = table.index_select(0, g).view(nA, B, -1)
        local = A % bins.tiles_per_image  # tile index inside its own image
        px = ((local % bins.tiles_x) * ts)[:, None] + self.ar_t[None, :]
        py = (torch.div(local, bins.tiles_x, rounding_mode="floor") * ts)[:, None] + self.ar_t[None, :]
        dx = (px.to(self.dtype) + 0.5)[:, None, :] - prm[..., 0, None]  # [nA, B, ts] per column
        dy = (py.to(self.dtype) + 0.5)[:, None, :] - prm[..., 1, None]  # [nA, B, ts] per row
        # log(o) - sigma split by row and column: two full-size passes before the exp.
        col_term = prm[..., 2, None] * dx * dx
        row_term = prm[..., 4, None] * dy * dy + prm[..., 5, None]
        t = row_term[..., :, None] + col_term[..., None, :]
        t.addcmul_(dy[..., :, None], (prm[..., 3, None] * dx)[..., None, :])
        t = t.view(nA, B, ts * ts)
        neg_sigma = t > prm[..., 5, None] if check_sigma else None
        unclamped = t < self.log_amax if want_unclamped else None
        # min(alpha_max, o exp(-sigma)) as exp(min(log alpha_max, t)): one pass fewer; equal to rounding.
        alpha = F.threshold_(t.clamp_(EXP_FLOOR, self.log_amax).exp_(), self.alpha_thr, 0.0)
        if neg_sigma is not None:
            alpha.masked_fill_(neg_sigma, 0.0)
        return g, prm, dx, dy, alpha, unclamped

    def transmit(self, A: torch.Tensor, alpha: torch.Tensor):
        """Front-to-back compositing of one chunk: weights w [nA, B, P] (zero past each pixel's stop) and
        TB [nA, B + 1, P], the transmittance before each Gaussian and after the last; updates T and the
        terminated flags of tiles A."""
        T_old = self.T.index_select(0, A)
        done_old = self.done.index_select(0, A)
        T_in = T_old.masked_fill(done_old, 0.0)  # terminated pixels composite nothing more (w = 0)
        nA, B, P = alpha.shape
        TB = alpha.new_empty(nA, B + 1, P)
        TB[:, 0] = T_in
        torch.mul(torch.cumprod(1.0 - alpha, 1), T_in[:, None], out=TB[:, 1:])
        w = torch.mul(alpha, TB[:, :-1])
        last = TB[:, -1]
        # T only decreases along the chunk, so a pixel whose T after the whole chunk is still above t_min
        # keeps every Gaussian of it: the stop mask is only built for the few tiles where some pixel stops.
        stopping = (last <= self.cfg.t_min) & ~done_old
        T_new = torch.where(done_old, T_old, last)
        S = torch.nonzero(stopping.any(1)).flatten()
        if S.numel():
            TBs = TB.index_select(0, S)
            incl = TBs[:, 1:] > self.cfg.t_min  # a prefix along B
            w.index_copy_(0, S, w.index_select(0, S).mul_(incl))
            T_stop = TBs.gather(1, incl.sum(1, keepdim=True)).squeeze(1)
            T_new.index_copy_(0, S, torch.where(stopping.index_select(0, S), T_stop, T_new.index_select(0, S)))
        self.T.index_copy_(0, A, T_new)
        self.done.index_copy_(0, A, done_old | stopping)
        return w, TB


def to_tiles(img: torch.Tensor, bins: TileBins) -> torch.Tensor:
    """[C, H, W, D] -> [tiles, D, ts*ts] (zero padded). Channels before pixels so the colour products are
    plain [D, B] x [B, P] matmuls without transposed operands."""
    C, H, W, D = img.shape
    ts = bins.tile_size
    pad = img.new_zeros(C, bins.tiles_y * ts, bins.tiles_x * ts, D)
    pad[:, :H, :W] = img
    return (pad.view(C, bins.tiles_y, ts, bins.tiles_x, ts, D).permute(0, 1, 3, 5, 2, 4)
            .reshape(bins.num_tiles, D, ts * ts))


def from_tiles(t: torch.Tensor, bins: TileBins, width: int, height: int) -> torch.Tensor:
    """[tiles, D, ts*ts] -> [C, H, W, D]."""
    ts, D = bins.tile_size, t.shape[1]
    img = t.view(bins.num_images, bins.tiles_y, bins.tiles_x, D, ts, ts).permute(0, 1, 4, 2, 5, 3)
    return img.reshape(bins.num_images, bins.tiles_y * ts, bins.tiles_x * ts, D)[:, :height, :width]


_BASIS: dict = {}


def self_basis(ts: int, dtype, device) -> torch.Tensor:
    """[ts, 3] columns (1, u, u^2) at the tile-local pixel centres u = 0.5 .. ts - 0.5 (cached)."""
    key = (ts, dtype, str(device))
    if key not in _BASIS:
        u = torch.arange(ts, dtype=dtype, device=device) + 0.5
        _BASIS[key] = torch.stack([torch.ones_like(u), u, u * u], -1)
    return _BASIS[key]


class RasterizeTiles(torch.autograd.Function):
    """(means2d [M, 2], conics [M, 3], opacities [M], colors [M, D], background [C, D]) -> (image [C, H, W, D],
    alpha [C, H, W, 1]) for the C = ``bins.num_images`` images; each Gaussian is drawn into one image (its
    2D parameters are that camera's), they are sorted front to back within each image and binned by
    ``render._tiles.bin_gaussians``."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, bins, width, height, cfg, check_sigma, stats):
        dtype, device = colors.dtype, colors.device
        D = colors.shape[1]
        table = _gaussian_table(means2d, conics, opacities, dtype)
        col_tab = torch.cat([colors, colors.new_zeros(1, D)], 0)
        sweep = _Sweep(bins, width, height, cfg, dtype, device)
        acc = torch.zeros(bins.num_tiles, D, bins.tile_size ** 2, dtype=dtype, device=device)
        for pos, B, A in sweep.rounds():
            g, _, _, _, alpha, _ = sweep.alphas(table, A, pos, B, check_sigma)
            w, _ = sweep.transmit(A, alpha)
            cols_t = col_tab.index_select(0, g).view(A.numel(), B, D).transpose(1, 2).contiguous()
            acc.index_add_(0, A, torch.bmm(cols_t, w))
        bg_t = background.repeat_interleave(bins.tiles_per_image, 0)  # [tiles, D]: each tile's image's background
        C_t = torch.addcmul(acc, sweep.T[:, None, :], bg_t[:, :, None])
        image = from_tiles(C_t, bins, width, height)
        alpha_img = 1.0 - from_tiles(sweep.T[:, None, :], bins, width, height)
        stats.update(rounds=sweep.rounds_run, tiles_terminated=sweep.tiles_terminated,
                     pixels_terminated=int((sweep.done & sweep.inside).sum()))
        ctx.save_for_backward(means2d, conics, opacities, colors, background, C_t, sweep.T)
        ctx.bins, ctx.size, ctx.cfg, ctx.check_sigma = bins, (width, height), cfg, check_sigma
        return image, alpha_img

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        means2d, conics, opacities, colors, background, C_t, T_final = ctx.saved_tensors
        bins, (width, height), cfg = ctx.bins, ctx.size, ctx.cfg
        dtype, device = colors.dtype, colors.device
        M, D = colors.shape
        C = bins.num_images
        if grad_image is None:
            grad_image = torch.zeros(C, height, width, D, dtype=dtype, device=device)
        if grad_alpha is None:
            grad_alpha = torch.zeros(C, height, width, 1, dtype=dtype, device=device)
        g_t = to_tiles(grad_image.to(dtype), bins)  # [nt, D, P]
        ga_t = to_tiles(grad_alpha.to(dtype), bins)[:, 0]  # [nt, P]
        Q = (C_t * g_t).sum(1)  # C . dL/dC per pixel: the colour behind the first Gaussian, projected
        gaT = ga_t * T_final  # alpha = 1 - T_final contributes dA/dalpha_i = T_final / (1 - alpha_i)
        grad_bg = torch.einsum("tdp,tp->td", g_t, T_final).view(C, bins.tiles_per_image, D).sum(1)

        table = _gaussian_table(means2d, conics, opacities, dtype)
        col_tab = torch.cat([colors, colors.new_zeros(1, D)], 0)
        grads = torch.zeros(M + 1, 6 + D, dtype=dtype, device=device)
        prefix = torch.zeros_like(Q)  # sum_{j processed} w_j (c_j . g) per pixel
        sweep = _Sweep(bins, width, height, cfg, dtype, device)
        ts = bins.tile_size
        # alpha can only hit the alpha_max clamp (where dalpha/dt = 0) if some opacity reaches it.
        clamp_possible = bool(opacities.numel()) and float(opacities.max()) >= cfg.alpha_max
        base = Q - gaT  # per pixel: C . g minus the alpha-output term (dA/dalpha_i = T_final / (1 - alpha_i))
        for pos, B, A in sweep.rounds():
            nA = A.numel()
            g, prm, dx, dy, alpha, unclamped = sweep.alphas(table, A, pos, B, ctx.check_sigma, clamp_possible)
            w, TB = sweep.transmit(A, alpha)
            gA = g_t.index_select(0, A)  # [nA, D, P]
            cols = col_tab.index_select(0, g).view(nA, B, D)
            cg = torch.bmm(cols, gA)  # [nA, B, P] c_i . g
            grad_cols = torch.bmm(w, gA.transpose(1, 2))  # [nA, B, D]
            wcg = w * cg
            cs = torch.cumsum(wcg, 1)
            # X_i = (colour behind Gaussian i) . g - T_final g_alpha; prefix carries earlier rounds.
            X = (base.index_select(0, A) - prefix.index_select(0, A))[:, None, :] - cs
            prefix.index_add_(0, A, cs[:, -1])
            # dL/dt_i = alpha_i dL/dalpha_i = w_i (c_i . g) - X_i alpha_i / (1 - alpha_i) on included pixels, and
            # alpha_i / (1 - alpha_i) = w_i / T_after_i there (w = 0 elsewhere; the clamp only guards 0 / 0).
            G = wcg.sub_(X.mul_(w).div_(TB[:, 1:].clamp_min(max(0.5 * cfg.t_min, 1e-30))))
            if unclamped is not None:
                G.mul_(unclamped)
            # Moments sum_p G u^i v^j in tile-local pixel coordinates (u, v) = (c + 0.5, r + 0.5), which are the
            # same for every tile: one skinny GEMM over all rows, one over the 3 x ts results. Then centre them
            # on the mean, dx = u - mu (exact algebra; u is in [0.5, ts), so no harmful cancellation).
            mom = (G.view(-1, ts) @ self_basis(ts, dtype, device)).view(nA * B, ts, 3)  # [q, r, i]
            mom = (mom.transpose(1, 2).reshape(-1, ts) @ self_basis(ts, dtype, device)).view(nA, B, 3, 3)
            mu = dx[..., :1].neg().add_(0.5).squeeze(-1)  # tile-local mean: u_0 - dx_0 with u_0 = 0.5
            mv = dy[..., :1].neg().add_(0.5).squeeze(-1)
            m00, m01, m02 = mom[..., 0, 0], mom[..., 0, 1], mom[..., 0, 2]  # [.., i (u power), j (v power)]
            m10, m11, m20 = mom[..., 1, 0], mom[..., 1, 1], mom[..., 2, 0]
            s0 = m00
            sx = m10 - mu * m00
            sy = m01 - mv * m00
            sxx = m20 - 2 * mu * m10 + mu * mu * m00
            syy = m02 - 2 * mv * m01 + mv * mv * m00
            sxy = m11 - mu * m01 - mv * m10 + mu * mv * m00
            a, b, c = prm[..., 6], prm[..., 7], prm[..., 8]
            per_pair = torch.cat([torch.stack([a * sx + b * sy, b * sx + c * sy, -0.5 * sxx, -sxy, -0.5 * syy, s0],
                                              -1), grad_cols], -1)
            grads.index_add_(0, g, per_pair.view(nA * B, 6 + D))
        grads = grads[:M]
        g_means2d = grads[:, 0:2]
        g_conics = grads[:, 2:5]
        g_opac = grads[:, 5] / opacities.clamp_min(1e-30)
        g_colors = grads[:, 6:]
        return (g_means2d, g_conics, g_opac, g_colors, grad_bg.to(background.dtype), None, None, None, None, None,
                None)
