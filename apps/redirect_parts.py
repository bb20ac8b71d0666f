"""``apps.redirect``'s resumable output: the chunks in ``OUT.parts/``, the settings they were made with, and
the final HDF5 file assembled from them."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from apps.labels_table import is_labels_csv
from toolkit.errors import ToolkitError

SETTINGS_VERSION = 3
"""The format of ``OUT.parts/settings.json`` this app writes (chunks of another are refused): 2 seeds the
fitting's noise per chunk (1 had no version field), 3 stamps the input's contents (``input_stamp``), not only
its path."""


def chunk_path(parts: Path, k: int) -> Path:
    """The file of chunk ``k`` in ``parts``."""
    return parts / f"part_{k:05d}.npz"


def sampling_steps(args, cfg) -> int:
    """The DDIM steps to render with: ``--steps``, else the run's evaluation setting."""
    from train.run_config import eval_sampling_steps

    return args.steps or eval_sampling_steps(cfg)  # the run's evaluation renders with these


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


def redirect_settings(run, src, args, gazes: np.ndarray, n_rows: int, fit_steps: int, photos: dict | None = None) -> dict:
    """What the chunks' contents depend on, resolved (the same input or setting spelt another way is the same):
    the run (``TrainedRun``: its trained checkpoint's size and time), the input file, the gazes themselves, the
    rows, the rendering and the fitting (with the run's eval section when rows are weight-fitted); CSV-only
    settings for CSV input only. ``photos`` (photo input: ``apps.redirect_photo.photo_settings``) replaces the
    prepared file's path and stamp, which change every run, by the photos' and the preparation's settings."""
    import hashlib

    st = run.context.path("gaussian", "checkpoint").stat()
    settings = {"version": SETTINGS_VERSION, "run_dir": str(run.run_dir.resolve()), "checkpoint": [st.st_size, st.st_mtime_ns],
                "dataset": str(Path(getattr(src, "path", args.dataset)).resolve()),
                "input_stamp": input_stamp(src, args.dataset),
                "gazes_sha1": hashlib.sha1(np.ascontiguousarray(gazes, np.float64).tobytes()).hexdigest(),
                "rows": n_rows, "batch": args.batch, "steps": sampling_steps(args, run.config),
                "fit_weights": args.fit_weights, "natural_eyes": args.natural_eyes}
    if photos is not None:
        settings.update(photos)
    csv = is_labels_csv(args.dataset)
    if csv:
        settings.update(focal=args.focal, distance=args.distance, fit_lr=args.fit_lr)
    if args.fit_weights or csv:  # fitting draws the diffusion renderer's noise from the seed's streams
        settings.update(fit_steps=fit_steps, seed=args.seed)
    if args.fit_weights:
        as_json = lambda d: {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}  # noqa: E731
        settings["eval"] = as_json({k: v for k, v in vars(run.config.eval).items()
                                    if k.startswith("tta_") and k != "tta_steps"})  # the steps: fit_steps
        if args.natural_eyes:  # what the fit then uses in place of the section's weights and gaze term
            from train.presets import NATURAL_EYES_FIT

            settings["natural_eyes_fit"] = as_json(NATURAL_EYES_FIT)
    return settings


def check_out_of_run(out: str | Path, run_dir: str | Path) -> None:
    """Before any work: an output inside the run directory must neither add a subject file to its data folder
    (a retraining would take it as a subject) nor replace one of its files; an earlier output of this command
    there (its ``generator`` attribute) may be written again. Paths compared resolved, links followed."""
    out_r, run_r = Path(out).resolve(), Path(run_dir).resolve()
    if not out_r.is_relative_to(run_r):
        return
    if out_r.is_relative_to(run_r / "data"):
        raise ToolkitError(f"out {out}: inside the run's data folder ({run_dir}/data), where a retraining would "
                           "read it as a subject; give another path")
    if out_r.exists() and not _is_redirect_output(out_r):
        raise ToolkitError(f"out {out}: already exists inside the run {run_dir} and is not an earlier output of "
                           "apps.redirect; writing it would replace it, give another path")


def _is_redirect_output(path: Path) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("generator") == "apps.redirect"
    except (OSError, ValueError):  # not an HDF5 file: one of the run's own
        return False


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


def read_chunk(path: Path, parts: Path, keys: set[str] | None, like: dict | None, source_rows: np.ndarray | None) -> dict:
    """Chunk ``path``'s arrays, checked before any goes into the output: a chunk left by an earlier run may have
    been cut short or edited, and a bad one would otherwise be a traceback or, worse, a file with NaN or with
    datasets of unequal lengths. It must load, hold exactly ``keys`` (None: any, ``face_patch`` among them), give
    every array its expected rows (``source_rows`` [n]: the ``source_row`` column it must hold, else as many as
    its ``face_patch``), the trailing shapes and dtypes of ``like`` (the chunk read before it, so the datasets
    can grow) and only finite floats. Any fault is one ToolkitError naming the chunk and how to have it rendered again."""
    from toolkit.errors import one_line

    def bad(problem: str) -> ToolkitError:
        return ToolkitError(f"chunk {path}: {problem}; delete it (or the folder {parts}) and rerun the same "
                            "command to render it again")

    try:
        z = np.load(path)  # pickles refused (allow_pickle=False): a chunk holds plain arrays
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError("a single .npy array, not an .npz archive")
        with z:
            arrays = {name: z[name] for name in z.files}
    except Exception as e:  # noqa: BLE001 -- a damaged archive fails in many ways (zip, zlib, npy header, EOF)
        raise bad(f"unreadable ({type(e).__name__}: {one_line(e, 160)})") from None
    needed = {"face_patch"} | ({"source_row"} if source_rows is not None else set())  # counted, compared below
    keys = keys if keys is not None else set(arrays) | needed
    missing, extra = sorted(keys - set(arrays)), sorted(set(arrays) - keys)
    if missing or extra:
        raise bad("; ".join([f"missing the arrays {', '.join(missing)}"] * bool(missing)
                            + [f"unexpected arrays {', '.join(extra)}"] * bool(extra)))
    rows = np.shape(arrays["face_patch"])[:1] if source_rows is None else (len(source_rows),)
    for name, v in sorted(arrays.items()):
        if not rows or v.shape[:1] != rows:
            raise bad(f"array {name!r} has shape {v.shape}, expected " + (f"{rows[0]} rows" if rows else "rows"))
        if like is not None and (v.shape[1:] != like[name].shape[1:] or v.dtype != like[name].dtype):
            raise bad(f"array {name!r} is {v.dtype} of shape {v.shape}, expected {like[name].dtype} rows of shape "
                      f"{like[name].shape[1:]} as in the chunks before it")
        n_bad = int((~np.isfinite(v)).sum()) if v.dtype.kind in "fc" else 0
        if n_bad:
            raise bad(f"array {name!r} holds {n_bad} non-finite values (NaN or inf)")
    if source_rows is not None and not np.array_equal(arrays["source_row"], source_rows):
        raise bad("its 'source_row' column is not the input rows this chunk renders")
    return arrays


def assemble(parts: Path, n_chunks: int, out_path: Path, attrs: dict, extra_rows: dict | None = None,
             source_rows: list[np.ndarray] | None = None, keys: Sequence[str] | None = None) -> int:
    """Concatenate the chunk files into one HDF5 file (atomic); returns the number of images. ``extra_rows``:
    name -> [N_in, ...] arrays of the input rows, written per output row (``v[source_row]``). Each chunk is
    checked as it is read (``read_chunk``) against ``source_rows`` (per chunk, the ``source_row`` column it
    must hold; default: as many rows as its ``face_patch``) and ``keys`` (default: the first chunk's); a bad
    one writes nothing."""
    from toolkit.io import atomic_h5
    from toolkit.limits import check_allocation

    n, like = 0, None
    # The file is built in memory (a full disk then fails cleanly, see atomic_h5): at most its parts' size.
    check_allocation(sum(chunk_path(parts, k).stat().st_size for k in range(n_chunks)), f"writing {out_path}",
                     "ask for fewer target gazes or inputs per run")
    with atomic_h5(out_path) as h:
        # One chunk in memory at a time: the datasets grow as the chunks are appended.
        for k in range(n_chunks):
            want = set(keys) if keys is not None else set(like) if like is not None else None
            arrays = read_chunk(chunk_path(parts, k), parts, want, like,
                                None if source_rows is None else source_rows[k])
            for name, v in arrays.items():
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
            n += int(arrays["face_patch"].shape[0])
            like = {name: np.empty((0, *v.shape[1:]), v.dtype) for name, v in arrays.items()}  # not a view: frees the chunk
        for k, v in (extra_rows or {}).items():
            h.create_dataset(k, data=np.asarray(v)[h["source_row"][:]])
        for k, v in attrs.items():
            h.attrs[k] = v
    return n
