"""Write a gaze-redirected copy of a dataset: the job users come for (augmented data for gaze estimators).

    python -m apps.redirect RUN_DIR DATASET OUT.h5 [--gazes grid:5x5:30 | random:200:35 | file:gazes.csv]
                            [--rows N] [--batch 8] [--seed 0]
    python -m apps.redirect RUN_DIR crops/labels.csv OUT.h5 [--focal F] [--distance D] [--fit-steps N]
    python -m apps.redirect RUN_DIR DATASET OUT.h5 --fit-weights [--fit-steps N]   # new faces: fit each row first
    python -m apps.redirect RUN_DIR DATASET OUT.h5 --fit-weights --natural-eyes    # ... turning, not repainting, the eyes
    python -m apps.redirect RUN_DIR photo.jpg [more.jpg photos/] OUT_DIR [--paste-back] [--largest-face]  # photos

For every input row and every target gaze (head frame, degrees in the spec), the trained model renders the
same person looking there. The output is one HDF5 file in the schema of docs/data.md, with the target gaze
as the label (``pitchyaw_head``, and ``pitchyaw_cam`` in the camera frame) plus ``source_row`` (the input
row) and the file attribute ``source_file``.

Inputs:

- an HDF5 subject file (docs/data.md): camera, head pose and codes come from the file;
- a folder of normalized face crops (ETH-XGaze style) with a labels CSV, one row per image. Columns
  (details in ``apps/labels_table.py``, frames in ``apps/labels_csv.py``, docs/redirect.md): ``image`` (path
  relative to the CSV), ``head_pitch``, ``head_yaw`` (degrees, the face direction in the normalized camera) are
  required;
  ``head_roll``, ``gaze_pitch``/``gaze_yaw`` (the image's own gaze, camera frame, degrees), ``focal``
  (pixels), ``distance`` (metres), ``mask`` (head mask image) and ``code`` (``.npy`` of the model's shape code)
  are optional. Rows without a code get one by test-time fitting on the image (``--fit-steps``; needs the
  gaze columns). The whole CSV and every file it names are checked before any rendering; each problem is
  one error naming the line and column. Output landmarks, mesh and eye masks of CSV rows come from the
  run's geometry and the model's splatted silhouettes (approximate: the crops carry none);
- photos (photo files and/or folders of them, several allowed): prepared on the fly as ``apps.prepare``
  does, fitted as ``--fit-weights`` fits (always), and written to an output folder with a grid per face and,
  with ``--paste-back``, each redirected face pasted back into its photo (``apps/redirect_photo.py``).

``--fit-weights`` fits every row as the evaluation fits a pair before rendering it
(``train.trained_run.TrainedRun.row_fitter``): what a face the run never trained on needs (docs/redirect.md).
``--natural-eyes`` fits other weights with a gaze term that may only turn the eyes
(``train.presets.NATURAL_EYES_FIT``).

Resumable: work is done in chunks written atomically to ``OUT.parts/``; a rerun skips finished chunks,
and the final file is assembled (atomically) when all chunks exist, each checked as it is read (a damaged
one is refused by name, ``redirect_parts.read_chunk``). ``OUT.parts/settings.json`` records the
settings the chunks were made with; a rerun with other settings is refused rather than mixed in.
Shardable: under ``torchrun`` each process renders the chunks ``k ≡ rank (mod world)`` and rank 0 assembles.
Each chunk draws its random numbers (a diffusion renderer's noise while fitting) from its own stream, seeded
by ``--seed`` and the chunk's number, so a resumed or sharded run writes what an uninterrupted one does.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from apps.labels_table import is_labels_csv
from apps.redirect_parts import (
    assemble,
    check_out_of_run,
    check_parts_settings,
    chunk_path,
    redirect_settings,
    sampling_steps,
)
from apps.redirect_render import OUTPUT_KEYS, render_chunk
from toolkit.errors import CliParser, ToolkitError, run_cli
from toolkit.host import keep_freed_memory
from toolkit.io import check_not_an_input
from toolkit.limits import check_allocation, check_count

GRID_EXAMPLE = "grid:5x5:30 (pitch rows × yaw columns over ±30°), random:200:35 (200 gazes uniform in ±35°), file:gazes.csv"


MAX_GAZES = 100_000
"""Target gazes per input row (``--gazes``): more is a typo, not a dataset (each row is rendered at every one)."""
MAX_FIT_STEPS = 20_000
"""Test-time fitting steps per row (``--fit-steps``): runs fit in tens to hundreds; more would run for days."""
MAX_BATCH = 4096
"""Input rows per chunk (``--batch``)."""


def _spec_range(spec: str, deg: str) -> float:
    """The ± range of a grid or random spec, degrees -> radians: finite and below 90°."""
    r = float(deg)  # a ValueError names the spec's expected form (parse_gazes)
    if not (math.isfinite(r) and 0 <= r < 90):
        raise ToolkitError(f"--gazes {spec!r}: expected a range in [0, 90) degrees, got {deg}")
    return math.radians(r)


def parse_gazes(spec: str, seed: int = 0) -> np.ndarray:
    """A gaze spec -> [G, 2] (pitch, yaw) radians, head frame."""
    kind, _, rest = spec.partition(":")
    try:
        if kind == "grid":
            dims, rng = rest.split(":")
            ny, nx = (int(v) for v in dims.lower().split("x"))
            if ny < 1 or nx < 1:
                raise ToolkitError(f"--gazes {spec!r}: a grid needs at least 1 row and 1 column, got {ny}x{nx}")
            r = _spec_range(spec, rng)
            if ny * nx > MAX_GAZES:
                raise ToolkitError(f"--gazes {spec!r}: {ny * nx} gazes; at most {MAX_GAZES} per input row")
            p = np.linspace(-r, r, ny) if ny > 1 else np.zeros(1)
            y = np.linspace(-r, r, nx) if nx > 1 else np.zeros(1)
            out = np.stack(np.meshgrid(p, y, indexing="ij"), -1).reshape(-1, 2)
        elif kind == "random":
            n, rng = rest.split(":")
            n, r = int(n), _spec_range(spec, rng)
            if not 1 <= n <= MAX_GAZES:
                raise ToolkitError(f"--gazes {spec!r}: expected 1..{MAX_GAZES} random gazes per input row, got {n}")
            out = np.random.default_rng(seed).uniform(-r, r, size=(n, 2))
        elif kind == "file":
            path = Path(rest)
            if not path.is_file():
                raise ToolkitError(f"--gazes file {path}: no such file")
            if path.stat().st_size > MAX_GAZES * 64:  # a 'pitch,yaw' line is far shorter than 64 bytes
                raise ToolkitError(f"--gazes file {path}: {path.stat().st_size} bytes; expected at most {MAX_GAZES} "
                                   f"lines of 'pitch,yaw' (at most {MAX_GAZES * 64} bytes)")
            try:
                with warnings.catch_warnings():  # numpy warns of an empty file; the check below says it in one line
                    warnings.simplefilter("ignore", UserWarning)
                    vals = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
            except ValueError as e:  # a header line, a stray word: numpy says which line
                raise ToolkitError(f"--gazes file {path}: expected lines of 'pitch,yaw' in degrees (# starts a "
                                   f"comment): {e}") from None
            if vals.size == 0:
                raise ToolkitError(f"--gazes file {path}: no gazes in the file (expected lines of 'pitch,yaw' in degrees)")
            if vals.shape[1] != 2:
                raise ToolkitError(f"--gazes file {path}: expected two columns (pitch, yaw in degrees), got {vals.shape[1]}")
            if len(vals) > MAX_GAZES:
                raise ToolkitError(f"--gazes file {path}: {len(vals)} gazes; at most {MAX_GAZES} per input row")
            out = np.radians(vals)
        else:
            raise ValueError
    except ToolkitError:
        raise
    except (ValueError, IndexError):
        raise ToolkitError(f"--gazes {spec!r}: expected {GRID_EXAMPLE}") from None
    if out.size == 0 or not np.isfinite(out).all() or (np.abs(out) >= math.pi / 2).any():
        raise ToolkitError(f"--gazes {spec!r}: gazes must be finite and within ±90°")
    return out.astype(np.float32)



def open_source(run, args):
    """The input rows: a ``GazeDataset`` over an HDF5 file, or a validated ``LabelsCsvSource`` (``run``: the
    ``TrainedRun``, whose geometry places the CSV rows' landmarks and mesh)."""
    cfg = run.config
    if not is_labels_csv(args.dataset):
        from train.data.dataset import GazeDataset

        ds = GazeDataset([args.dataset], res=cfg.data.res, with_mesh=True)
        return ds
    from apps.labels_csv import LabelsCsvSource
    from geometry.mesh_files import load_mesh
    from toolkit.scene import GaussianScene
    from train.data.generate import NORM_CROP, NORM_DISTANCE

    scene_path = run.context.path("geometry", "scene")
    landmarks = GaussianScene.load(scene_path).metadata.get("landmarks")
    if landmarks is None:
        raise ToolkitError(f"{scene_path}: no landmarks in its metadata (re-run stage geometry)")
    verts, _ = load_mesh(run.context.path("geometry", "mesh"))
    return LabelsCsvSource(args.dataset, cfg.data.res, torch.tensor(landmarks, dtype=torch.float32), verts,
                           focal=args.focal, distance=args.distance, default_distance=NORM_DISTANCE,
                           default_crop=NORM_CROP, code_widths=run.code_widths())


def build_parser() -> argparse.ArgumentParser:
    ap = CliParser(prog="python -m apps.redirect", description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", help="a trained run directory (train/run.py)")
    ap.add_argument("dataset", nargs="+", metavar="INPUT",
                    help="an HDF5 subject file (docs/data.md), a labels CSV of face crops (or the folder holding "
                         "labels.csv; columns in docs/redirect.md), or photos: photo files (JPEG, PNG, WebP, TIFF, "
                         "HEIC, ...) and/or folders of them")
    ap.add_argument("out", help="output HDF5 file; for photo input an output folder")
    ap.add_argument("--gazes", default="grid:3x3:25", help=f"target gazes: {GRID_EXAMPLE} (default: %(default)s)")
    ap.add_argument("--rows", type=int, default=0, help="use only the first N input rows (0 = all; default: %(default)s)")
    ap.add_argument("--batch", type=int, default=4, help="input rows per chunk (default: %(default)s)")
    ap.add_argument("--steps", type=int, default=0, help="DDIM steps (0 = the run's evaluation setting: eval.sampling_steps, else gaussian.sampling_steps)")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of random: gazes and of the fitting's diffusion noise (drawn per chunk, so a "
                         "resumed or sharded run writes what an uninterrupted one does)")
    ap.add_argument("--focal", type=float, default=None,
                    help="CSV input: focal length (pixels of the images) for rows without one (default: the "
                         "project's normalized camera, size x 0.6 / 0.26); photos: their focal length in pixels "
                         "(default as apps.prepare: EXIF, else 1.2 x the longer side)")
    ap.add_argument("--distance", type=float, default=None,
                    help="CSV input: camera-to-face distance (metres) for rows without one (default 0.6)")
    ap.add_argument("--fit-steps", type=int, default=-1,
                    help="test-time fitting steps: of the shape code on CSV rows without a code, and of each row "
                         "with --fit-weights (default: the run's eval.tta_steps, or 50 when that is 0)")
    ap.add_argument("--fit-lr", type=float, default=1e-2, help="CSV input: learning rate of the code fitting (default: %(default)s)")
    ap.add_argument("--fit-weights", action="store_true",
                    help="fit each input row as the run's evaluation does before rendering its gazes: the code and "
                         "eval.tta_weights (by default face features, renderer) for --fit-steps steps on eval.tta_region, with "
                         "the loss estimator's gaze term at the row's target gazes; one row at a time, from the "
                         "trained weights each time (CSV rows need their own gaze)")
    ap.add_argument("--natural-eyes", action="store_true",
                    help="with --fit-weights: fit the face features, eye rotation field and renderer, with a gaze "
                         "term that may only turn the eyes (train.presets.NATURAL_EYES_FIT): no coloured specks "
                         "in the eyes (the demo preset's own fit; docs/redirect.md)")
    ap.add_argument("--largest-face", action="store_true", help="photo input: only the largest face of each photo")
    ap.add_argument("--paste-back", action="store_true",
                    help="photo input: also write each face at each gaze pasted back into its photo, at the photo's "
                         "resolution (OUT/<photo>_face<k>_<pitch>_<yaw>.png)")
    return ap


def check_args(args: argparse.Namespace) -> None:
    """The flags' own checks, before the run or the input is opened (each a one-line ToolkitError)."""
    if args.natural_eyes and not args.fit_weights:  # photo input is always fitted (resolve_inputs)
        raise ToolkitError("--natural-eyes sets how --fit-weights fits each row; give --fit-weights too")
    check_count(args.batch, "--batch", 1, MAX_BATCH, "input rows per chunk")
    check_count(args.rows, "--rows", 0, 10**9, "a row count (0 = all rows)")
    check_count(args.steps, "--steps", 0, 100_000, "DDIM steps (0 = the run's setting)")
    if args.fit_steps != -1:
        check_count(args.fit_steps, "--fit-steps", 0, MAX_FIT_STEPS, "test-time fitting steps per row")
    if not (math.isfinite(args.fit_lr) and 0 < args.fit_lr <= 1):
        raise ToolkitError(f"--fit-lr must be in (0, 1], got {args.fit_lr}")
    if not 0 <= args.seed < 2**32:  # each chunk's stream is seeded from it (and numpy takes it for random: gazes)
        raise ToolkitError(f"--seed must be in [0, 2^32), got {args.seed}")
    if args.photos:
        from apps.redirect_photo import check_photo_out

        check_photo_out(args)
        return
    from toolkit.images import is_picture

    if is_picture(args.dataset):  # named as a dataset (.h5), so not read as a photo: the name is the mistake
        raise ToolkitError(f"dataset {args.dataset}: a picture by its content, named as an HDF5 dataset; give it its "
                           "image suffix (.jpg, .png) to redirect it as a photo")
    if Path(args.out).suffix.lower() not in (".h5", ".hdf5"):
        raise ToolkitError(f"out {args.out}: expected an HDF5 file name ending in .h5 or .hdf5")
    if Path(args.out).is_dir():  # before any rendering: the file is only written once every chunk is done
        raise ToolkitError(f"out {args.out}: is a directory, expected the path of the HDF5 file to write")
    data = Path(args.dataset)
    read = [data, *(sorted(data.glob("*.h5")) + sorted(data.glob("*.hdf5")) if data.is_dir() else [])]
    check_not_an_input(args.out, [*read, args.run_dir], "out", "dataset")
    if (Path(args.run_dir) / "config.yaml").is_file():  # else TrainedRun.open says it is not a run directory
        check_out_of_run(args.out, args.run_dir)


def check_sizes(n_rows: int, n_gazes: int, res: int, args: argparse.Namespace) -> None:
    """Refuse, before any work, a job whose memory would not fit (``toolkit.limits.check_allocation``): one row's
    diffusion noise for all its gazes at once (at most 4 float32 channels per pixel), a chunk's images, and the
    output file, built in memory (RGB and three masks, a byte each, per pixel)."""
    px = res * res
    check_allocation(n_gazes * px * 16, f"--gazes {args.gazes!r} ({n_gazes} gazes of {res}x{res} pixels per row)",
                     "ask for fewer gazes")
    check_allocation(args.batch * n_gazes * px * 6, f"--batch {args.batch} x {n_gazes} gazes",
                     "lower --batch or ask for fewer gazes")
    check_allocation(n_rows * n_gazes * px * 6, f"the output {args.out} ({n_rows} rows x {n_gazes} gazes)",
                     "ask for fewer gazes or --rows, or split the input")


def fit_steps_for(args: argparse.Namespace, cfg, src) -> int:
    """The test-time fitting steps (``--fit-steps``, else the run's ``eval.tta_steps`` or 50), checked against
    ``--fit-weights``, which needs >= 1 step and every CSV row's own gaze; ``--fit-steps`` given for HDF5 rows
    without ``--fit-weights`` (nothing to fit) is refused rather than ignored."""
    fit_steps = args.fit_steps if args.fit_steps >= 0 else (cfg.eval.tta_steps or 50)
    if args.fit_steps >= 0 and not args.fit_weights and src is not None and not hasattr(src, "items"):
        raise ToolkitError("--fit-steps sets how long --fit-weights fits each row (and the code fit of CSV rows "
                           "without a code); HDF5 rows are rendered from their stored codes: give --fit-weights too")
    if args.fit_weights:
        if fit_steps < 1:
            what = "photo input (fitted before it is rendered)" if getattr(args, "photos", None) else "--fit-weights"
            raise ToolkitError(f"{what} needs --fit-steps >= 1, got {fit_steps}")
        missing = [r.line for r in getattr(src, "rows", []) if r.gaze is None]
        if missing:
            raise ToolkitError(f"{src.path} line {missing[0]}: --fit-weights fits the image at its own gaze; "
                               f"fill gaze_pitch and gaze_yaw ({len(missing)} rows lack them)")
    return fit_steps


def render_chunks(todo: list[int], mine: list[int], chunks: list[list[int]], items, parts: Path, args, info,
                  render) -> None:
    """Render and write (atomically) the chunks ``todo`` of this process's ``mine``; ``items(rows)`` gives a
    chunk's input items, ``render(items, rows)`` its arrays. A failure on any rank stops every rank (their
    finished chunks kept), raised here."""
    from tqdm import tqdm

    from toolkit.io import atomic_write
    from train.training.distributed import all_ranks

    failure = None
    try:
        for k in tqdm(todo, desc=f"redirect (rank {info.rank})", disable=not info.is_main,
                      initial=len(mine) - len(todo), total=len(mine)):
            # Each chunk's own random stream (a diffusion renderer's noise while fitting): its images then do not
            # depend on which chunks this process rendered before it.
            torch.manual_seed((args.seed * 1_000_003 + k) % 2**63)
            arrays = render(items(chunks[k]), chunks[k])
            with atomic_write(chunk_path(parts, k), "wb") as f:
                np.savez(f, **arrays)
    except Exception as e:  # noqa: BLE001 -- re-raised below, once every rank knows
        failure = e
    # A rank that failed must not leave the others waiting at the barrier (torchrun's agent would kill them;
    # other launchers would not): all learn of it and stop on their own, their finished chunks kept.
    if not all_ranks(failure is None, info):
        if failure is not None:
            raise failure
        raise ToolkitError(f"redirect: another process failed (its error is above); the chunks done are kept in "
                           f"{parts}: rerun the same command to resume")


def redirect_dataset(args: argparse.Namespace, gazes: np.ndarray, run=None, attrs: dict | None = None,
                     photos: dict | None = None, extra_rows: dict | None = None) -> int:
    """Render ``args.dataset``'s rows at ``gazes`` [G, 2] (radians, head frame) into ``args.out``; returns the
    images written. ``run`` an open ``TrainedRun`` (default: ``args.run_dir``'s); ``attrs`` the output file's
    attributes (default: the input's path as ``source_file``); ``photos`` what photo input's rows come from, in
    place of the prepared file's path and stamp in the chunks' settings (``redirect_parts.redirect_settings``);
    ``extra_rows`` per-input-row arrays [N, ...] copied to each output row (``redirect_parts.assemble``)."""
    from train.trained_run import TrainedRun
    from train.training.distributed import barrier, cleanup, init_distributed

    run = run or TrainedRun.open(args.run_dir)
    cfg = run.config
    src = open_source(run, args)  # validates the whole input before any model is loaded
    fit_steps = fit_steps_for(args, cfg, src)
    n_rows = len(src) if args.rows <= 0 else min(args.rows, len(src))
    check_sizes(n_rows, len(gazes), cfg.data.res, args)
    info = init_distributed("cpu" if not torch.cuda.is_available() else "auto")
    device = torch.device(info.device)
    model, renderer = run.load_model(device)
    diffusion = getattr(renderer, "diffusion", None)
    steps = sampling_steps(args, cfg)
    if diffusion is not None and not 1 <= steps <= diffusion.num_timesteps:
        raise ToolkitError(f"--steps must be 0 (the run's setting) or 1..{diffusion.num_timesteps} DDIM steps, "
                           f"got {args.steps}")
    fit = run.row_fitter(model, renderer, device, fit_steps, natural_eyes=args.natural_eyes) if args.fit_weights else None

    def items(rows: list[int]) -> list[dict]:
        if hasattr(src, "items"):
            return src.items(rows, model, renderer, device, fit_steps=fit_steps, fit_lr=args.fit_lr)
        return [src[r] for r in rows]

    chunks = [list(range(i, min(i + args.batch, n_rows))) for i in range(0, n_rows, args.batch)]
    out = Path(args.out)
    parts = out.with_suffix(out.suffix + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    check_parts_settings(parts, redirect_settings(run, src, args, gazes, n_rows, fit_steps, photos))
    mine = [k for k in range(len(chunks)) if k % info.world_size == info.rank]
    todo = [k for k in mine if not chunk_path(parts, k).exists()]
    render_chunks(todo, mine, chunks, items, parts, args, info, lambda its, rows: render_chunk(
        model, renderer, its, rows, gazes, cfg.data.res, steps, device, fit))
    barrier(info)
    n = 0
    if info.is_main:
        n = assemble(parts, len(chunks), out, {"source_file": str(args.dataset), "run_dir": str(Path(args.run_dir)),
                                               "gazes_spec": args.gazes, "generator": "apps.redirect",
                                               **(attrs or {})}, extra_rows,
                     source_rows=[np.repeat(c, len(gazes)) for c in chunks], keys=OUTPUT_KEYS)
        # The settings go last: chunks left by an interrupted clean-up stay tied to what made them.
        for p in sorted(parts.iterdir(), key=lambda p: p.name == "settings.json"):
            p.unlink()
        parts.rmdir()
        print(f"wrote {out}: {n} redirected images ({n_rows} rows × {len(gazes)} gazes)")
    cleanup(info)
    return n


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    keep_freed_memory()
    from apps.redirect_photo import redirect_photos, resolve_inputs

    resolve_inputs(args)  # photo input (args.photos) or one dataset (args.dataset)
    check_args(args)
    gazes = parse_gazes(args.gazes, args.seed)
    if args.photos:
        redirect_photos(args, gazes, redirect_dataset, fit_steps_for)
    else:
        redirect_dataset(args, gazes)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
