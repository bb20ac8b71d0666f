"""A finished run directory, opened for use: what apps and benchmarks load a trained model with.

    run = TrainedRun.open("out/demo/run")
    model, renderer = run.load_model("cpu")
    test_files = run.split("test")
    fit = run.row_fitter(model, renderer, "cpu", steps=30)   # the evaluation's fitting of a new face

Everything is read as the stages wrote it (``train.stages.artifacts.RunArtifacts``, which the stages use too).
"""

from __future__ import annotations

import logging
from pathlib import Path

from toolkit.errors import ToolkitError
from train.config import load_yaml_config
from train.run_config import RunConfig
from train.stages import STAGES
from train.stages.artifacts import RunArtifacts
from train.stages.pipeline import RunContext, finished_stages


class TrainedRun(RunArtifacts):
    """A run directory's config and the outputs of its finished stages (``.context`` for the stage runner),
    with what is built from them: ``.split(which)``, ``.estimator(role, device)``, ``.load_model(device)``,
    ``.build_model(device)``, ``.row_fitter(...)`` (see :class:`RunArtifacts`); its model's code is as wide as the
    data it was trained on (``.code_widths()``)."""

    @classmethod
    def open(cls, run_dir: str | Path) -> "TrainedRun":
        """A finished (or partly finished) run directory, with the outputs of every stage that finished in it
        (whether or not its fingerprint still matches ``config.yaml``: a warning names the stale ones). A
        ToolkitError when it is not a run directory or its Gaussian stage has not finished."""
        run_dir = Path(run_dir)
        if not (run_dir / "config.yaml").is_file():
            raise ToolkitError(f"{run_dir}: not a run directory (no config.yaml); train one with python -m train.run")
        ctx = RunContext(run_dir, _run_config(run_dir / "config.yaml"), log=lambda m: None)
        stale = finished_stages(STAGES, ctx)
        if "gaussian" not in ctx.outputs:
            raise ToolkitError(f"{run_dir}: stage 'gaussian' has not finished; there is no trained model")
        if stale:
            # A finished model stays usable after config.yaml was edited or the toolkit added config fields;
            # python -m train.run would re-run these stages.
            logging.getLogger(__name__).warning(
                "%s: stage(s) %s ran under a different config than config.yaml now gives; using their outputs as "
                "they are", run_dir, ", ".join(stale))
        return cls(ctx)

    def code_widths(self) -> tuple[int, int]:
        """(identity, expression) widths of the trained model's code, as its final checkpoint records them
        (``train.stages.artifacts.checkpoint_code_widths``): the run's data's, 80 + 64 for native data."""
        from train.stages.artifacts import checkpoint_code_widths

        return checkpoint_code_widths(self.context.path("gaussian", "checkpoint"))

    def build_model(self, device, code_widths: tuple[int, int] | None = None):
        """(model, renderer) untrained, at the trained model's code widths (:meth:`code_widths`) unless given:
        a finished run's training files need not be at hand."""
        return super().build_model(device, code_widths or self.code_widths())


def _run_config(path: Path) -> RunConfig:
    """A finished run's ``config.yaml``, its values checked as ``train.run`` checks them (not the files it names,
    which a copied run may lack): an error names the file and the key, before any model is built."""
    from train.stages.checks import check_values

    if not path.read_text(encoding="utf-8", errors="replace").strip():
        raise ToolkitError(f"{path}: empty; expected the run's config (python -m train.run writes it)")
    cfg = load_yaml_config(RunConfig, path)
    try:
        check_values(cfg)
    except ToolkitError as e:
        raise ToolkitError(f"{path}: {e}") from None
    return cfg
