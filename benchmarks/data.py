"""Synthetic data generation throughput (images/s) at 128² and 512², with the labels' consistency error.

Target: 8 subjects × 10 frames × 18 cameras at 128² in under 60 s on a 2-core CPU.

    .venv/bin/python benchmarks/data.py                  # 8×10 at 128², 2×10 at 512²
    .venv/bin/python benchmarks/data.py --subjects 2     # quicker

Columns: time split into subject meshing, rendering + labels (GL), HDF5 writing; images/s overall; file size;
and, as the error column, the largest landmark reprojection error (stored 3D landmarks through the stored K
and extrinsics against the stored 2D landmarks, pixels: a consistency check of the stored labels, not of the
images). Mask/silhouette and iris/gaze errors against the images are tested
in tests/train/data/test_synthetic.py.

Part 2, streaming training batches: the Gaussian stage's reader (``train.training.trainer.open_split``) drawing
batches as its steps do (the loop's step generators, the next step's rows read ahead) from a 512² split at 1x,
4x and 16x its rows -- one generated subject file, symlinked as many times as the scale asks (files × 18 rows
each) -- each reader and scale in a fresh subprocess, which reports its rows/s and its peak resident memory
(``ru_maxrss``). Readers: the rows with their default cache, the rows with no cache (what reading costs), and
the whole split in memory (``load_split``, the stages' loader before; up to ``--memory-max-scale``).
Targets: peak RSS grows at most 10 % from 1x to 16x; 512² rows stream at >= 100 rows/s on 2 cores.

    .venv/bin/python benchmarks/data.py --skip-generation      # part 2 alone (~2 min on 2 cores)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import OUT_DIR, count, format_table, machine_info, save_plot  # noqa: E402
from toolkit.cameras import eth_xgaze_rig  # noqa: E402
from toolkit.errors import CliParser, ToolkitError, run_cli  # noqa: E402
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


STREAM_SCALES = (1, 4, 16)
STREAM_READERS = {"rows, default cache": "rows", "rows, no cache": "rows-nocache", "in memory (before)": "memory"}


def stream_child(folder: Path, reader: str, res: int, draws: int, batch: int, workers: int) -> dict:
    """In a fresh process: open the split of ``folder`` with ``reader`` and draw ``draws`` rows as the Gaussian
    stage's steps do; rows/s, peak RSS (MiB), the seconds opening took and the cache's hits."""
    from train.training.trainer import drawn_rows, load_split, open_split

    files = sorted(folder.glob("*.h5"))
    t0 = time.perf_counter()
    if reader == "memory":
        data = load_split(files, "all", res)
    else:
        data = open_split(files, "all", res, cache_bytes=0 if reader == "rows-nocache" else None, workers=workers)
    t_open = time.perf_counter() - t0
    steps = max(1, draws // batch)
    for s in range(steps + 1):  # step 0 a warm-up (torch's first indexing, the reading threads' start)
        if s == 1:
            t0 = time.perf_counter()
        data.take(drawn_rows(len(data), batch, 0, s), "cpu")
        if hasattr(data, "prefetch"):  # as the trainer does: the next step's rows read while this one computes
            data.prefetch(drawn_rows(len(data), batch, 0, s + 1))
    dt = time.perf_counter() - t0
    src = getattr(data, "source", None)
    out = {"rows": len(data), "open s": t_open, "rows/s": steps * batch / dt,
           "peak RSS MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "hits %": 100 * src.hits / max(1, src.hits + src.reads) if src is not None else None,
           "cached MiB": src.cached_bytes / 2**20 if src is not None else None}
    if src is not None:
        data.close()
    return out


def _stream_split(tmp: Path, res: int, frames: int, files: int) -> dict[int, Path]:
    """{scale: folder} of ``files`` × scale symlinks to one generated subject file (``frames`` × 18 rows)."""
    params = SubjectParams.sample(2000)
    rows, subj, attrs = generate_subject(params, n_frames=frames, res=res, seed=1, subject=build_subject(params))
    src = write_subject_h5(tmp / "source" / "subject.h5", rows, subject=subj, attrs=attrs)
    out = {}
    for scale in STREAM_SCALES:
        d = out[scale] = tmp / f"x{scale}"
        d.mkdir()
        for k in range(files * scale):
            (d / f"subject{k:04d}.h5").symlink_to(src)
    return out


def streaming(a) -> list[dict]:
    """Part 2's rows: each reader at each scale, measured by :func:`stream_child` in a fresh subprocess."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folders = _stream_split(Path(tmp), a.stream_res, a.stream_frames, a.stream_files)
        for name, reader in STREAM_READERS.items():
            for scale, folder in folders.items():
                if reader == "memory" and scale > a.memory_max_scale:
                    continue
                cmd = [sys.executable, str(Path(__file__).resolve()), "--stream-child", str(folder), "--reader",
                       reader, "--stream-res", str(a.stream_res), "--stream-draws", str(a.stream_draws),
                       "--stream-batch", str(a.stream_batch), "--stream-workers", str(a.stream_workers)]
                # Through a shell that forks it: Linux carries a process's peak RSS across exec, so a child started
                # straight from this process (torch imported, a subject generated) would report this one's peak.
                done = subprocess.run(["/bin/sh", "-c", '"$@"; rc=$?; exit $rc', "sh", *cmd], capture_output=True,
                                      text=True, check=False)
                if done.returncode != 0:
                    tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
                    raise ToolkitError(f"streaming {name} at {scale}x failed: {tail}")
                rows.append({"reader": name, "scale": f"{scale}x", **json.loads(done.stdout.splitlines()[-1])})
                print(format_table(rows[-1:]), flush=True)
    for r in rows:
        base = next(b for b in rows if b["reader"] == r["reader"] and b["scale"] == "1x")
        r["RSS vs 1x %"] = 100 * (r["peak RSS MiB"] / base["peak RSS MiB"] - 1)
    return rows


def stream_verdicts(rows: list[dict], res: int) -> list[str]:
    lines = []
    for name in ("rows, default cache", "rows, no cache"):
        top = next(r for r in rows if r["reader"] == name and r["scale"] == f"{STREAM_SCALES[-1]}x")
        ok = top["RSS vs 1x %"] <= 10
        lines.append(f"target: peak RSS grows <= 10 % from 1x to {STREAM_SCALES[-1]}x ({name}) -> "
                     f"{top['RSS vs 1x %']:+.1f} % ({'meets' if ok else 'MISSES'} the target)")
    cold = min(r["rows/s"] for r in rows if r["reader"] == "rows, no cache")
    lines.append(f"target: {res}² rows stream at >= 100 rows/s (no cache, slowest scale) -> {cold:.0f} rows/s "
                 f"({'meets' if cold >= 100 else 'MISSES'} the target)")
    return lines


def _args(argv):
    ap = CliParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subjects", type=count("--subjects", 1), default=8, help="subjects at 128² (512² uses a quarter)")
    ap.add_argument("--frames", type=count("--frames", 1), default=10)
    ap.add_argument("--skip-generation", action="store_true", help="part 1 (generation throughput) not run")
    ap.add_argument("--skip-streaming", action="store_true", help="part 2 (streaming training batches) not run")
    ap.add_argument("--stream-res", type=count("--stream-res", 8), default=512)
    ap.add_argument("--stream-frames", type=count("--stream-frames", 1), default=1, help="frames of the subject file")
    ap.add_argument("--stream-files", type=count("--stream-files", 1), default=6, help="subject files at 1x")
    ap.add_argument("--stream-draws", type=count("--stream-draws", 1), default=512,
                    help="rows drawn per measurement (enough to fill the default cache at 1x)")
    ap.add_argument("--stream-batch", type=count("--stream-batch", 1), default=4, help="rows a step draws (paper: 4)")
    ap.add_argument("--stream-workers", type=count("--stream-workers", 0), default=2, help="reading threads")
    ap.add_argument("--memory-max-scale", type=count("--memory-max-scale", 1), default=4,
                    help="largest scale the whole-split reader loads (16x at 512²: ~9 GB)")
    ap.add_argument("--stream-child", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--reader", default="rows", choices=sorted(set(STREAM_READERS.values())), help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def main(argv=None) -> None:
    a = _args(argv)
    if a.stream_child is not None:
        print(json.dumps(stream_child(a.stream_child, a.reader, a.stream_res, a.stream_draws, a.stream_batch,
                                      a.stream_workers)))
        return
    print(machine_info())
    print(f"load average: {os.getloadavg()}")
    if not a.skip_generation:
        generation(a)
    if not a.skip_streaming:
        rows = streaming(a)
        print(f"\nStreaming training batches of {a.stream_batch} rows at {a.stream_res}² ({a.stream_draws} rows drawn "
              f"per measurement, {a.stream_workers} reading threads, one fresh process each):")
        print(format_table(rows, ["reader", "scale", "rows", "open s", "rows/s", "hits %", "cached MiB",
                                  "peak RSS MiB", "RSS vs 1x %"]))
        for line in stream_verdicts(rows, a.stream_res):
            print(line)
        series = {name: ([r["rows"] for r in rows if r["reader"] == name],
                         [r["peak RSS MiB"] for r in rows if r["reader"] == name]) for name in STREAM_READERS}
        png = save_plot(OUT_DIR / "data_streaming.png", series, xlabel="training rows in the split",
                        ylabel="peak RSS (MiB)", title=f"streaming {a.stream_res}² training batches "
                        f"({machine_info()[:60]})", logx=True, logy=True)
        print(f"plot: {png}")


def generation(a) -> None:
    """Part 1: generation throughput at 128² and 512²."""
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
