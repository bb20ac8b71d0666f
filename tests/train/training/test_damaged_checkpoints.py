"""Damaged, forged or misplaced checkpoints and metrics logs: each is one ToolkitError naming the file (or a
skipped checkpoint, said so), before any step, with nothing of the user's deleted."""

import json
import shutil
from types import SimpleNamespace

import pytest
import torch

from toolkit import ToolkitError
from toolkit.io import load_tensors, save_tensors
from train.stages.gaussian import resume_step
from train.training.checkpoint import CheckpointManager, checkpoint_metadata, load_training_checkpoint
from train.training.loop import MetricsLogger, train_loop


def _problem(seed=0):
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1))
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    calls = []

    def step_fn(step, g):
        calls.append(step)
        x = torch.randn(8, 4, generator=g)
        loss = (model(x).squeeze(-1) - x.sum(-1)).pow(2).mean()
        return {"total": loss}

    return model, opt, step_fn, calls


def _run(run_dir, steps=20, resume=False, log=None):
    """A small run in ``run_dir`` (checkpoints every 10 steps); returns its model and the steps it trained."""
    model, opt, f, calls = _problem(seed=1)
    train_loop("t", f, modules={"m": model}, optimizers={"o": opt}, steps=steps, run_dir=run_dir, ckpt_every=10,
               progress=False, resume=resume, log=log)
    return model, calls


def _files(folder):
    return {p.name: (p.read_bytes() if p.is_file() else "dir") for p in sorted(folder.iterdir())}


def _gaussian_ctx(run_dir, resume=True, ema_decay=0.0):
    """What :func:`train.stages.gaussian.resume_step` reads of a run context: the checkpoints sit where the
    Gaussian stage keeps them (``run_dir/gaussian/checkpoints``)."""
    return SimpleNamespace(run_dir=run_dir, resume=resume, config=SimpleNamespace(gaussian=SimpleNamespace(
        ema_decay=ema_decay)))


@pytest.fixture
def finished(tmp_path):
    """A finished 20-step run laid out as the Gaussian stage's: checkpoints at steps 10 and 20."""
    stage = tmp_path / "gaussian"
    _run(stage)
    return tmp_path, CheckpointManager(stage / "checkpoints")


def test_a_copy_under_another_steps_name_is_refused_naming_both_steps(finished):
    run_dir, mgr = finished
    assert resume_step(_gaussian_ctx(run_dir)) == 20  # the step the checkpoint records
    shutil.copy(mgr.path_for(20), mgr.folder / "ckpt_99999999.safetensors")
    before = _files(mgr.folder)
    message = r"ckpt_99999999\.safetensors: its name says step 99999999 but its metadata records step 20"
    with pytest.raises(ToolkitError, match=message):
        resume_step(_gaussian_ctx(run_dir))
    with pytest.raises(ToolkitError, match=message):
        _run(run_dir / "gaussian", steps=30, resume=True)
    assert _files(mgr.folder) == before


def _rewrite_metadata(path, field, value):
    tensors, meta = load_tensors(path)
    meta[field] = value
    save_tensors(path, tensors, meta)


BAD_METADATA = [("extra", None, "extra"), ("extra", [1], "extra"), ("step", "abc", "step"), ("step", None, "step"),
                ("step", -1, "step"), ("step", 2.5, "step"), ("modules", "m", "modules"), ("optim", [], "optim"),
                ("optim", {"optim/o": {"param_groups": 1, "scalars": {}}}, "optim"), ("rng", "x", "rng"),
                ("rng", {"python": [3, [1, 2], None], "numpy": []}, "rng"),
                ("rng", {"python": 1, "numpy": ["MT19937", "abc", 0, 0, 0.0]}, "rng")]


@pytest.mark.parametrize("field,value,named", BAD_METADATA)
def test_metadata_of_the_wrong_type_is_one_line_naming_the_file_and_the_field(finished, field, value, named):
    run_dir, mgr = finished
    newest = mgr.path_for(20)
    _rewrite_metadata(newest, field, value)
    model, opt, _, _ = _problem(seed=5)
    weights = [p.detach().clone() for p in model.parameters()]
    message = rf"ckpt_00000020\.safetensors: metadata '{named}' must be"
    with pytest.raises(ToolkitError, match=message) as e:
        load_training_checkpoint(newest, modules={"m": model}, optimizers={"o": opt})
    assert "\n" not in str(e.value)
    assert all(torch.equal(a, b) for a, b in zip(weights, model.parameters()))  # refused before loading
    with pytest.raises(ToolkitError, match=message):
        checkpoint_metadata(newest)
    # A resume passes over it as over a truncated one, saying so, and resumes from the one before.
    assert resume_step(_gaussian_ctx(run_dir)) == 10
    lines = []
    _, calls = _run(run_dir / "gaussian", steps=20, resume=True, log=lines.append)
    assert calls == list(range(10, 20))
    assert lines == ["[t] skipped unreadable checkpoint(s) ['ckpt_00000020.safetensors']; resuming from "
                     "ckpt_00000010.safetensors"]


def test_a_resume_with_every_checkpoint_unreadable_is_refused_and_deletes_nothing(finished):
    run_dir, mgr = finished
    for p in mgr.all():
        p.write_bytes(b"garbage" * 10)
    before = _files(mgr.folder)
    message = r"checkpoints: none of its checkpoints can be read \(ckpt_00000010.safetensors, " \
              r"ckpt_00000020.safetensors; .*remove them to train the stage afresh, or rerun without --resume"
    with pytest.raises(ToolkitError, match=message):
        resume_step(_gaussian_ctx(run_dir))
    model, opt, f, calls = _problem()
    with pytest.raises(ToolkitError, match=message):
        train_loop("t", f, modules={"m": model}, optimizers={"o": opt}, steps=20, run_dir=run_dir / "gaussian",
                   ckpt_every=10, progress=False, resume=True)
    assert calls == [] and _files(mgr.folder) == before


def test_a_resume_without_checkpoints_starts_at_step_zero(tmp_path):
    assert resume_step(_gaussian_ctx(tmp_path)) == 0
    (tmp_path / "gaussian" / "checkpoints").mkdir(parents=True)
    _, calls = _run(tmp_path / "gaussian", steps=3, resume=True)
    assert calls == [0, 1, 2]


@pytest.mark.parametrize("resume", [True, False])
def test_a_directory_under_a_checkpoints_name_is_refused_before_any_step(finished, resume):
    run_dir, mgr = finished
    newest = mgr.path_for(20)
    newest.unlink()
    newest.mkdir()
    before = _files(mgr.folder)
    message = r"ckpt_00000020\.safetensors: is a directory, expected a checkpoint file"
    with pytest.raises(ToolkitError, match=message):
        resume_step(_gaussian_ctx(run_dir, resume=resume))
    model, opt, f, calls = _problem()
    with pytest.raises(ToolkitError, match=message):
        train_loop("t", f, modules={"m": model}, optimizers={"o": opt}, steps=40, run_dir=run_dir / "gaussian",
                   ckpt_every=10, progress=False, resume=resume)
    assert calls == [] and _files(mgr.folder) == before


def test_a_checkpoint_gone_since_the_listing_is_no_refusal(finished, monkeypatch):
    """Under torchrun the main rank clears the folder for a fresh run while another rank checks it: a file
    listed and then deleted is not "no regular file". A link to nothing still is."""
    from train.training.checkpoint import CheckpointManager

    _, mgr = finished
    listed = mgr.all()
    for p in listed:
        p.unlink()
    monkeypatch.setattr(CheckpointManager, "all", lambda self: listed)
    mgr.check_files()
    listed[0].symlink_to(mgr.folder / "nowhere")
    with pytest.raises(ToolkitError, match=r"is a broken link, expected a checkpoint file"):
        mgr.check_files()


def test_undecodable_lines_of_the_metrics_log_are_kept_like_other_garbage(tmp_path):
    ml = MetricsLogger(tmp_path, tensorboard=False)
    for step in (1, 2, 3):
        ml.log("t", step, {"x": 1.0})
    records = (tmp_path / "metrics.jsonl").read_bytes().splitlines(keepends=True)
    garbage = b"\xff\xfe\x00binary\x80\n"
    (tmp_path / "metrics.jsonl").write_bytes(records[0] + garbage + b"[" * 100_000 + b"\n" + records[1] + records[2]
                                             + b"\x80torn")
    ml.start("t", 1)
    assert (tmp_path / "metrics.jsonl").read_bytes() == records[0] + garbage + b"[" * 100_000 + b"\n"
    ml.log("t", 2, {"x": 2.0})
    assert json.loads((tmp_path / "metrics.jsonl").read_bytes().splitlines()[-1])["step"] == 2


def test_a_metrics_log_that_is_a_directory_is_one_line(tmp_path):
    (tmp_path / "metrics.jsonl").mkdir()
    with pytest.raises(ToolkitError, match=r"metrics\.jsonl: cannot read the metrics log"):
        MetricsLogger(tmp_path, tensorboard=False).start("t", 0)
    assert (tmp_path / "metrics.jsonl").is_dir()
