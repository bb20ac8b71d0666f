"""The SDF network of the mesh stage (after Gaussian Head Avatar's MeshHeadModule) and mesh extraction.

``SDFNet(x) -> (sdf [N], offset [N, 3], feature [N, 128])`` for world points x [N, 3]:

- inputs are mapped from the configured box to [-1, 1]^3 and positionally encoded with 4 frequencies
  (x, sin(2^k pi x), cos(2^k pi x), k = 0..3 -> 3 + 24 = 27 inputs);
- 5 hidden layers of 256 with the encoded input concatenated again before the 4th (a skip);
- heads: the SDF (world units, negative inside), a tet-vertex offset bounded by ``tanh / grid_res`` in the
  box's normalized units (at most half a cell of the [-1, 1] grid, so deformed tets rarely invert), and a
  128-d feature that later seeds the Gaussians' features.

:func:`pretrain_sphere` fits the network to a sphere so fitting starts from a closed surface;
:func:`extract_mesh` runs DMTet on a tet grid (differentiably when asked).
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass

import torch
from torch import nn

from geometry.dmtet import marching_tets
from geometry.tets import tet_grid
from toolkit.errors import ToolkitError, one_line

CHECKPOINT_KIND = "ditgaze.sdf_net"


@dataclass
class SDFNetConfig:
    """Architecture and the world box the network lives in."""

    n_freqs: int = 4
    """Positional-encoding frequencies (4 -> 27 inputs)."""
    hidden: int = 256
    """Width of the hidden layers."""
    n_layers: int = 5
    """Number of hidden layers."""
    skip_at: int = 3
    """Hidden layer (0-based) that receives the encoded input again."""
    feature_dim: int = 128
    """Width of the feature head."""
    grid_res: int = 64
    """Tet grid resolution the offsets are bounded for (|offset| <= 1 / grid_res, normalized units)."""
    box_min: tuple[float, float, float] = (-1.0, -1.0, -1.0)
    """World-space box mapped to [-1, 1]^3."""
    box_max: tuple[float, float, float] = (1.0, 1.0, 1.0)
    softplus_beta: float = 100.0
    """Smooth ReLU (as in IDR/NeuS) so the SDF has continuous gradients for the eikonal term."""

    def validate(self) -> "SDFNetConfig":
        lo, hi = torch.tensor(self.box_min), torch.tensor(self.box_max)
        if lo.shape != (3,) or hi.shape != (3,) or not bool((hi > lo).all()):
            raise ToolkitError(f"SDFNetConfig: box_min < box_max expected on every axis, got {self.box_min} {self.box_max}")
        if self.n_layers < 2 or not 0 < self.skip_at < self.n_layers or self.hidden < 1 or self.grid_res < 1:
            raise ToolkitError(f"SDFNetConfig: bad architecture {asdict(self)}")
        for name in ("n_freqs", "feature_dim"):  # 0 is legal: no encoding frequencies, no feature head
            if getattr(self, name) < 0:
                raise ToolkitError(f"SDFNetConfig.{name}: expected >= 0, got {getattr(self, name)}")
        if not 0 < self.softplus_beta < math.inf:  # NaN too; beta 0 divides by zero in the softplus
            raise ToolkitError(f"SDFNetConfig.softplus_beta: expected a finite value > 0, got {self.softplus_beta}")
        return self


def positional_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """[N, 3] in [-1, 1] -> [N, 3 + 6 n_freqs]: x, then sin and cos of 2^k pi x."""
    freqs = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * math.pi
    xf = (x[:, None, :] * freqs[:, None]).reshape(x.shape[0], 3 * n_freqs)
    return torch.cat([x, torch.sin(xf), torch.cos(xf)], -1)


class SDFNet(nn.Module):
    """PE -> MLP (skip) -> SDF, bounded tet offset, feature (see module doc)."""

    def __init__(self, config: SDFNetConfig | None = None):
        super().__init__()
        self.config = cfg = (config or SDFNetConfig()).validate()
        self.in_dim = 3 + 6 * cfg.n_freqs
        lo, hi = torch.tensor(cfg.box_min), torch.tensor(cfg.box_max)
        self.register_buffer("center", (lo + hi) / 2, persistent=False)
        self.register_buffer("half_size", (hi - lo) / 2, persistent=False)
        layers = []
        for i in range(cfg.n_layers):
            d_in = self.in_dim if i == 0 else cfg.hidden
            if i == cfg.skip_at:
                d_in += self.in_dim
            layers.append(nn.Linear(d_in, cfg.hidden))
        self.layers = nn.ModuleList(layers)
        self.act = nn.Softplus(beta=cfg.softplus_beta)
        self.head = nn.Linear(cfg.hidden, 1 + 3 + cfg.feature_dim)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        # Small, centred init: the SDF head starts near zero, the offsets near zero (tanh), so pre-training
        # towards a sphere is quick; the skip layer is scaled down so it does not dominate at start.
        for lin in self.layers:
            nn.init.kaiming_uniform_(lin.weight, a=math.sqrt(5))
            nn.init.zeros_(lin.bias)
        nn.init.normal_(self.head.weight, std=1e-3)
        nn.init.zeros_(self.head.bias)

    @property
    def scale(self) -> torch.Tensor:
        """World units per normalized unit (the SDF is predicted in normalized units, scaled by the mean)."""
        return self.half_size.mean()

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.center) / self.half_size

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """[N, 3] world points -> (sdf [N] world units, offset [N, 3] world units, feature [N, F])."""
        if x.dim() != 2 or x.shape[1] != 3:
            raise ToolkitError(f"SDFNet: points expected [N, 3], got {list(x.shape)}")
        pe = positional_encoding(self.normalize(x), self.config.n_freqs)
        h = pe
        for i, lin in enumerate(self.layers):
            if i == self.config.skip_at:
                h = torch.cat([h, pe], -1) / math.sqrt(2)
            h = self.act(lin(h))
        out = self.head(h)
        sdf = out[:, 0] * self.scale
        offset = torch.tanh(out[:, 1:4]) / self.config.grid_res * self.half_size
        return sdf, offset, out[:, 4:]

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward(x)[0]

    @torch.no_grad()
    def evaluate(self, x: torch.Tensor, chunk: int = 65536) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Chunked, gradient-free forward for large point sets."""
        outs = [self.forward(x[i:i + chunk]) for i in range(0, x.shape[0], chunk)]
        return tuple(torch.cat(o, 0) for o in zip(*outs))  # type: ignore[return-value]

    # ------------------------------------------------------------------ storage
    def save(self, path: str | os.PathLike, info: dict | None = None) -> None:
        from toolkit.io import save_checkpoint

        meta = {"kind": CHECKPOINT_KIND, "config": asdict(self.config), **(info or {})}
        save_checkpoint(path, self.state_dict(), meta)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "SDFNet":
        from toolkit.io import load_checkpoint

        state, info = load_checkpoint(path)
        if info.get("kind") != CHECKPOINT_KIND:
            raise ToolkitError(f"{path}: not an SDF network checkpoint (kind={info.get('kind')!r}, expected {CHECKPOINT_KIND!r})")
        cfg = info.get("config", {})
        try:
            cfg = SDFNetConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items()})
            net = cls(cfg)
            net.load_state_dict(state)
        except (TypeError, RuntimeError) as e:
            raise ToolkitError(f"{path}: SDF checkpoint does not match the network ({one_line(e, 160)})") from None
        return net


# ---------------------------------------------------------------------------------------- sphere init
@dataclass
class SphereInit:
    """Pre-training target: a sphere (world units) and the optimisation budget."""

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.5
    steps: int = 300
    batch: int = 4096
    lr: float = 1e-3
    seed: int = 0


def pretrain_sphere(net: SDFNet, init: SphereInit | None = None) -> float:
    """Regress the SDF to a sphere and the offsets to zero; returns the final mean |sdf error| (world)."""
    init = init or SphereInit()
    if not 0 < init.radius < math.inf or not all(math.isfinite(v) for v in init.center):
        raise ToolkitError(f"pretrain_sphere: expected a finite centre and a radius > 0, got {init.center}, "
                           f"{init.radius}")
    if init.steps < 1 or init.batch < 1:
        raise ToolkitError(f"pretrain_sphere: expected steps >= 1 and batch >= 1, got {init.steps} and {init.batch}")
    g = torch.Generator().manual_seed(init.seed)
    c = torch.tensor(init.center, dtype=torch.float32)
    opt = torch.optim.Adam(net.parameters(), lr=init.lr)
    err = float("nan")
    for _ in range(init.steps):
        # Half the samples uniform in the box, half in a shell around the target surface.
        u = (torch.rand(init.batch // 2, 3, generator=g) * 2 - 1) * net.half_size + net.center
        d = torch.nn.functional.normalize(torch.randn(init.batch - init.batch // 2, 3, generator=g), dim=-1)
        shell = c + d * (init.radius + torch.randn(d.shape[0], 1, generator=g) * 0.1 * init.radius)
        x = torch.cat([u, shell])
        target = (x - c).norm(dim=-1) - init.radius
        sdf, offset, _ = net(x)
        loss = (sdf - target).abs().mean() / net.scale + offset.square().mean() / net.scale**2
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        err = float((sdf.detach() - target).abs().mean())
    return err


# ---------------------------------------------------------------------------------------- extraction
def extract_mesh(net: SDFNet, res: int = 64, kind: str = "kuhn", *, use_offsets: bool = True,
                 differentiable: bool = False, grid: tuple[torch.Tensor, torch.Tensor] | None = None,
                 with_features: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """DMTet mesh of the network's zero set on a ``kind`` grid of ``res`` over the network's box.

    With ``differentiable``, the network is evaluated without gradients on the whole grid, then again
    with gradients only at the vertices of the tets the surface crosses: the mesh is differentiable
    w.r.t. the network at a fraction of a full-grid backward pass.
    The offsets are bounded to half a cell of the network's ``grid_res``; on a finer grid they are clamped
    to half a cell of ``res``, the same bound relative to the grid, so a vertex never moves past the middle
    of its cell (DMTet's bound; saturated offsets can still invert a tet, at any resolution).
    Returns verts [M, 3], faces [F, 3], features [M, F] (or None).
    """
    if grid is None:
        grid = tet_grid(kind, res, net.config.box_min, net.config.box_max)
    verts, tets = grid
    verts = verts.to(net.center.device)
    sdf, offset, feat = net.evaluate(verts)
    bound = net.half_size / res if res > net.config.grid_res else None

    def moved(offset):
        if not use_offsets:
            return verts
        return verts + (offset if bound is None else torch.maximum(torch.minimum(offset, bound), -bound))

    if not differentiable:
        return marching_tets(moved(offset), tets, sdf, feat if with_features else None)
    with torch.no_grad():
        inside = (sdf < 0).to(torch.uint8)[tets]
        n_in = inside.sum(1)
        active = torch.unique(tets[(n_in > 0) & (n_in < 4)].reshape(-1))
    s2, o2, f2 = net(verts[active])
    sdf = sdf.index_put((active,), s2)
    offset = offset.index_put((active,), o2)
    feat = feat.index_put((active,), f2) if with_features else None
    return marching_tets(moved(offset), tets, sdf, feat)
