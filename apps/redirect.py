"""Write a gaze-redirected copy of a dataset: the job users come for (augmented data for gaze estimators).

    python -m apps.redirect RUN_DIR DATASET OUT.h5 [--gazes grid:5x5:30 | random:200:35 | file:gazes.csv]
                            [--rows N] [--batch 8] [--seed 0]
    python -m apps.redirect RUN_DIR crops/labels.csv OUT.h5 [--focal F] [--distance D] [--fit-steps N]
    python -m apps.redirect RUN_DIR DATASET OUT.h5 --fit-weights [--fit-steps N]   # new faces: fit each row first
    python -m apps.redirect RUN_DIR DATASET OUT.h5 --fit-weights --natural-eyes    # ... turning, not repainting, the eyes

For every input row and every target gaze (head frame, degrees in the spec), the trained model renders the
same person looking there. The output is one HDF5 file in the schema of docs/data.md, with the target gaze
as the label (``pitchyaw_head``, and ``pitchyaw_cam`` in the camera frame) plus ``source_row`` (the input
row) and the file attribute ``source_file``.

Inputs:

- an HDF5 subject file (docs/data.md): camera, head pose and codes come from the file;
- a folder of normalized face crops (ETH-XGaze style) with a labels CSV, one row per image. Columns
  (details and frames in ``apps/labels_csv.py`` and docs/redirect.md): ``image`` (path relative to the CSV),
  ``head_pitch``, ``head_yaw`` (degrees, the face direction in the normalized camera) are required;
  ``head_roll``, ``gaze_pitch``/``gaze_yaw`` (the image's own gaze, camera frame, degrees), ``focal``
  (pixels), ``distance`` (metres), ``mask`` (head mask image) and ``code`` (``.npy`` of the 144-d shape code)
  are optional. Rows without a code get one by test-time fitting on the image (``--fit-steps``; needs the
  gaze columns). The whole CSV and every file it names are checked before any rendering; each problem is
  one error naming the line and column. Output landmarks, mesh and eye masks of CSV rows come from the
  run's geometry and the model's splatted silhouettes (approximate: the crops carry none).

``--fit-weights`` fits every row as the evaluation fits a pair before rendering it (:func:`row_fitter`):
what a face the run never trained on needs (docs/redirect.md). ``--natural-eyes`` fits other weights with a gaze
term that may only turn the eyes (``train.evaluation.fitting.NATURAL_EYES_FIT``, :func:`row_fitter`).

Resumable: work is done in chunks written atomically to ``OUT.parts/``; a rerun skips finished chunks,
and the final file is assembled (atomically) when all chunks exist. ``OUT.parts/settings.json`` records the
settings the chunks were made with; a rerun with other settings is refused rather than mixed in.
Shardable: under ``torchrun`` each process renders the chunks ``k ≡ rank (mod world)`` and rank 0 assembles.
Each chunk draws its random numbers (a diffusion renderer's noise while fitting) from its own stream, seeded
by ``--seed`` and the chunk's number, so a resumed or sharded run writes what an uninterrupted one does.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from toolkit.errors import ToolkitError, run_cli
from toolkit.host import keep_freed_memory
from toolkit.rotations import so3_exp

GRID_EXAMPLE = "grid:5x5:30 (pitch rows × yaw columns over ±30°), random:200:35 (200 gazes uniform in ±35°), file:gazes.csv"


MAX_GAZES = 100_000
"""Target gazes per input row (``--gazes``): more is a typo, not a dataset (each row is rendered at every one)."""


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


def _chunk_path(parts: Path, k: int) -> Path:
    return parts / f"part_{k:05d}.npz"


def row_fitter(ctx, model, renderer, device, steps: int, *, gaze_term: bool = True, natural_eyes: bool = False
               ) -> Callable[[dict, torch.Tensor], torch.Tensor]:
    """The evaluation's test-time fitting of one input row (``train.run.row_fitter``, which the eval stage's
    gaze-sweep figure uses too)."""
    from train.run import row_fitter as fitter

    return fitter(ctx, model, renderer, device, steps, gaze_term=gaze_term, natural_eyes=natural_eyes)


RENDER_BATCH = 32
"""Gazes of one input row rendered in one forward pass: a long gaze list (random:2000:35) is rendered in
slices of this many, so memory does not grow with it."""


def render_gazes(model, renderer, code: torch.Tensor, pose: torch.Tensor, gz: torch.Tensor, V: torch.Tensor,
                 K: torch.Tensor, res: int, steps: int) -> torch.Tensor:
    """One input row at G gazes -> [G, 3, res, res] images, ``RENDER_BATCH`` gazes at a time; ``code``
    [G, C], ``pose`` [G, 6], ``gz`` [G, 2], ``V`` [G, 4, 4], ``K`` [G, 3, 3]. A diffusion renderer's
    starting noise is drawn for all G at once (its ``seed=0`` stream), so the images do not depend on the
    slicing."""
    G, noise, out = gz.shape[0], None, []
    for a in range(0, G, RENDER_BATCH):
        s = slice(a, min(a + RENDER_BATCH, G))
        maps = model(code[s], pose[s], gz[s], V[s], K[s], res, res, renders=("head",))
        if hasattr(renderer, "diffusion"):
            if noise is None:
                shape = renderer.latent_shape(maps["head"])
                noise = torch.randn((G, *shape[1:]), generator=torch.Generator().manual_seed(0))
            out.append(renderer.render(maps["head"], code[s], gaze=gz[s], pose=pose[s], steps=steps, noise=noise[s]))
        else:
            out.append(renderer.render(maps["head"], code[s], gaze=gz[s], pose=pose[s]))
    return torch.cat(out)


def render_chunk(model, renderer, items: list[dict], rows: list[int], gazes: np.ndarray, res: int, steps: int,
                 device, fit: Callable[[dict, torch.Tensor], torch.Tensor] | None = None) -> dict:
    """Render every (row, gaze) pair of the input ``items`` (``GazeDataset`` items or
    ``LabelsCsvSource.items``; ``rows`` their input row numbers) -> arrays of the output schema.

    ``fit`` (:func:`row_fitter`): fit each row before rendering its gazes, from the trained weights each time."""
    from train.evaluation.fitting import restored_weights

    out: dict[str, list] = {k: [] for k in ("face_patch", "head_mask", "pitchyaw_head", "pitchyaw_cam", "pose",
                                            "w2c_Rmat", "w2c_Tvec", "inmat", "latent_codes", "face_head_pose",
                                            "cam_index", "frame_index", "source_row", "left_eye_mask",
                                            "right_eye_mask", "facial_landmarks", "facial_landmarks_3d", "scale",
                                            "vertice")}
    from toolkit.rotations import pitchyaw_to_vector, vector_to_pitchyaw

    G = gazes.shape[0]
    gz = torch.from_numpy(gazes).float().to(device)
    for it, r in zip(items, rows):
        rep = lambda k, it=it: torch.as_tensor(it[k]).float()[None].expand(G, *torch.as_tensor(it[k]).shape).to(device)  # noqa: E731
        code, pose, V, K = rep("latent_code"), rep("pose"), rep("viewmat"), rep("K")
        with restored_weights(model, renderer) if fit is not None else contextlib.nullcontext():
            if fit is not None:
                code = fit(it, gz).expand(G, -1)
                if not torch.isfinite(code).all():
                    raise ToolkitError(f"--fit-weights: the fit of input row {r} diverged (non-finite code); try "
                                       "fewer --fit-steps or a lower eval.tta_renderer_lr")
            with torch.no_grad():
                img = render_gazes(model, renderer, code, pose, gz, V, K, res, steps)
        if not torch.isfinite(img).all():  # NaN would be written as black pixels
            raise ToolkitError(f"input row {r}: the render is not finite (a non-finite code or a diverged fit?)")
        mask = torch.as_tensor(it["head_mask"]).float().to(device)
        img = img * mask + (1 - mask)
        R = V[:, :3, :3] @ so3_exp(pose[:, :3])
        cam_gaze = vector_to_pitchyaw(torch.einsum("bij,bj->bi", R, pitchyaw_to_vector(gz)))
        bgr = (img.clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy()[..., ::-1] * 255).round().astype(np.uint8)
        out["face_patch"].append(bgr)
        out["head_mask"].append(np.repeat((mask[0].cpu().numpy() > 0.5).astype(np.uint8)[None] * 255, G, 0))
        out["pitchyaw_head"].append(gazes)
        out["pitchyaw_cam"].append(cam_gaze.cpu().numpy())
        out["pose"].append(pose.cpu().numpy())
        out["w2c_Rmat"].append(V[:, :3, :3].cpu().numpy())
        out["w2c_Tvec"].append(V[:, :3, 3].cpu().numpy())
        out["inmat"].append(K.cpu().numpy())
        out["latent_codes"].append(code.cpu().numpy())
        out["face_head_pose"].append(np.repeat(np.asarray(it["face_head_pose"], np.float32)[None], G, 0))
        out["cam_index"].append(np.full(G, int(it["cam_index"]), np.int32))  # the schema's int32 (docs/data.md)
        out["frame_index"].append(np.full(G, int(it["frame_index"]), np.int32))  # the schema's int32 (docs/data.md)
        out["source_row"].append(np.full(G, r, np.int64))
        # Gaze does not move the lids, landmarks or mesh of the synthetic subjects: the input's stay valid.
        for key, src in (("left_eye_mask", "left_eye_mask"), ("right_eye_mask", "right_eye_mask")):
            m = (np.asarray(it[src]).reshape(res, res) > 0.5).astype(np.uint8) * 255
            out[key].append(np.repeat(m[None], G, 0))
        for key, src in (("facial_landmarks", "landmarks"), ("facial_landmarks_3d", "landmarks_3d"),
                         ("scale", "scale"), ("vertice", "vertice")):
            a = np.asarray(it[src], np.float32)
            out[key].append(np.repeat(a[None], G, 0))
    return {k: np.concatenate(v) for k, v in out.items()}


def sampling_steps(args, cfg) -> int:
    from train.run_config import eval_sampling_steps

    return args.steps or eval_sampling_steps(cfg)  # the run's evaluation renders with these


SETTINGS_VERSION = 3
"""Of ``OUT.parts/settings.json``: 2 since the fitting's noise is seeded per chunk (version 1 had no field), 3
since the input's contents are stamped (``input_stamp``), not only its path."""


def input_stamp(src, dataset: str | Path) -> str:
    """What the input rows' contents depend on, for a resumed run to notice an input replaced or edited under
    the same path: a CSV source's own stamp (its text, the files it names, the codes), else each HDF5 file's
    size and modification time."""
    import hashlib

    if hasattr(src, "stamp"):
        return src.stamp()
    p = Path(dataset)
    files = sorted(p.glob("*.h5")) if p.is_dir() else [p]  # a folder: the files GazeDataset reads
    from toolkit.io import file_stamp

    return hashlib.sha1(";".join(map(file_stamp, files)).encode()).hexdigest()


def redirect_settings(ctx, src, args, gazes: np.ndarray, n_rows: int, fit_steps: int) -> dict:
    """What the chunks' contents depend on, resolved (the same input or setting spelt another way is the same):
    the run (its trained checkpoint's size and time), the input file, the gazes themselves, the rows, the
    rendering and the fitting (with the run's eval section when rows are weight-fitted); CSV-only settings
    for CSV input only."""
    import hashlib

    ckpt = ctx.path("gaussian", "checkpoint")
    st = ckpt.stat()
    settings = {"version": SETTINGS_VERSION, "run_dir": str(ctx.run_dir.resolve()), "checkpoint": [st.st_size, st.st_mtime_ns],
                "dataset": str(Path(getattr(src, "path", args.dataset)).resolve()),
                "input_stamp": input_stamp(src, args.dataset),
                "gazes_sha1": hashlib.sha1(np.ascontiguousarray(gazes, np.float64).tobytes()).hexdigest(),
                "rows": n_rows, "batch": args.batch, "steps": sampling_steps(args, ctx.config),
                "fit_weights": args.fit_weights, "natural_eyes": args.natural_eyes}
    csv = is_labels_csv(args.dataset)
    if csv:
        settings.update(focal=args.focal, distance=args.distance, fit_lr=args.fit_lr)
    if args.fit_weights or csv:  # fitting draws the diffusion renderer's noise from the seed's streams
        settings.update(fit_steps=fit_steps, seed=args.seed)
    if args.fit_weights:
        as_json = lambda d: {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}  # noqa: E731
        settings["eval"] = as_json({k: v for k, v in vars(ctx.config.eval).items()
                                    if k.startswith("tta_") and k != "tta_steps"})  # the steps: fit_steps
        if args.natural_eyes:  # what the fit then uses in place of the section's weights and gaze term
            from train.evaluation.fitting import NATURAL_EYES_FIT

            settings["natural_eyes_fit"] = as_json(NATURAL_EYES_FIT)
    return settings


def check_parts_settings(parts: Path, settings: dict) -> None:
    """Record ``settings`` in ``parts/settings.json``, or refuse (ToolkitError) when chunks already there were
    made with other settings: a resumed run must not mix, say, fitted and unfitted rows in one file. Settings
    with no chunk yet (a run stopped before its first one) are simply replaced."""
    import json

    from toolkit.io import atomic_write_json

    path = parts / "settings.json"
    if not path.is_file() and any(parts.glob("part_*.npz")):
        raise ToolkitError(f"{parts} holds chunks but no settings.json, so what made them is unknown; delete "
                           f"{parts} to start over")
    if path.is_file() and any(parts.glob("part_*.npz")):
        try:
            before = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise ToolkitError(f"{path}: unreadable ({e}); delete {parts} to start over") from e
        changed = sorted(k for k in set(before) | set(settings) if before.get(k) != settings.get(k))
        if before.get("version") != settings.get("version"):
            raise ToolkitError(f"{parts} holds chunks from another version of apps.redirect (settings version "
                               f"{before.get('version', 1)}, this one writes {settings.get('version')}); delete {parts} "
                               f"to start over")
        if changed:
            raise ToolkitError(f"{parts} holds chunks of a run with other settings ({', '.join(changed)} differ); "
                               f"rerun with the same settings to resume, or delete {parts} to start over")
    else:
        atomic_write_json(path, settings)


def assemble(parts: Path, n_chunks: int, out_path: Path, attrs: dict) -> int:
    """Concatenate the chunk files into one HDF5 file (atomic); returns the number of images."""
    import h5py

    from toolkit.io import atomic_write

    n = 0
    with atomic_write(out_path, "w+b") as f:
        with h5py.File(f, "w") as h:
            # One chunk in memory at a time: the datasets grow as the chunks are appended (h5py reads back
            # what it wrote as they grow: the temp file is opened for reading too).
            for k in range(n_chunks):
                with np.load(_chunk_path(parts, k)) as z:
                    for name in z.files:
                        v = z[name]
                        if name not in h:
                            # Growing datasets need chunks: one image each (as write_subject_h5 stores them),
                            # small rows ~64 KiB at a time (h5py's guess from the first part may be 1 row).
                            rows = 1 if v.ndim >= 3 else max(1, min(4096, (1 << 16) // max(1, v[0].nbytes)))
                            h.create_dataset(name, data=v, maxshape=(None, *v.shape[1:]), chunks=(rows, *v.shape[1:]),
                                             compression="lzf" if v.ndim >= 3 else None)
                            continue
                        d = h[name]
                        d.resize(d.shape[0] + v.shape[0], axis=0)
                        d[-v.shape[0]:] = v
                    n += int(z["face_patch"].shape[0])
            for k, v in attrs.items():
                h.attrs[k] = v
    return n


def is_labels_csv(path: str | Path) -> bool:
    p = Path(path)
    return p.suffix.lower() == ".csv" or (p.is_dir() and (p / "labels.csv").is_file())


def open_source(ctx, args):
    """The input rows: a ``GazeDataset`` over an HDF5 file, or a validated ``LabelsCsvSource``."""
    cfg = ctx.config
    if not is_labels_csv(args.dataset):
        from train.data.dataset import GazeDataset

        ds = GazeDataset([args.dataset], res=cfg.data.res, with_mesh=True)
        ds.check_unit_scale("redirection with the Gaussian model (its head is posed rigidly)")
        return ds
    from apps.labels_csv import LabelsCsvSource
    from geometry.mesh_stats import load_mesh
    from toolkit.scene import GaussianScene
    from train.data.generate import NORM_CROP, NORM_DISTANCE

    landmarks = GaussianScene.load(ctx.path("geometry", "scene")).metadata.get("landmarks")
    if landmarks is None:
        raise ToolkitError(f"{ctx.path('geometry', 'scene')}: no landmarks in its metadata (re-run stage geometry)")
    verts, _ = load_mesh(ctx.path("geometry", "mesh"))
    return LabelsCsvSource(args.dataset, cfg.data.res, torch.tensor(landmarks, dtype=torch.float32), verts,
                           focal=args.focal, distance=args.distance, default_distance=NORM_DISTANCE,
                           default_crop=NORM_CROP)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m apps.redirect", description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", help="a trained run directory (train/run.py)")
    ap.add_argument("dataset", help="an HDF5 subject file (docs/data.md), or a labels CSV of face crops "
                                    "(or the folder holding labels.csv; columns in docs/redirect.md)")
    ap.add_argument("out", help="output HDF5 file")
    ap.add_argument("--gazes", default="grid:3x3:25", help=f"target gazes: {GRID_EXAMPLE}")
    ap.add_argument("--rows", type=int, default=0, help="use only the first N input rows (0 = all)")
    ap.add_argument("--batch", type=int, default=4, help="input rows per chunk")
    ap.add_argument("--steps", type=int, default=0, help="DDIM steps (0 = the run's evaluation setting: eval.sampling_steps, else gaussian.sampling_steps)")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of random: gazes and of the fitting's diffusion noise (drawn per chunk, so a "
                         "resumed or sharded run writes what an uninterrupted one does)")
    ap.add_argument("--focal", type=float, default=None,
                    help="CSV input: focal length (pixels of the images) for rows without one "
                         "(default: the project's normalized camera, size x 0.6 / 0.26)")
    ap.add_argument("--distance", type=float, default=None,
                    help="CSV input: camera-to-face distance (metres) for rows without one (default 0.6)")
    ap.add_argument("--fit-steps", type=int, default=-1,
                    help="test-time fitting steps: of the shape code on CSV rows without a code, and of each row "
                         "with --fit-weights (default: the run's eval.tta_steps, or 50 when that is 0)")
    ap.add_argument("--fit-lr", type=float, default=1e-2, help="CSV input: learning rate of the code fitting")
    ap.add_argument("--fit-weights", action="store_true",
                    help="fit each input row as the run's evaluation does before rendering its gazes: the code and "
                         "eval.tta_weights (by default face features, renderer) for --fit-steps steps on eval.tta_region, with "
                         "the loss estimator's gaze term at the row's target gazes; one row at a time, from the "
                         "trained weights each time (CSV rows need their own gaze)")
    ap.add_argument("--natural-eyes", action="store_true",
                    help="with --fit-weights: fit the face features, eye rotation field and renderer, with a gaze "
                         "term that may only turn the eyes (train.evaluation.fitting.NATURAL_EYES_FIT): no coloured specks "
                         "in the eyes (the demo preset's own fit since session 22; docs/redirect.md)")
    args = ap.parse_args(argv)
    keep_freed_memory()
    if args.natural_eyes and not args.fit_weights:
        raise ToolkitError("--natural-eyes sets how --fit-weights fits each row; give --fit-weights too")
    from train.run import load_trained, open_run
    from train.training.distributed import all_ranks, barrier, cleanup, init_distributed

    run_dir = Path(args.run_dir)
    if args.batch < 1:
        raise ToolkitError(f"--batch must be >= 1, got {args.batch}")
    if args.rows < 0:
        raise ToolkitError(f"--rows must be >= 0 (0 = all rows), got {args.rows}")
    if args.steps < 0:
        raise ToolkitError(f"--steps must be >= 0 (0 = the run's setting), got {args.steps}")
    if Path(args.out).suffix.lower() not in (".h5", ".hdf5"):
        raise ToolkitError(f"out {args.out}: expected an HDF5 file name ending in .h5 or .hdf5")
    if Path(args.out).is_dir():  # before any rendering: the file is only written once every chunk is done
        raise ToolkitError(f"out {args.out}: is a directory, expected the path of the HDF5 file to write")
    if not (math.isfinite(args.fit_lr) and 0 < args.fit_lr <= 1):
        raise ToolkitError(f"--fit-lr must be in (0, 1], got {args.fit_lr}")
    if not 0 <= args.seed < 2**32:  # each chunk's stream is seeded from it (and numpy takes it for random: gazes)
        raise ToolkitError(f"--seed must be in [0, 2^32), got {args.seed}")
    if Path(args.out).resolve() == Path(args.dataset).resolve():
        raise ToolkitError(f"out {args.out}: is the input dataset; the output would replace it, give another path")
    gazes = parse_gazes(args.gazes, args.seed)
    ctx = open_run(run_dir)
    cfg = ctx.config
    src = open_source(ctx, args)  # validates the whole input before any model is loaded
    fit_steps = args.fit_steps if args.fit_steps >= 0 else (cfg.eval.tta_steps or 50)
    if args.fit_weights:
        if fit_steps < 1:
            raise ToolkitError(f"--fit-weights needs --fit-steps >= 1, got {fit_steps}")
        missing = [r.line for r in getattr(src, "rows", []) if r.gaze is None]
        if missing:
            raise ToolkitError(f"{src.path} line {missing[0]}: --fit-weights fits the image at its own gaze; "
                               f"fill gaze_pitch and gaze_yaw ({len(missing)} rows lack them)")
    info = init_distributed("cpu" if not torch.cuda.is_available() else "auto")
    device = torch.device(info.device)
    model, renderer = load_trained(ctx, device)
    diffusion = getattr(renderer, "diffusion", None)
    if diffusion is not None and not 1 <= sampling_steps(args, cfg) <= diffusion.num_timesteps:
        raise ToolkitError(f"--steps must be 0 (the run's setting) or 1..{diffusion.num_timesteps} DDIM steps, "
                           f"got {args.steps}")
    fit = row_fitter(ctx, model, renderer, device, fit_steps, natural_eyes=args.natural_eyes) if args.fit_weights else None

    def items(rows: list[int]) -> list[dict]:
        if hasattr(src, "items"):
            return src.items(rows, model, renderer, device, fit_steps=fit_steps, fit_lr=args.fit_lr)
        return [src[r] for r in rows]

    n_rows = len(src) if args.rows <= 0 else min(args.rows, len(src))
    chunks = [list(range(i, min(i + args.batch, n_rows))) for i in range(0, n_rows, args.batch)]
    out = Path(args.out)
    parts = out.with_suffix(out.suffix + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    check_parts_settings(parts, redirect_settings(ctx, src, args, gazes, n_rows, fit_steps))
    from tqdm import tqdm

    from toolkit.io import atomic_write

    mine = [k for k in range(len(chunks)) if k % info.world_size == info.rank]
    todo = [k for k in mine if not _chunk_path(parts, k).exists()]
    steps = sampling_steps(args, cfg)
    failure = None
    try:
        for k in tqdm(todo, desc=f"redirect (rank {info.rank})", disable=not info.is_main,
                      initial=len(mine) - len(todo), total=len(mine)):
            # Each chunk's own random stream (a diffusion renderer's noise while fitting): its images then do not
            # depend on which chunks this process rendered before it.
            torch.manual_seed((args.seed * 1_000_003 + k) % 2**63)
            arrays = render_chunk(model, renderer, items(chunks[k]), chunks[k], gazes, cfg.data.res, steps, device, fit)
            with atomic_write(_chunk_path(parts, k), "wb") as f:
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
    barrier(info)
    if info.is_main:
        n = assemble(parts, len(chunks), out, {"source_file": str(args.dataset), "run_dir": str(run_dir),
                                               "gazes_spec": args.gazes, "generator": "apps.redirect"})
        # The settings go last: chunks left by an interrupted clean-up stay tied to what made them.
        for p in sorted(parts.iterdir(), key=lambda p: p.name == "settings.json"):
            p.unlink()
        parts.rmdir()
        print(f"wrote {out}: {n} redirected images ({n_rows} rows × {len(gazes)} gazes)")
    cleanup(info)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
