"""Synthetic data generation throughput (images/s) at 128² and 512², with the labels' consistency error.

Target: 8 subjects × 10 frames × 18 cameras at 128² in under 60 s on a 2-core CPU.

    .venv/bin/python benchmarks/data.py                  # 8×10 at 128², 2×10 at 512²
    .venv/bin/python benchmarks/data.py --subjects 2     # quicker

Columns: time split into subject meshing, rendering + labels (GL), HDF5 writing; images/s overall; file size;
and, as the error column, the largest landmark reprojection error (stored 3D landmarks through the stored K
and extrinsics against the stored 2D landmarks, pixels: a consistency check of the stored labels, not of the
images). Mask/silhouette and iris/gaze errors against the images are tested
in tests/train/data/test_synthetic.py.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import OUT_DIR, count, format_table, machine_info, save_plot  # noqa: E402
from toolkit.cameras import eth_xgaze_rig  # noqa: E402
from toolkit.errors import run_cli  # noqa: E402
from train.data.format import write_subject_h5  # noqa: E402
from train.data.generate import RIG_RADIUS, generate_subject  # noqa: E402
from train.data.subject_params import SubjectParams  # noqa: E402
from train.data.synthetic import build_subject  # noqa: E402


def reprojection_error(path: Path) -> float:
    with h5py.File(path, "r") as f:
        R, T, K = f["w2c_Rmat"][()], f["w2c_Tvec"][()], f["inmat"][()]
        p3, p2 = f["facial_landmarks_3d"][()], f["facial_landmarks"][()]
    pc = np.einsum("nij,nkj->nki", R, p3) + T[:, None]
    uv = np.einsum("nij,nkj->nki", K, pc)
    return float(np.abs(uv[..., :2] / uv[..., 2:] - p2).max())


def run(res: int, n_subjects: int, n_frames: int, out: Path) -> dict:
    rig = eth_xgaze_rig(radius=RIG_RADIUS)
    t_build = t_render = t_write = 0.0
    n_images, err = 0, 0.0
    # One throw-away subject first: the first build and render pay one-time costs (caches, the GL context)
    # that would otherwise skew a short run's throughput.
    warm = SubjectParams.sample(999)
    generate_subject(warm, n_frames=1, res=res, rig=rig, subject=build_subject(warm))
    t0 = time.perf_counter()
    for s in range(n_subjects):
        params = SubjectParams.sample(1000 + s)
        t = time.perf_counter()
        subject = build_subject(params)
        t_build += time.perf_counter() - t
        t = time.perf_counter()
        rows, subj, attrs = generate_subject(params, n_frames=n_frames, res=res, rig=rig, subject=subject)
        t_render += time.perf_counter() - t
        t = time.perf_counter()
        path = write_subject_h5(out / f"subject{s:04d}.h5", rows, subject=subj, attrs=attrs)
        t_write += time.perf_counter() - t
        n_images += len(rows["face_patch"])
        err = max(err, reprojection_error(path))
    total = time.perf_counter() - t0
    return {"res": f"{res}²", "subjects × frames × cams": f"{n_subjects} × {n_frames} × {len(rig)}",
            "images": n_images, "mesh s": t_build, "render+labels s": t_render, "write s": t_write,
            "total s": total, "images/s": n_images / total, "MB/subject": sum(
                p.stat().st_size for p in out.glob("*.h5")) / n_subjects / 1e6, "landmark reproj err px": err}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subjects", type=count("--subjects", 1), default=8, help="subjects at 128² (512² uses a quarter)")
    ap.add_argument("--frames", type=count("--frames", 1), default=10)
    a = ap.parse_args(argv)
    print(machine_info())
    import os

    print(f"load average: {os.getloadavg()}")
    rows = []
    for res, n_sub in ((128, a.subjects), (512, max(1, a.subjects // 4))):
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(run(res, n_sub, a.frames, Path(tmp)))
        print(format_table(rows[-1:]), flush=True)
    print()
    print(format_table(rows))
    r128 = rows[0]
    if r128["images"] == 8 * 10 * 18:
        verdict = "meets" if r128["total s"] < 60 else "MISSES"
        print(f"target: 8 × 10 × 18 at 128² in < 60 s -> {r128['total s']:.1f} s ({verdict} the target)")
    else:
        est = 1440 / r128["images/s"]
        print(f"target: 8 × 10 × 18 at 128² in < 60 s -> estimated {est:.1f} s from {r128['images']} images")
    png = save_plot(OUT_DIR / "data.png", {"generation": ([128, 512], [r["images/s"] for r in rows])},
                    xlabel="face-patch resolution (px)", ylabel="images / s", title="synthetic data generation "
                    f"({machine_info()[:60]})", logy=True)
    print(f"plot: {png}")


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
