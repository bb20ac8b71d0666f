"""``train.run augment``'s protocol A on a trained run: wall time against the redirected arm's gain, by cost knob.

Protocol A (docs/augment.md) spends its time on the base estimator, one test-time fit per redirected input
(``--redirect-cameras`` cameras of each calibration frame) and the arms' fine-tuning. For each value of
``--redirect-cameras`` (one run of ``python -m train.run augment --protocols A`` each, into
``out/benchmarks/augment/cams<n>``), this prints the wall-clock seconds against, at each k, the control's error
(ii), the redirected arm's (iii), its paired difference (iii) − (ii) with the 95 % interval, and the truth arm's
(iv). Writes ``out/benchmarks/augment.png``: (iii) − (ii) against seconds, one line per k.

    .venv/bin/python benchmarks/augment.py [--run-dir out/demo/run] [--redirect-cameras 1 3] [--seeds 3]
                                           [--ks 1 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from benchmarks.common import OUT_DIR, count, demo_or_tiny_run, format_table, machine_info, save_plot  # noqa: E402
from toolkit.errors import CliParser, run_cli  # noqa: E402


def protocol_a_rows(run_dir: str, cams: int, args) -> list[dict]:
    """One protocol A run with ``--redirect-cameras cams`` -> a table row per k (seconds: the whole run)."""
    from train.augment.cli import main as augment

    out = OUT_DIR / "augment" / f"cams{cams}"
    argv = ["--run-dir", run_dir, "--out", str(out), "--protocols", "A", "--seeds", str(args.seeds),
            "--redirect-cameras", str(cams), "--ks", *map(str, args.ks)]
    t0 = time.perf_counter()
    if augment(argv) != 0:
        raise SystemExit(f"augment {' '.join(argv)} failed")
    seconds = time.perf_counter() - t0
    a = json.loads((out / "augment.json").read_text())["A"]
    rows = []
    for k in a["iii"]:
        iii = a["iii"][k]
        rows.append({"cameras": cams, "k": int(k), "seconds": round(seconds, 1), "ii °": a["ii"][k]["mean"],
                     "iii °": iii["mean"], "iii − ii °": iii["diff"], "95% lo": iii["lo"], "95% hi": iii["hi"],
                     "iv °": a["iv"][k]["mean"], "units": iii["n"]})
    return rows


def main(argv=None) -> int:
    ap = CliParser(description=__doc__.split("\n")[0], epilog=__doc__,
                   formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-dir", default=None,
                    help="a trained run on synthetic data (default: out/demo/run when `make demo` made one, else "
                         "the tiny preset is trained into out/benchmarks/augment_tiny_run)")
    ap.add_argument("--redirect-cameras", type=count("--redirect-cameras", 1), nargs="+", default=[1, 3],
                    help="values of augment --redirect-cameras to time (each one protocol A run)")
    ap.add_argument("--seeds", type=count("--seeds", 1), default=3, help="augment --seeds (repetitions)")
    ap.add_argument("--ks", type=count("--ks", 1), nargs="+", default=[1, 3], help="augment --ks")
    ap.add_argument("--threads", type=count("--threads", 1), default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    run_dir = args.run_dir or demo_or_tiny_run("augment_tiny_run")
    print(machine_info())
    rows = [r for cams in args.redirect_cameras for r in protocol_a_rows(run_dir, cams, args)]
    print(format_table(rows))
    series = {f"k={k}": ([r["seconds"] for r in rows if r["k"] == k], [r["iii − ii °"] for r in rows if r["k"] == k])
              for k in sorted({r["k"] for r in rows})}
    save_plot(OUT_DIR / "augment.png", series, xlabel="protocol A wall time (s)",
              ylabel="(iii) − (ii) gaze error (deg; < 0: redirected data helps)",
              title=f"protocol A on {run_dir}, by --redirect-cameras {args.redirect_cameras}")
    print(f"wrote {OUT_DIR / 'augment.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
