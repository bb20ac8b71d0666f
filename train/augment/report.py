"""The augmentation benchmark's results: paired differences with 95 % intervals, ``augment.json``, a Markdown
table and a PNG (error against k, one line per arm)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

REFERENCE = {"A": "ii", "B": "real"}
"""The arm every other arm of a protocol is compared with (the honest control)."""
T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228,
       12: 2.179, 15: 2.131, 20: 2.086, 30: 2.042}
"""Two-sided 95 % Student t quantiles by degrees of freedom (between entries the next lower one: wider)."""


def t95(dof: int) -> float:
    if dof <= 0:
        return math.inf
    return T95[max(d for d in T95 if d <= dof)] if dof <= 30 else 1.96


def paired(arm: list[float], reference: list[float]) -> dict[str, float]:
    """Mean of ``arm`` and its paired difference to ``reference`` (same units in the same order) with the
    difference's 95 % t interval: {"mean", "diff", "lo", "hi", "n"} (degrees; negative diff = better)."""
    a, r = np.asarray(arm, np.float64), np.asarray(reference, np.float64)
    d = a - r
    half = t95(len(d) - 1) * (d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else math.inf)
    return {"mean": float(a.mean()), "diff": float(d.mean()), "lo": float(d.mean() - half),
            "hi": float(d.mean() + half), "n": int(len(d))}


def summarize(results: dict[str, dict]) -> dict:
    """``{protocol: {arm: {level: paired(...)}}}`` from the protocols' raw errors."""
    out = {}
    for protocol, arms in results.items():
        ref = arms[REFERENCE[protocol]]
        out[protocol] = {arm: {lvl: paired(errs, ref[lvl]) for lvl, errs in levels.items()} for arm, levels in arms.items()}
    return out


def gain(summary: dict, k: str) -> dict[str, float]:
    """Protocol A at ``k``: (iii)'s relative gain over (ii) and the share of the (ii) -> (iv) gap it closes."""
    a = summary["A"]
    ii, iii, iv = (a[arm][k]["mean"] for arm in ("ii", "iii", "iv"))
    gap = ii - iv
    return {"relative": (ii - iii) / ii, "gap_closed": (ii - iii) / gap if gap > 0 else float("nan")}


def markdown(summary: dict, meta: dict) -> str:
    lines = [f"# Does redirected data make a gaze estimator better? ({meta['run_dir']})", "",
             "Gaze error in degrees on held-out rows; diff = arm − control (negative is better) with its paired 95 % "
             f"t interval over the units: protocol A {meta['units']['A']}, protocol B {meta['units']['B']}.", ""]
    names = {"A": "Protocol A: personal calibration (control: ii, k real frames)",
             "B": "Protocol B: few training subjects (control: real frames only)"}
    for protocol, arms in summary.items():
        levels = sorted(next(iter(arms.values())), key=int)
        lines += [f"## {names[protocol]}", "", "| arm | " + " | ".join(f"{'k' if protocol == 'A' else 'n'} = {lv}"
                                                                        for lv in levels) + " |",
                  "|---|" + "---|" * len(levels)]
        for arm, cells in arms.items():
            lines.append(f"| {arm} | " + " | ".join(_cell(cells[lv], arm == REFERENCE[protocol]) for lv in levels) + " |")
        lines.append("")
    if "A" in summary:
        for k in sorted(summary["A"]["ii"], key=int):
            g = gain(summary, k)
            lines.append(f"k = {k}: (iii) against (ii), {-100 * g['relative']:+.1f} % error (negative is better); "
                         f"(iii) closes {100 * g['gap_closed']:.0f} % of the (ii) → (iv) gap.")
    lines += ["", "![error against k](augment.png)", ""]
    return "\n".join(lines)


def _cell(c: dict, control: bool) -> str:
    return f"{c['mean']:.2f}" if control else f"{c['mean']:.2f} ({c['diff']:+.2f} [{c['lo']:+.2f}, {c['hi']:+.2f}])"


def figure(summary: dict, path: Path) -> None:
    """``augment.png``: per protocol, mean error against k (or n) with one line per arm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(summary), figsize=(5 * len(summary), 3.6), squeeze=False)
    for ax, (protocol, arms) in zip(axes[0], summary.items()):
        for arm, cells in arms.items():
            lv = sorted(cells, key=int)
            ax.plot([int(v) for v in lv], [cells[v]["mean"] for v in lv], "o-", label=arm)
        ax.set_xticks(sorted({int(v) for cells in arms.values() for v in cells}))
        ax.set_xlabel("calibration frames k" if protocol == "A" else "training subjects n")
        ax.set_ylabel("gaze error (deg)")
        ax.set_title(f"protocol {protocol}")
        ax.legend()
    write_png(fig, path)


def write_png(fig, path: Path) -> None:
    """Write a matplotlib figure to ``path`` atomically as a PNG, and close it."""
    import matplotlib.pyplot as plt

    from toolkit.io import atomic_path

    try:
        fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
    finally:
        plt.close(fig)
