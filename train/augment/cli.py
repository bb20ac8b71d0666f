"""``python -m train.run augment --run-dir RUN --out OUT [options]``: the augmentation benchmark on a finished run
(:mod:`train.augment`) -> ``OUT/augment.json``, ``augment.md``, ``augment.png``."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence

from toolkit.errors import ToolkitError


def main(argv: Sequence[str] | None = None) -> int:
    from toolkit.io import atomic_write_json, atomic_write_text, check_not_an_input
    from train.augment.config import build_parser, config_from_args
    from train.augment.protocol import protocol_a, protocol_b
    from train.augment.report import figure, markdown, summarize
    from train.stages.artifacts import resolve_device
    from train.trained_run import TrainedRun

    args = build_parser().parse_args(argv)
    cfg = config_from_args(args)
    run = TrainedRun.open(args.run_dir)
    if args.device != "auto":
        run.config.device = args.device
    device = resolve_device(run.config)
    out = Path(args.out)
    check_not_an_input(out, [Path(args.run_dir)], "--out", "folder")
    if out.exists() and not out.is_dir():
        raise ToolkitError(f"--out {out}: exists and is not a folder")
    _check_splits(run, cfg)
    t0, log = time.perf_counter(), (lambda m: print(m, flush=True))
    runners = {"A": protocol_a, "B": protocol_b}
    raw = {p: runners[p](run, cfg, device, log) for p in cfg.protocols}
    summary = summarize(raw)
    meta = {"run_dir": str(args.run_dir), "seconds": round(time.perf_counter() - t0, 1), "device": str(device),
            "units": {"A": "repetition x held-out person", "B": "repetition"}, "config": _as_json(cfg)}
    atomic_write_json(out / "augment.json", {**summary, "meta": meta, "raw": raw})
    atomic_write_text(out / "augment.md", markdown(summary, meta))
    figure(summary, out / "augment.png")
    print(json.dumps({"out": str(out), "seconds": meta["seconds"]}))
    return 0


def _check_splits(run, cfg) -> None:
    """One line before any work when the run's data cannot give the protocols their subjects."""
    if not run.split("test"):
        raise ToolkitError(f"{run.run_dir}: the run has no held-out subjects to calibrate on")
    if "A" in cfg.protocols and min(cfg.ks) >= (most := max(_frame_count(f, run) for f in run.split("test"))):
        raise ToolkitError(f"augment --ks {list(cfg.ks)}: the run's held-out persons have at most {most} frames, "
                           f"and a k must leave a frame to test on (k < {most})")
    if "B" in cfg.protocols and not any(n <= len(run.split("train")) for n in cfg.subjects):
        raise ToolkitError(f"augment --subjects {list(cfg.subjects)}: the run has {len(run.split('train'))} "
                           "training subjects")


def _frame_count(path: Path, run) -> int:
    from train.data.dataset import GazeDataset

    ds = GazeDataset([path], layout=run.config.data.layout)
    try:
        return len(set(ds.frame_indices(0).tolist()))
    finally:
        ds.close()


def _as_json(cfg) -> dict:
    from dataclasses import asdict

    return json.loads(json.dumps(asdict(cfg)))
