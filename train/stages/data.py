"""Stage ``data``: generate the synthetic dataset (nothing to do when ``data.root`` points at subject files)."""

from __future__ import annotations

from pathlib import Path

from toolkit.errors import ToolkitError
from train.stages.pipeline import RunContext


def stage_data(ctx: RunContext) -> dict[str, str]:
    """Write ``data.subjects`` synthetic subjects and their split into ``run_dir/data``; outputs ``dir`` and
    ``split`` (none with an external ``data.root``, which must exist)."""
    d = ctx.config.data
    if d.root:
        if not Path(d.root).exists():
            raise ToolkitError(f"data.root: {d.root} does not exist")
        return {}
    from train.data.generate import synth_dataset

    synth_dataset(ctx.run_dir / "data", n_subjects=d.subjects, n_frames=d.frames, res=d.res, seed=d.seed,
                  test_fraction=d.test_fraction, light_jitter=d.light_jitter, log=ctx.log,
                  test_frames=d.test_frames or None, kappa_deg=d.kappa_deg)
    return {"dir": "data", "split": "data/split.json"}
