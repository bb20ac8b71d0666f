"""Marching tetrahedra: run time against surface error on analytic SDFs (Kuhn vs BCC vs subdivision vs MC).

    python benchmarks/dmtet.py [--res 16 32 64 128] [--repeats 3] [--threads N]

Shapes: an off-centre sphere, a tilted torus and a head-like smooth blend (ellipsoid + nose + eyes).
Surface error = |f(p)| / |grad f(p)| at the output vertices (exact distance for the sphere and torus,
first-order estimate for the blend) and at face centroids (chordal error); ``order`` is
log2(error at res/2 / error at res) of the centroid error: 2 means second-order decay. Times are
``marching_tets`` only (grid from the disk cache, SDF evaluated beforehand), median of ``--repeats``.
Marching cubes runs at the same number of SDF samples when scikit-image is installed.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

from benchmarks.common import OUT_DIR, format_table, machine_info, save_plot, timeit  # noqa: E402
from geometry.dmtet import marching_tets  # noqa: E402
from geometry.tets import subdivide, tet_grid  # noqa: E402


def sphere(p):
    return (p - torch.tensor([0.13, -0.07, 0.05], dtype=p.dtype)).norm(dim=-1) - 0.55


_TILT = None


def torus(p):
    global _TILT
    if _TILT is None or _TILT.dtype != p.dtype:
        a = math.radians(30)
        _TILT = torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]], dtype=p.dtype)
    q = (p - torch.tensor([0.05, 0.02, -0.03], dtype=p.dtype)) @ _TILT.T
    return torch.stack([torch.sqrt(q[:, 0] ** 2 + q[:, 2] ** 2) - 0.5, q[:, 1]], -1).norm(dim=-1) - 0.2


def _smin(a, b, k):
    h = (0.5 + 0.5 * (b - a) / k).clamp(0, 1)
    return b * (1 - h) + a * h - k * h * (1 - h)


def head(p):
    """Ellipsoid skull (approximate SDF), nose and eyeballs blended with a polynomial smooth-min."""
    axes = torch.tensor([0.6, 0.8, 0.7], dtype=p.dtype)
    q = p / axes
    k0 = q.norm(dim=-1)
    k1 = (q / axes).norm(dim=-1)
    # (The bound k0 (k0 - 1) / k1 is 0/0 at the centre: use -min(axes) there, or the centre is a zero.)
    skull = torch.where(k1 > 1e-6, k0 * (k0 - 1) / k1.clamp_min(1e-6), -axes.min().expand_as(k0))
    nose = (p - torch.tensor([0.0, 0.1, -0.68], dtype=p.dtype)).norm(dim=-1) - 0.12
    eyes = torch.minimum((p - torch.tensor([-0.24, -0.08, -0.56], dtype=p.dtype)).norm(dim=-1) - 0.11,
                         (p - torch.tensor([0.24, -0.08, -0.56], dtype=p.dtype)).norm(dim=-1) - 0.11)
    return _smin(_smin(skull, nose, 0.08), eyes, 0.04)


SHAPES = {"sphere": sphere, "torus": torus, "head": head}


def surface_error(fn, pts: torch.Tensor) -> torch.Tensor:
    """|f| / |grad f| in float64 (distance to the zero set, to first order)."""
    x = pts.detach().double().requires_grad_(True)
    f = fn(x)
    (g,) = torch.autograd.grad(f.sum(), x)
    return (f.abs() / g.norm(dim=-1).clamp_min(1e-12)).detach()


def run_case(fn, kind, res, repeats, subdiv=False):
    v, t = tet_grid(kind, res // 2 if subdiv else res)
    if subdiv:
        v, t, _ = subdivide(v, t)
    s = fn(v)
    secs = timeit(lambda: marching_tets(v, t, s), repeats=repeats, warmup=1)
    mv, mf, _ = marching_tets(v, t, s)
    cen = mv[mf].mean(1)
    e_v, e_c = surface_error(fn, mv), surface_error(fn, cen)
    return {"grid_verts": v.shape[0], "tets": t.shape[0], "out_verts": mv.shape[0], "faces": mf.shape[0],
            "time_s": secs, "vert_err_max": float(e_v.max()), "face_err_mean": float(e_c.mean()),
            "face_err_max": float(e_c.max())}


def run_mc(fn, res, repeats):
    try:
        from skimage.measure import marching_cubes
    except ImportError:
        return None
    r = torch.linspace(-1, 1, res + 1, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1)
    vol = fn(grid.reshape(-1, 3)).reshape(res + 1, res + 1, res + 1).float().numpy()
    h = 2.0 / res
    secs = timeit(lambda: marching_cubes(vol, 0.0, spacing=(h, h, h)), repeats=repeats, warmup=1)
    verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=(h, h, h))
    mv = torch.from_numpy(verts.copy()).double() - 1.0
    mf = torch.from_numpy(faces.astype("int64"))
    e_v, e_c = surface_error(fn, mv), surface_error(fn, mv[mf].mean(1))
    return {"grid_verts": (res + 1) ** 3, "tets": 0, "out_verts": mv.shape[0], "faces": mf.shape[0], "time_s": secs,
            "vert_err_max": float(e_v.max()), "face_err_mean": float(e_c.mean()), "face_err_max": float(e_c.max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, nargs="+", default=[16, 32, 64, 128])
    ap.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=list(SHAPES))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave the default)")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    print(machine_info())
    print(f"load average: {os.getloadavg()}")
    rows, series = [], {}
    methods = [("kuhn", False), ("bcc", False), ("kuhn+subdiv", True), ("mc", False)]
    for shape in a.shapes:
        fn = SHAPES[shape]
        for name, subdiv in methods:
            prev = None
            for res in a.res:
                if name == "mc":
                    r = run_mc(fn, res, a.repeats)
                    if r is None:
                        continue
                else:
                    r = run_case(fn, name.split("+")[0], res, a.repeats, subdiv)
                cell = 2.0 / res
                order = math.log2(prev / r["face_err_mean"]) if prev else None
                prev = r["face_err_mean"]
                row = {"shape": shape, "method": name, "res": res, **r, "face_err/cell": r["face_err_mean"] / cell,
                       "order": order}
                rows.append(row)
                print(format_table([row]).splitlines()[-1], flush=True)
                series.setdefault(f"{shape} {name}", ([], []))
                series[f"{shape} {name}"][0].append(r["time_s"])
                series[f"{shape} {name}"][1].append(r["face_err_mean"])
    cols = ["shape", "method", "res", "tets", "out_verts", "faces", "time_s", "vert_err_max", "face_err_mean",
            "face_err/cell", "order"]
    print()
    print(format_table(rows, cols))
    try:
        import skimage  # noqa: F401
    except ImportError:
        print("marching cubes: scikit-image is not installed, so the MC rows are left out")
    path = save_plot(OUT_DIR / "dmtet.png", series, xlabel="marching time (s)", ylabel="mean face-centroid error",
                     title="DMTet: run time vs surface error (Kuhn, BCC, Kuhn+subdivision, MC)", logx=True, logy=True)
    print(f"plot: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
