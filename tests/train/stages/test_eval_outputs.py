"""The eval stage's outputs on a re-run: refused before the evaluation when one cannot be written, and never left
half new (a failure while making them keeps the previous evaluation's whole set)."""

import hashlib
import shutil
from pathlib import Path

import pytest
import torch

from toolkit import ToolkitError
from train.config import apply_overrides, load_yaml_config
from train.evaluation.report import EVAL_OUTPUTS
from train.run_config import RunConfig
from train.stages import STAGES
from train.stages.pipeline import RunContext, run_stages

RERUN = ["eval.pairs_per_subject=1", "eval.tta_steps=0"]  # another eval config: the stage runs again, briefly


def _files(run: Path) -> dict[str, str]:
    return {str(p.relative_to(run)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(run.rglob("*")) if p.is_file()}


def _rerun_eval(run: Path) -> dict[str, str]:
    cfg = apply_overrides(load_yaml_config(RunConfig, run / "config.yaml"), RERUN)
    return run_stages(STAGES, ["eval"], RunContext(run, cfg, log=lambda m: None))


@pytest.mark.parametrize("name", EVAL_OUTPUTS)
def test_an_eval_output_that_is_a_directory_is_refused_before_the_evaluation(tiny_run, tmp_path, monkeypatch, name):
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    (d / name).unlink(missing_ok=True)
    (d / name).mkdir()
    before = _files(d)

    def no_evaluation(*a, **k):
        raise AssertionError("the evaluation started before its outputs were checked")

    monkeypatch.setattr("train.stages.eval.RunArtifacts", no_evaluation)
    with pytest.raises(ToolkitError, match=rf"{name}: is a directory, expected a file path to write"):
        _rerun_eval(d)
    assert _files(d) == before and (d / name).is_dir()


def test_a_failure_while_making_the_eval_outputs_leaves_the_previous_set(tiny_run, tmp_path, monkeypatch):
    """The qualitative figure's sweep fails after the evaluation: metrics.json, report.md, the figures and the
    stage's record are all still the previous evaluation's."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    before = _files(d)

    def failing_sweep(*a, **k):
        raise RuntimeError("the sweep failed")

    monkeypatch.setattr("train.stages.eval._eval_sweep", failing_sweep)
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with pytest.raises(RuntimeError, match="the sweep failed"):
            _rerun_eval(d)
    finally:
        torch.set_num_threads(old)
    after = _files(d)
    for name in [*EVAL_OUTPUTS, "stages/eval.json"]:
        assert after.get(name) == before.get(name), name
