"""The paper's Table 3 in one command: ``python -m train.run ablate --preset demo --seeds 3 --run-dir out/ablate``.

For each seed, the full model is trained in ``RUN_DIR/seed<s>/full`` (``seed=s``: the stages' training
randomness; the data are the same for every seed), and each row of Table 3 in a copy of it in which only the
Gaussian and eval stages run again with the row's switch (the data, geometry, codec and estimators are the full
run's, so the rows differ in that switch alone). Every row is evaluated by the same protocol; ``ablation.md``
and ``ablation.png`` give each row's mean and its paired 95 % interval against the full model (units: seeds)
and its wall time. Resumable: ``train.run`` skips every stage that finished under the same config, so a rerun
trains only what is missing. ``--augment`` adds protocol A of ``train.run augment`` per row as a column.

``--row NAME OVERRIDE...`` (repeatable) replaces Table 3's rows by rows of the user's own against the same full
model, e.g. one switch of the paper's recipe each (docs/model.md): ``--row "paper optimizer"
gaussian.lr=1e-4 gaussian.renderer_lr=1e-4 gaussian.lr_schedule=step``. Only Gaussian- and eval-stage keys
make a row that shares the full run's earlier stages; another key retrains those stages in the row's copy.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Sequence

from toolkit.errors import ERROR_FILE_ENV, CliParser, ToolkitError

ROWS = (("full", ()),
        ("w/o DiT renderer", ("gaussian.renderer=unet", "gaussian.feature_upscale=4")),
        ("w/o orthogonality loss", ("gaussian.orthogonality=false",)),
        ("w/o weak supervision", ("gaussian.weak_supervision=false",)))
"""Table 3's rows: (name, overrides of the full model). Without the DiT renderer is GazeGaussian's renderer at
its own upscale (4: docs/renderer.md)."""
METRICS = (("gaze", "gaze_error_deg", -1), ("head pose", "head_pose_error_deg", -1), ("PSNR", "psnr", 1),
           ("SSIM", "ssim", 1), ("LPIPS", "lpips", -1), ("FID", "fid", -1))
"""(column, metrics.json key, +1 when higher is better)."""
AUGMENT_COLUMN = "augment A (iii) − (ii)"
"""The prefix of the augmentation columns (``--augment``): one per calibration level k."""


def build_parser() -> argparse.ArgumentParser:
    p = CliParser(prog="python -m train.run ablate",
                  description="Train and evaluate the paper's Table 3 rows over seeds (docs/augment.md). "
                                            "The demo preset on 2 cores: ~15 min for a seed's full run, then "
                                            "5-7 min for each other row; --augment adds 3-5 min a row and seed.")
    p.add_argument("--preset", default="demo", help="the preset of every row (default: demo)")
    p.add_argument("--seeds", type=int, default=3, help="seeds (repetitions) per row, >= 1 (default: 3)")
    p.add_argument("--run-dir", default="out/ablate", help="folder of the rows' run directories and the table")
    p.add_argument("--augment", action="store_true", help="add protocol A of `train.run augment` per row")
    p.add_argument("--row", nargs="+", action="append", metavar=("NAME", "OVERRIDE"),
                   help="a row of your own, repeatable: its name, then its section.key=value overrides of the full "
                        "model; given, these rows replace Table 3's")
    p.add_argument("overrides", nargs="*", help="section.key=value overrides applied to every row")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from toolkit.io import atomic_write_json, atomic_write_text

    args = build_parser().parse_args(argv)
    if not 1 <= args.seeds <= 100:
        raise ToolkitError(f"ablate --seeds: expected 1 to 100 seeds, got {args.seeds}")
    root = Path(args.run_dir)
    rows = table_rows(args.row)
    check_rows(args.preset, args.overrides, rows)
    results = {name: [] for name, _ in rows}
    for seed in range(args.seeds):
        full = root / f"seed{seed}" / "full"
        for k, (name, switch) in enumerate(rows):
            row_dir = full if k == 0 else full.with_name(_slug(name))
            results[name].append(_run_row(args, full, row_dir, seed, switch))
    table = summarize_rows(results)
    atomic_write_json(root / "ablation.json", {"rows": table, "raw": results, "seeds": args.seeds,
                                               "preset": args.preset, "overrides": args.overrides,
                                               "row_overrides": {name: list(switch) for name, switch in rows}},
                      strict=True)  # one seed: no interval (inf), written as null
    atomic_write_text(root / "ablation.md", ablation_markdown(table, args))
    ablation_figure(table, root / "ablation.png")
    print(json.dumps({"table": str(root / "ablation.md")}))
    return 0


def table_rows(custom: list[list[str]] | None) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The rows to train: Table 3's (:data:`ROWS`), or ``ROWS[0]`` (the full model) and the ``--row`` rows
    ([name, override, ...] each), checked for one line each before any training."""
    if not custom:
        return ROWS
    rows = [ROWS[0]]
    for name, *overrides in custom:
        slugs = [_slug(n) for n, _ in rows]
        if not _slug(name).strip("_.") or _slug(name) in slugs:
            raise ToolkitError(f"ablate --row {name!r}: expected a name of its own (not empty, not 'full', "
                               f"unlike the other rows' folders {slugs})")
        bad = [o for o in overrides if "=" not in o or "." not in o.split("=", 1)[0]]
        if not overrides or bad:
            raise ToolkitError(f"ablate --row {name!r}: expected one or more section.key=value overrides, got "
                               f"{bad or overrides}")
        rows.append((name, tuple(overrides)))
    return tuple(rows)


def check_rows(preset_name: str, overrides: list[str], rows) -> None:
    """Each row's config built and checked as its ``train.run`` will build it, before any training: a bad preset,
    key or value is one line naming the row."""
    from train.config import apply_overrides
    from train.presets import PRESETS, preset
    from train.stages.checks import check_config

    if preset_name not in PRESETS:
        raise ToolkitError(f"ablate --preset {preset_name!r}: expected one of {sorted(PRESETS)}")
    try:
        shared = apply_overrides(preset(preset_name), overrides)
        check_config(shared)  # the full row's config
    except ToolkitError as e:
        raise ToolkitError(f"ablate overrides (every row's): {e}") from None
    for name, switch in rows[1:]:
        try:
            check_config(apply_overrides(shared, list(switch)))
        except ToolkitError as e:
            raise ToolkitError(f"ablate row {name!r}: {e}") from None


def _slug(name: str) -> str:
    """The row's folder name: lower case, 'w/o ' as 'no_', anything but letters, digits, '.', '-' as '_'."""
    return re.sub(r"[^a-z0-9.\-]+", "_", name.replace("w/o ", "no_").lower())


def _run_row(args, full: Path, row_dir: Path, seed: int, switch: tuple[str, ...]) -> dict:
    """Train (or resume) one row of one seed, in a process of its own, and read its metrics and wall time."""
    import subprocess
    import sys

    if row_dir == full:
        argv = ["--preset", args.preset, "--run-dir", str(full), f"seed={seed}", *args.overrides]
    else:
        if not (row_dir / "config.yaml").exists():  # a copy of the full run: its data, geometry, codec, estimators
            _copy_run(full, row_dir)
        argv = ["--preset", args.preset, "--run-dir", str(row_dir), f"seed={seed}", *args.overrides, *switch]
    # The row's error line comes back through a file and becomes this command's one error line; its progress
    # and warnings reach the terminal as they happen.
    with tempfile.TemporaryDirectory() as tmp:
        error_file = Path(tmp) / "error"
        code = subprocess.run([sys.executable, "-m", "train.run", *argv],
                              env={**os.environ, ERROR_FILE_ENV: str(error_file)}).returncode
        error = error_file.read_text(encoding="utf-8").strip() if error_file.exists() else ""
    if code != 0:
        raise ToolkitError(f"{row_dir}: the row's run failed: {error or f'exit {code} (its output is above)'}")
    metrics = json.loads((row_dir / "metrics.json").read_text())["metrics"]
    seconds = sum(json.loads((row_dir / "stages" / f"{s}.json").read_text()).get("seconds", 0.0)
                  for s in ("gaussian", "eval"))
    out = {key: metrics.get(key) for _, key, _ in METRICS} | {"seconds": seconds}
    if args.augment:
        out["augment_A"] = _augment_row(row_dir)
    return out


def _copy_run(full: Path, row_dir: Path) -> None:
    """``full`` without its Gaussian stage and evaluation, copied to ``row_dir`` whole or not at all."""
    if row_dir.exists():
        raise ToolkitError(f"{row_dir}: exists but is not a run directory (no config.yaml); remove it, and the "
                           "row is copied from the full run again")
    tmp = row_dir.with_name(f".{row_dir.name}.copying")
    shutil.rmtree(tmp, ignore_errors=True)  # an interrupted copy's leftovers
    shutil.copytree(full, tmp, ignore=shutil.ignore_patterns("gaussian", "metrics.json", "report.md", "augment"))
    tmp.rename(row_dir)


def _augment_row(row_dir: Path) -> dict:
    """Protocol A of ``train.run augment`` on one row (written beside it): (iii) − (ii) at each k."""
    from train.augment.cli import main as augment

    out = row_dir / "augment"
    if not (out / "augment.json").exists():
        augment(["--run-dir", str(row_dir), "--out", str(out), "--protocols", "A", "--seeds", "1"])
    res = json.loads((out / "augment.json").read_text())["A"]
    return {k: c["diff"] for k, c in res["iii"].items()}


def summarize_rows(results: dict[str, list[dict]]) -> dict:
    """{row: {column: paired(row, full) or None}} over the seeds (``train.augment.report.paired``)."""
    from train.augment.report import paired

    full = results[ROWS[0][0]]  # the full model is every table's first row
    table = {}
    for name, runs in results.items():
        cells = {}
        for column, key in [(c, k) for c, k, _ in METRICS] + [("wall time (s)", "seconds")]:
            a, r = [x.get(key) for x in runs], [x.get(key) for x in full]
            known = all(isinstance(v, (int, float)) and math.isfinite(v) for v in a + r)  # LPIPS, FID: n/a without weights
            cells[column] = paired(a, r) if known else None
        if all("augment_A" in x for x in runs + full):
            for k in runs[0]["augment_A"]:
                gains = [x["augment_A"][k] for x in runs]
                # The full row's cell is (iii) − (ii) against 0, with its interval; the others' against the full row's.
                cells[f"{AUGMENT_COLUMN} k={k}"] = (paired(gains, [0.0] * len(runs)) | {"against_zero": True}
                                                    if name == ROWS[0][0] else paired(gains, [x["augment_A"][k] for x in full]))
        table[name] = cells
    return table


def ablation_markdown(table: dict, args) -> str:
    columns = [c for c in next(iter(table.values())) if any(row[c] is not None for row in table.values())]
    title = "Switches against the full model" if args.row else "Table 3: ablations"
    lines = [f"# {title} ({args.preset} preset, {args.seeds} seed{'s' * (args.seeds != 1)})", "",
             "Mean over seeds; other rows: (row − full) and its paired 95 % t interval (units: seeds). Gaze and head "
             "pose in degrees, wall time of the Gaussian and eval stages." + _augment_note(columns), "",
             "| row | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
    for name, cells in table.items():
        lines.append(f"| {name} | " + " | ".join(_cell(cells[c], name == ROWS[0][0]) for c in columns) + " |")
    return "\n".join(lines + ["", "![ablation](ablation.png)", ""])


def _augment_note(columns: list[str]) -> str:
    if not any(c.startswith(AUGMENT_COLUMN) for c in columns):
        return ""
    return (f" {AUGMENT_COLUMN}: protocol A of `train.run augment`, (iii) − (ii) in degrees (negative: the row's "
            "redirected copies help a k-frame calibration), the full row with its own 95 % interval over the seeds.")


def _cell(c: dict | None, full: bool) -> str:
    if c is None:
        return "n/a"
    mean = _num(c["mean"], 3)
    if c.get("against_zero"):
        return f"{mean} [{_num(c['lo'], 2, '+')}, {_num(c['hi'], 2, '+')}]"
    return mean if full else f"{mean} ({_num(c['diff'], 2, '+')} [{_num(c['lo'], 2, '+')}, {_num(c['hi'], 2, '+')}])"


def _num(x: float, digits: int, sign: str = "") -> str:
    """``x`` to ``digits`` significant digits, never in exponent form (wall times run to thousands of seconds)."""
    return f"{x:{sign}.0f}" if abs(x) >= 10 ** digits else f"{x:{sign}.{digits}g}"


def ablation_figure(table: dict, path: Path) -> None:
    """``ablation.png``: gaze error and PSNR per row, with the paired intervals as error bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from train.augment.report import write_png

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    names = list(table)
    for ax, column in zip(axes, ("gaze", "PSNR")):
        cells = [table[n][column] for n in names]
        means = [c["mean"] if c else 0 for c in cells]
        err = [(c["hi"] - c["diff"]) if c and c["hi"] != c["diff"] else 0 for c in cells]
        ax.bar(range(len(names)), means, yerr=[min(e, 1e3) for e in err], capsize=4)
        ax.set_xticks(range(len(names)), names, rotation=15, fontsize=8)
        ax.set_ylabel("gaze error (deg)" if column == "gaze" else "PSNR (dB)")
    write_png(fig, path)
