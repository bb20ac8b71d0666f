"""Marching tetrahedra: run time against surface error on analytic SDFs (Kuhn vs BCC vs subdivision vs MC).

    python benchmarks/dmtet.py [--res 16 32 64 128] [--repeats 3] [--threads N] [--shapes sphere torus head]
    python benchmarks/dmtet.py --breakdown-only --threads 2     # just the Kuhn-128 target timing

Shapes: an off-centre sphere, a tilted torus and a head-like smooth blend (ellipsoid + nose + eyes).
Surface error = |f(p)| / |grad f(p)| at the output vertices (exact distance for the sphere and torus,
first-order estimate for the blend) and at face centroids (chordal error); ``order`` is the centroid error's
log(error ratio) / log(res ratio) between a method's consecutive ``--res`` rows: 2 means second-order decay.
``res`` is the lattice actually meshed: ``kuhn+subdiv`` subdivides a res // 2 grid once, so an odd ``--res``
row reads res - 1. ``--res`` is at least 4: coarser grids miss the torus's surface altogether.
``samples`` is the number of SDF evaluations (grid vertices). ``time_s`` is the extraction alone
(``marching_tets``, or ``marching_cubes``), median of ``--repeats``; ``grid_s`` (tet grid from the disk
cache, plus subdivision; the lattice for MC) and ``sdf_s`` (evaluating the analytic SDF) are timed
separately so nothing is hidden. Marching cubes rows (scikit-image, optional extra ``bench``) use the
Kuhn grid's samples: the (res+1)^3 lattice. ``mc-trimesh`` is trimesh's ``matrix_to_marching_cubes``,
which meshes the binary occupancy (sdf < 0), so its vertices sit at edge midpoints (first order).
The closing breakdown times extraction on a Kuhn 128 grid, stage by stage, against its target of <= 0.3 s.
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

from benchmarks.common import OUT_DIR, count, format_table, machine_info, save_plot, timeit  # noqa: E402
from geometry.dmtet import marching_tets  # noqa: E402
from geometry.tets import subdivide, tet_grid  # noqa: E402
from toolkit.errors import CliParser, run_cli  # noqa: E402


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
    def grid():
        v, t = tet_grid(kind, res // 2 if subdiv else res)
        if subdiv:
            v, t, _ = subdivide(v, t)
        return v, t

    grid_s = timeit(grid, repeats=repeats, warmup=1)  # the warm-up builds the disk cache when missing
    v, t = grid()
    sdf_s = timeit(lambda: fn(v), repeats=repeats, warmup=1)
    s = fn(v)
    secs = timeit(lambda: marching_tets(v, t, s), repeats=repeats, warmup=1)
    mv, mf, _ = marching_tets(v, t, s)
    return _errors(fn, mv, mf, {"samples": v.shape[0], "tets": t.shape[0], "grid_s": grid_s, "sdf_s": sdf_s,
                                "time_s": secs})


def _errors(fn, mv, mf, row):
    cen = mv[mf].mean(1)
    e_v, e_c = surface_error(fn, mv), surface_error(fn, cen)
    return {**row, "out_verts": mv.shape[0], "faces": mf.shape[0], "vert_err_max": float(e_v.max()),
            "face_err_mean": float(e_c.mean()), "face_err_max": float(e_c.max())}


def have_skimage() -> bool:
    try:
        import skimage.measure  # noqa: F401
    except ImportError:
        return False
    return True


def run_mc(fn, res, repeats, flavour="skimage"):
    """Marching cubes on the (res+1)^3 lattice over [-1, 1]^3 (the Kuhn grid's samples); None without skimage."""
    if not have_skimage():
        return None
    from skimage.measure import marching_cubes

    def lattice():
        r = torch.linspace(-1, 1, res + 1)
        return torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)

    grid_s = timeit(lattice, repeats=repeats, warmup=1)
    pts = lattice()
    sdf_s = timeit(lambda: fn(pts), repeats=repeats, warmup=1)
    vol = fn(pts).reshape(res + 1, res + 1, res + 1).numpy()
    h = 2.0 / res
    if flavour == "skimage":
        def extract():
            verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=(h, h, h))
            return verts, faces
    else:  # trimesh meshes the binary occupancy (True = inside) at level 0.5
        from trimesh.voxel.ops import matrix_to_marching_cubes

        def extract():
            m = matrix_to_marching_cubes(vol < 0, pitch=h)
            return m.vertices, m.faces

    secs = timeit(extract, repeats=repeats, warmup=1)
    verts, faces = extract()
    mv = torch.from_numpy(verts.copy()).double() - 1.0
    mf = torch.from_numpy(faces.astype("int64"))
    return _errors(fn, mv, mf, {"samples": (res + 1) ** 3, "tets": 0, "grid_s": grid_s, "sdf_s": sdf_s,
                                "time_s": secs})


def _median_min(fn, repeats: int) -> dict:
    """Median and minimum wall-clock seconds after one warm-up (the minimum is the least load-sensitive)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return {"time_s": times[len(times) // 2], "min_s": times[0]}


def breakdown(res: int, repeats: int) -> list[dict]:
    """The extraction target (<= 0.3 s) timed stage by stage: Kuhn grid at ``res``, off-centre sphere SDF."""
    from geometry.tets import grid_topology

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        grid_topology("kuhn", res, cache_dir=tmp)  # build from scratch + write the cache entry
        rows.append({"stage": f"grid build + cache write (kuhn {res}, once)", "time_s": time.perf_counter() - t0})
        rows.append({"stage": "grid from disk cache (tet_grid)",
                     **_median_min(lambda: tet_grid("kuhn", res, cache_dir=tmp), repeats)})
        v, t = tet_grid("kuhn", res, cache_dir=tmp)
    rows.append({"stage": f"SDF evaluation ({v.shape[0]} vertices)", **_median_min(lambda: sphere(v), repeats)})
    s = sphere(v)
    rows.append({"stage": f"marching_tets ({t.shape[0]} tets) [target <= 0.3 s]",
                 **_median_min(lambda: marching_tets(v, t, s), max(repeats, 9))})
    vg, sg = v.clone().requires_grad_(True), s.clone().requires_grad_(True)

    def fwd_bwd():
        mv, _, _ = marching_tets(vg, t, sg)
        mv.sum().backward()

    rows.append({"stage": "marching_tets + backward (grad w.r.t. verts and sdf)", **_median_min(fwd_bwd, repeats)})
    return rows


def main(argv=None) -> int:
    ap = CliParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=count("--res", 4), nargs="+", default=[16, 32, 64, 128])
    ap.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=list(SHAPES))
    ap.add_argument("--repeats", type=count("--repeats", 1), default=3)
    ap.add_argument("--threads", type=count("--threads", 0), default=0, help="torch threads (0: leave the default)")
    ap.add_argument("--breakdown-only", action="store_true", help="only the Kuhn target timing at max(--res)")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    print(machine_info())
    print("load average (1, 5, 15 min): %.2f %.2f %.2f" % os.getloadavg())
    mc_note = None if have_skimage() else "marching cubes: skipped: scikit-image not installed (pip install '.[bench]')"
    if mc_note:
        print(mc_note)
    rows, series = [], {}
    methods = [("kuhn", False), ("bcc", False), ("kuhn+subdiv", True), ("mc-skimage", False), ("mc-trimesh", False)]
    for shape in [] if a.breakdown_only else a.shapes:
        fn = SHAPES[shape]
        for name, subdiv in methods:
            prev = None
            for res in a.res:
                if name.startswith("mc-"):
                    r = run_mc(fn, res, a.repeats, name[3:])
                    if r is None:
                        break
                else:
                    r = run_case(fn, name.split("+")[0], res, a.repeats, subdiv)
                meshed = 2 * (res // 2) if subdiv else res  # the lattice the row's mesh came from
                cell = 2.0 / meshed
                order = (math.log(prev[1] / r["face_err_mean"]) / math.log(meshed / prev[0])
                         if prev and meshed != prev[0] else None)
                prev = (meshed, r["face_err_mean"])
                row = {"shape": shape, "method": name, "res": meshed, **r, "face_err/cell": r["face_err_mean"] / cell,
                       "order": order}
                rows.append(row)
                print(f"  {shape} {name} res {meshed}: {r['time_s']:.4f} s, face error {r['face_err_mean']:.3g}", flush=True)
                xs, ys = series.setdefault(shape, {}).setdefault(name, ([], []))
                xs.append(r["time_s"])
                ys.append(r["face_err_mean"])
    if rows:
        cols = ["shape", "method", "res", "samples", "tets", "faces", "grid_s", "sdf_s", "time_s", "vert_err_max",
                "face_err_mean", "face_err/cell", "order"]
        print()
        print(format_table(rows, cols))
        if mc_note:
            print(mc_note)
        for shape, by_method in series.items():  # one plot per shape: 5 methods, distinct colours
            path = save_plot(OUT_DIR / f"dmtet_{shape}.png", by_method, xlabel="extraction time (s)",
                             ylabel="mean face-centroid error", logx=True, logy=True,
                             title=f"{shape}: extraction time vs surface error, res {min(a.res)}-{max(a.res)}")
            print(f"plot: {path}")
    res = max(a.res)
    print(f"\nextraction at {res} (Kuhn, off-centre sphere), stage by stage; load average now "
          "%.2f %.2f %.2f" % os.getloadavg())
    bd = breakdown(res, a.repeats)
    print(format_table(bd, ["stage", "time_s", "min_s"]))
    if res == 128:
        t = bd[3]["time_s"]
        print(f"target marching_tets at 128 <= 0.3 s: {'met' if t <= 0.3 else 'NOT met'} (median {t:.3f} s); "
              "load average after: %.2f %.2f %.2f" % os.getloadavg())
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
