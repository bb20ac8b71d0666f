"""A finished run opened for use (train.trained_run.TrainedRun), by the apps too."""

import shutil

import h5py
import pytest
import torch

from toolkit import ToolkitError
from train.trained_run import TrainedRun


def test_open_run_uses_a_run_finished_under_an_older_config(tiny_run, tmp_path, caplog):
    """A finished model must still open when its stages' fingerprints no longer match config.yaml (edited
    since, or hashed by an older toolkit whose config lacked a field), with a warning naming them."""
    import re

    d = tmp_path / "old"
    shutil.copytree(tiny_run, d)
    text = (d / "config.yaml").read_text()
    edited = re.sub(r"(?m)^  ckpt_every: (\d+)$", lambda m: f"  ckpt_every: {int(m.group(1)) + 1}", text, count=1)
    assert edited != text
    (d / "config.yaml").write_text(edited)
    ctx = TrainedRun.open(d).context
    assert ctx.path("gaussian", "checkpoint").exists()
    assert "gaussian" in caplog.text and "different config" in caplog.text


@pytest.mark.parametrize("edit, expected", [
    (lambda t: t.replace("\n  res: ", "\n  res: -5 #", 1), r"config.yaml: config key 'data.res': expected an image size"),
    (lambda t: t.replace("\n  sampling_steps: ", "\n  sampling_steps: 1000000000 #", 1),
     r"config.yaml: config key 'gaussian.sampling_steps'"),
    (lambda t: " \n", r"config.yaml: empty; expected the run's config")])
def test_a_finished_runs_config_is_checked_when_opened(tiny_run, tmp_path, edit, expected):
    """Every app opens a run through TrainedRun.open: a value train.run would refuse is named with its file and
    key there, not later by whatever first reads it."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d, ignore=shutil.ignore_patterns("data"))
    text = (d / "config.yaml").read_text()
    assert edit(text) != text
    (d / "config.yaml").write_text(edit(text))
    with pytest.raises(ToolkitError, match=expected):
        TrainedRun.open(d)


def test_redirect_app_writes_a_loadable_dataset(tiny_run, tmp_path):
    from apps import redirect
    from train.data.dataset import GazeDataset

    src = sorted((tiny_run / "data").glob("*.h5"))[-1]
    out = tmp_path / "redirected.h5"
    assert redirect.main([str(tiny_run), str(src), str(out), "--gazes", "grid:2x2:20", "--rows", "2", "--batch", "1"]) == 0
    with h5py.File(out) as f:
        assert f["face_patch"].shape[0] == 8 and f["pitchyaw_head"].shape == (8, 2)
        assert not (out.parent / "redirected.h5.parts").exists()
    ds = GazeDataset([out])
    assert len(ds) == 8
    with pytest.raises(ToolkitError, match="--gazes"):
        redirect.main([str(tiny_run), str(src), str(out), "--gazes", "spiral:3"])
    with pytest.raises(ToolkitError, match="not a run directory"):
        redirect.main([str(tmp_path), str(src), str(out)])
    from toolkit.errors import run_cli

    assert run_cli(redirect.main, [str(tiny_run), str(src), str(out), "--batch", "0"]) == 2


def test_preview_opens_a_trained_run(tiny_run, tmp_path):
    from apps.preview import load_scene
    from apps.preview_sweep import render_gaze_sweep

    scene = load_scene(str(tiny_run))
    assert scene.features.shape[1] == 3 and {1, 2} <= set(scene.part.unique().tolist())
    info = render_gaze_sweep(scene, tmp_path / "sweep.png", [0], [-20, 20], 64, 64)
    assert (tmp_path / "sweep.png").exists() and len(info["gazes"]) == 2
    with pytest.raises(ToolkitError, match=r"a trained run directory \(with config.yaml\)"):
        load_scene(str(tmp_path))


def test_a_trained_model_holding_nan_is_named_with_its_file_and_tensor(tiny_run, tmp_path):
    """A damaged final checkpoint is refused where it is read, naming the file and the tensor, instead of by the
    splatter (\"rasterize: means contains NaN\") or as a diverged test-time fit."""
    from toolkit.io import load_tensors, save_tensors

    d = tmp_path / "run"
    shutil.copytree(tiny_run, d, ignore=shutil.ignore_patterns("data"))
    run = TrainedRun.open(d)
    path = run.context.path("gaussian", "checkpoint")
    model, _ = run.load_model("cpu")  # undamaged: loads
    tensors, meta = load_tensors(path)
    key = next(k for k, v in tensors.items() if v.is_floating_point() and v.numel() > 1 and "renderer" in k)
    tensors[key] = tensors[key].clone().reshape(-1).index_fill(0, torch.tensor([0]), float("nan")).reshape(
        tensors[key].shape)
    save_tensors(path, tensors, meta)
    with pytest.raises(ToolkitError, match=r"final.safetensors: tensor 'renderer\..*' holds NaN or inf values: the "
                                           r"checkpoint is damaged"):
        run.load_model("cpu")


def test_load_model_names_a_device_torch_cannot_use(tiny_run):
    """The device argument is checked as the run's own ``device`` key is: one line, not torch's list of device
    types or an assertion from torch.cuda."""
    run = TrainedRun.open(tiny_run)
    with pytest.raises(ToolkitError, match=r"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got 'bogus'"):
        run.load_model("bogus")
    if not torch.cuda.is_available():
        with pytest.raises(ToolkitError, match=r"device=cuda but CUDA is not available; use device=cpu or device=auto"):
            run.load_model("cuda")


def test_row_fitter_checks_the_row_the_gazes_and_the_steps(tiny_run):
    """A row at another resolution, holding NaN or lacking keys, gazes of the wrong shape, dtype or values, and a
    negative step count are named up front, instead of a size mismatch deep in the loss, a NaN code, a splatter
    error or the unfitted code returned."""
    from train.data.dataset import GazeDataset
    from train.evaluation.fitting import restored_weights

    run = TrainedRun.open(tiny_run)
    model, renderer = run.load_model("cpu")
    res = run.config.data.res
    item = GazeDataset(run.split("test"), res=res)[0]
    with pytest.raises(ToolkitError, match=r"row_fitter steps: expected an integer >= 0 .*got -1"):
        run.row_fitter(model, renderer, "cpu", steps=-1)
    fit = run.row_fitter(model, renderer, "cpu", steps=0, gaze_term=False)
    gazes = torch.zeros(1, 2)
    small = {**item, "image": item["image"][:, : res // 2, : res // 2]}
    with pytest.raises(ToolkitError, match=rf"row fit item\['image'\]: expected shape \[3, {res}, {res}\] \(the run's "
                                           rf"data.res = {res}\), got \[3, {res // 2}, {res // 2}\]"):
        fit(small, gazes)
    with pytest.raises(ToolkitError, match=r"row fit item\['image'\]: expected finite values, found NaN or inf"):
        fit({**item, "image": torch.full_like(item["image"], float("nan"))}, gazes)
    with pytest.raises(ToolkitError, match=r"row fit item: missing key\(s\) \['head_mask'"):
        fit({k: v for k, v in item.items() if k != "head_mask"}, gazes)
    for bad, match in ((torch.zeros(2), r"expected \[G >= 1, 2\] \(pitch, yaw\), got \[2\]"),
                       (torch.zeros(1, 2, dtype=torch.long), r"expected a floating-point tensor"),
                       (torch.full((1, 2), float("nan")), r"expected finite values, found NaN or inf")):
        with pytest.raises(ToolkitError, match=r"row fit gazes: " + match):
            fit(item, bad)
    # float64 gazes are read as float32 (the gaze term's estimator compares them with its float32 output)
    assert run.fit_gaze_term("cpu") is not None
    fit = run.row_fitter(model, renderer, "cpu", steps=1)
    with restored_weights(model, renderer):
        torch.manual_seed(0)
        wide = fit(item, torch.tensor([[0.1, -0.2]], dtype=torch.float64))
    with restored_weights(model, renderer):
        torch.manual_seed(0)
        assert torch.equal(wide, fit(item, torch.tensor([[0.1, -0.2]])))
