"""The Gaussian stage with the paper-form field switches (``gaussian.field_input``, ``gaussian.eye_field_terms``):
trained end to end on the tiny preset, saved and reloaded; the presets that set them; their config errors."""

import json
import math
import shutil

import pytest

from toolkit import ToolkitError
from train import run
from train.config import apply_overrides
from train.presets import preset
from train.trained_run import TrainedRun


@pytest.mark.parametrize("switch,trained", [("gaussian.field_input=feature", "face_field.expr_attr_mlp"),
                                            ("gaussian.eye_field_terms=true", "eye_gaze_terms.mlp")],
                         ids=["feature_input", "eye_terms"])
def test_each_switch_trains_saves_and_reloads(tiny_run, tmp_path, switch, trained):
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    over = [switch, "gaussian.steps=2", "gaussian.log_every=1", "gaussian.ckpt_every=2"]
    assert run.main(["--preset", "tiny", "--run-dir", str(d), "--stages", "gaussian", *over]) == 0
    rows = [json.loads(line) for line in (d / "metrics.jsonl").read_text().splitlines()]
    rows = [r for r in rows if r.get("stage") == "gaussian" and r.get("step", 0) >= 1 and "total" in r]
    assert len(rows) >= 2 and all(math.isfinite(r["total"]) and math.isfinite(r["image"]) for r in rows[-2:])
    model, _ = TrainedRun.open(d).load_model("cpu")
    key, value = switch.removeprefix("gaussian.").split("=")
    assert str(getattr(model.config, key)).lower() == value
    last = dict(model.named_parameters())[f"{trained}.last.weight"]
    assert float(last.detach().abs().max()) > 0  # trained away from its zero start


def test_the_paper_preset_selects_the_papers_form_and_the_others_keep_the_default():
    assert preset("paper").gaussian.field_input == "feature" and preset("paper").gaussian.eye_field_terms
    for name in ("demo", "tiny"):
        g = preset(name).gaussian
        assert g.field_input == "position" and not g.eye_field_terms, name


def test_a_bad_field_input_names_the_key():
    with pytest.raises(ToolkitError, match=r"'gaussian.field_input': expected one of \['position', 'feature'\]"):
        apply_overrides(preset("tiny"), ["gaussian.field_input=z0"])
    with pytest.raises(ToolkitError, match=r"'gaussian.eye_field_terms': expected true/false"):
        apply_overrides(preset("tiny"), ["gaussian.eye_field_terms=3"])


def test_the_switches_reach_the_model_config():
    from train.training.trainer import model_config

    cfg = apply_overrides(preset("tiny"), ["gaussian.field_input=feature", "gaussian.eye_field_terms=true"])
    mc = model_config(cfg.gaussian)
    assert mc.field_input == "feature" and mc.eye_field_terms
