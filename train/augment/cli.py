"""``python -m train.run augment --run-dir RUN --out OUT [options]``: the augmentation benchmark on a finished run
(:mod:`train.augment`) -> ``OUT/augment.json``, ``augment.md``, ``augment.png``."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from toolkit.errors import ToolkitError

OUTPUTS = ("augment.json", "augment.md", "augment.png")


def main(argv: Sequence[str] | None = None) -> int:
    from toolkit.io import atomic_write_json, atomic_write_text, check_not_an_input, check_output_folder
    from train.augment.config import build_parser, config_from_args
    from train.augment.protocol import protocol_a, protocol_b
    from train.augment.report import figure, markdown, summarize
    from train.stages.artifacts import resolve_device
    from train.trained_run import TrainedRun

    args = build_parser().parse_args(argv)
    cfg = config_from_args(args)
    run = TrainedRun.open(args.run_dir)
    run.config.device = cfg.device  # auto: CUDA when available, whatever device the run trained on
    device = resolve_device(run.config)
    out = Path(args.out)
    check_not_an_input(out, [Path(args.run_dir)], "--out", "folder")
    check_output_folder(out, f"--out {out}")
    _check_splits(run, cfg)
    _make_out(out)
    t0, log = time.perf_counter(), (lambda m: print(m, flush=True))
    runners = {"A": protocol_a, "B": protocol_b}
    raw = {p: runners[p](run, cfg, device, log) for p in cfg.protocols}
    summary = summarize(raw)
    meta = {"run_dir": str(args.run_dir), "seconds": round(time.perf_counter() - t0, 1), "device": str(device),
            "units": {"A": "repetition x held-out person", "B": "repetition"}, "config": _as_json(cfg)}
    figure(summary, out / "augment.png")
    atomic_write_text(out / "augment.md", markdown(summary, meta))
    # Last: it marks a finished run. Strict JSON: one repetition has no interval (inf), written as null.
    atomic_write_json(out / "augment.json", {**summary, "meta": meta, "raw": raw}, strict=True)
    print(json.dumps({"out": str(out), "seconds": meta["seconds"]}))
    return 0


def _check_splits(run, cfg) -> None:
    """One line before any work when the run's data cannot give the protocols their subjects, or their copies
    would not fit in memory."""
    from toolkit.limits import check_allocation

    test_files = run.split("test")
    if not test_files:
        raise ToolkitError(f"{run.run_dir}: the run has no held-out subjects to calibrate on")
    held_out, train = [_frames(f, run) for f in test_files], [_frames(f, run) for f in run.split("train")]
    copies, image = 0, 3 * run.config.data.res ** 2  # uint8 RGB rows
    if "A" in cfg.protocols:
        if min(cfg.ks) >= (most := max(n for n, _ in held_out)):
            raise ToolkitError(f"augment --ks {list(cfg.ks)}: the run's held-out persons have at most {most} "
                               f"frames, and a k must leave a frame to test on (k < {most})")
        k = max(k for k in cfg.ks if k < most)
        copies = max(2 * k * min(cfg.redirect_cameras, cams) for _, cams in held_out)  # arms iii and iv
    if "B" in cfg.protocols:
        if not any(n <= len(train) for n in cfg.subjects):
            raise ToolkitError(f"augment --subjects {list(cfg.subjects)}: the run has {len(train)} training subjects")
        copies = max(copies, sum(n * min(cfg.redirect_cameras, cams) for n, cams in train))
    check_allocation(copies * cfg.grid ** 2 * image, f"augment's {copies * cfg.grid ** 2} redirected images",
                     "lower --grid or --redirect-cameras")


def _frames(path: Path, run) -> tuple[int, int]:
    """(frames, most cameras of a frame) of one subject file, from its labels."""
    from train.data.dataset import GazeDataset

    ds = GazeDataset([path], layout=run.config.data.layout)
    try:
        frames = ds.frame_indices(0)
    finally:
        ds.close()
    _, cams = np.unique(frames, return_counts=True)
    return len(cams), int(cams.max())


def _make_out(out: Path) -> None:
    """The output folder (checked by ``check_output_folder``), made before any work; none of its three files may
    be a folder."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # a read-only mount
        raise ToolkitError(f"--out {out}: cannot write here ({e.strerror or e})") from None
    if clash := [name for name in OUTPUTS if (out / name).is_dir()]:
        raise ToolkitError(f"--out {out}: {clash[0]} is a folder; expected a file to write")


def _as_json(cfg) -> dict:
    from dataclasses import asdict

    return json.loads(json.dumps(asdict(cfg)))
