"""geometry.pretrain_fields: the face deformation and eye rotation fields pre-trained in the geometry stage and the
Gaussian stage starting from them; with gaussian.region_renders=separate, a few steps end to end on the tiny preset."""

import json
import shutil

import pytest
import torch

from toolkit import ToolkitError
from train import run
from train.stages.field_pretrain import (
    load_fields,
    pretrain_fields,
    pretrain_terms,
    pretrained_modules,
    project,
    save_fields,
)
from train.trained_run import TrainedRun


def _fresh(run_dir, **gaussian):
    """The tiny run's model as the Gaussian stage builds it (seed 0), the training split, the run."""
    from train.training.trainer import open_split

    tr = TrainedRun.open(run_dir)
    for k, v in gaussian.items():
        setattr(tr.config.gaussian, k, v)
    torch.manual_seed(0)
    model, _ = tr.build_model("cpu")
    return model, open_split(tr.split("train"), "all", tr.config.data.res), tr


def _field_state(model) -> dict[str, torch.Tensor]:
    return {f"{n}.{k}": v.detach().clone() for n, m in pretrained_modules(model).items()
            for k, v in m.state_dict().items()}


def test_pretraining_lowers_its_loss_and_the_saved_fields_load_exactly(tiny_run, tmp_path):
    model, data, _ = _fresh(tiny_run)
    fresh = _field_state(model)
    other = {k: v.detach().clone() for k, v in model.state_dict().items() if not k.startswith(("face_field", "eye_field"))}
    try:
        result = pretrain_fields(model, data, steps=8, seed=0)
    finally:
        data.close()
    assert result["after"]["total"] < result["before"]["total"]
    trained = _field_state(model)
    assert any(not torch.equal(fresh[k], trained[k]) for k in fresh if k.startswith("face_field"))
    assert any(not torch.equal(fresh[k], trained[k]) for k in fresh if k.startswith("eye_field"))
    # only the fields trained; every weight trains again afterwards
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in other.items())
    assert all(p.requires_grad for p in model.parameters())
    path = tmp_path / "fields.safetensors"
    save_fields(model, path, result)
    again, data, _ = _fresh(tiny_run)
    data.close()
    assert sorted(load_fields(again, path)) == ["eye_field", "face_field"]
    assert all(torch.equal(v, _field_state(again)[k]) for k, v in trained.items())
    # a model with fields of another shape (gaussian.gaussians_hidden changed) is refused, naming the file
    wider, data, _ = _fresh(tiny_run, gaussians_hidden=8)
    data.close()
    with pytest.raises(ToolkitError, match=r"fields.safetensors: face_field does not fit the model"):
        load_fields(wider, path)


def test_the_pretraining_terms_are_finite_under_stress(tiny_run):
    """Codes far outside the data's range, a pose turning the head away, landmarks behind the camera and an empty
    head mask: finite terms and finite gradients."""
    model, data, _ = _fresh(tiny_run)
    try:
        b = data.take(torch.arange(2), "cpu")
    finally:
        data.close()
    b["code"] = b["code"] * 1e3
    b["pose"] = b["pose"] + torch.tensor([3.0, -2.0, 1.0, 0.0, 0.0, 0.0])
    b["head"] = torch.zeros_like(b["head"])
    from train.stages.field_pretrain import landmark_weights

    terms = pretrain_terms(model, b, landmark_weights(model))
    terms["total"].backward()
    assert all(torch.isfinite(v) for v in terms.values())
    grads = [p.grad for m in pretrained_modules(model).values() for p in m.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    behind = project(torch.tensor([[[0.0, 0.0, -10.0]]]), torch.zeros(1, 6), torch.eye(4)[None], torch.eye(3)[None])
    assert torch.isfinite(behind).all()


def test_both_switches_train_end_to_end_and_the_gaussian_stage_starts_from_the_pretrained_fields(tiny_run, tmp_path,
                                                                                                monkeypatch):
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    over = ["geometry.pretrain_fields=4", "gaussian.region_renders=separate", "gaussian.steps=2"]
    assert run.main(["--preset", "tiny", "--run-dir", str(d), "--stages", "geometry,gaussian", *over]) == 0
    saved = d / "geometry" / "fields.safetensors"
    info = json.loads((d / "stages" / "geometry.json").read_text())
    assert info["outputs"]["fields"] == "geometry/fields.safetensors" and saved.exists()
    logged = [json.loads(line) for line in (d / "metrics.jsonl").read_text().splitlines()]
    last = [r for r in logged if r["stage"] == "gaussian"][-1]
    assert {"rgb_face", "rgb_eyes", "diffusion_face", "diffusion_eyes"} <= set(last)
    assert all(v == v and abs(v) < float("inf") for k, v in last.items() if k not in ("stage", "time"))
    # The Gaussian stage's model, when its loop starts, holds the saved fields (not a fresh init).
    seen = {}

    class Started(Exception):
        pass

    def first_step(name, step_fn, modules, **kw):  # noqa: ARG001
        seen.update(_field_state(modules["model"]))
        raise Started

    monkeypatch.setattr("train.training.loop.train_loop", first_step)
    with pytest.raises(Started):
        run.main(["--preset", "tiny", "--run-dir", str(d), "--stages", "gaussian", "--force", "gaussian", *over])
    from toolkit.io import load_checkpoint

    state, _ = load_checkpoint(saved)
    fresh, data, _ = _fresh(tiny_run)
    data.close()
    assert sorted(seen) == sorted(state) and all(torch.equal(seen[k], state[k]) for k in state)
    assert any(not torch.equal(_field_state(fresh)[k], state[k]) for k in state)


@pytest.mark.parametrize("override,expected", [
    ("geometry.pretrain_fields=-1", "expected a step count >= 0, got -1"),
    ("geometry.pretrain_fields=1.5", "expected an integer, got 1.5"),
    ("geometry.pretrain_fields=20000000", "expected at most 10000000 steps"),
    ("gaussian.region_renders=both", "expected one of ['masks', 'separate'], got 'both'"),
])
def test_bad_values_of_the_switches_are_one_line_naming_the_key(override, expected):
    from train.config import apply_overrides
    from train.presets import preset

    with pytest.raises(ToolkitError) as err:
        apply_overrides(preset("tiny"), [override])
    key = override.split("=")[0]
    assert str(err.value).startswith(f"config key '{key}': {expected}") and "\n" not in str(err.value)


def test_the_paper_preset_turns_both_switches_on_and_the_others_leave_them_off():
    from train.presets import preset

    assert preset("paper").geometry.pretrain_fields > 0 and preset("paper").gaussian.region_renders == "separate"
    for name in ("demo", "tiny"):
        assert preset(name).geometry.pretrain_fields == 0 and preset(name).gaussian.region_renders == "masks"
