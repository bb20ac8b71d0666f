"""Stage estimator: the two estimators trained at once equal those trained in turn, and its warnings."""

import json
import shutil

import torch

import train.stages.estimator as estimator_stage
from train.trained_run import TrainedRun


def _estimator_stage(run_dir, threads: int, **estimator) -> tuple[dict, list[str]]:
    """Run stage estimator on ``run_dir`` with ``threads`` torch threads (and estimator-section overrides);
    returns its outputs and log lines."""
    ctx = TrainedRun.open(run_dir).context
    for k, v in estimator.items():
        setattr(ctx.config.estimator, k, v)
    lines = []
    ctx.log = lines.append
    torch.set_num_threads(threads)
    try:
        return estimator_stage.stage_estimator(ctx), lines
    finally:
        torch.set_num_threads(1)


def test_estimators_trained_at_once_equal_those_trained_in_turn(tiny_run, tmp_path):
    """With 2 CPU threads the stage trains both estimators at once, one process and thread each: the weights
    must be exactly those of the 1-thread run that trained them in turn (the fixture), and the summary too."""
    from safetensors.torch import load_file

    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    for role in ("loss", "eval"):
        (d / f"estimator_{role}.safetensors").unlink()
    (d / "estimators.json").unlink()
    outs, lines = _estimator_stage(d, threads=2)
    assert any("2 processes, 1 + 1 threads" in s for s in lines)
    # The tiny preset's 4-step estimators read far off: the stage says so, for each of them.
    assert sum("WARNING" in s and "training failed or was too short" in s for s in lines) == 2
    assert outs == {"loss": "estimator_loss.safetensors", "eval": "estimator_eval.safetensors",
                    "summary": "estimators.json"}
    for role in ("loss", "eval"):
        a, b = load_file(tiny_run / outs[role]), load_file(d / outs[role])
        assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a), role
    assert json.loads((d / "estimators.json").read_text()) == json.loads((tiny_run / "estimators.json").read_text())


def test_estimator_stage_warns_only_about_a_failed_estimator(tiny_run, tmp_path, monkeypatch):
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    readings = {"loss": 4.2, "eval": 87.0}

    def fake_train(*, role, run_dir, **kw):
        return f"estimator_{role}.safetensors", {"train_images": 18, "val_gaze_deg": readings[role]}

    monkeypatch.setattr(estimator_stage, "_train_estimator", fake_train)
    outs, lines = _estimator_stage(d, threads=1)
    warnings = [s for s in lines if "WARNING" in s]
    assert len(warnings) == 1 and "eval estimator reads held-out gazes 87.0 deg off" in warnings[0]


def test_estimators_at_once_with_render_workers_of_their_own(tiny_run, tmp_path):
    """With 4 threads each estimator's process gets 2, and renders its extra subjects with 2 processes of its
    own: the stage's processes must be allowed children."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    outs, lines = _estimator_stage(d, threads=4, synthetic_subjects=2)
    assert any("2 processes, 2 + 2 threads" in s for s in lines)
    est = json.loads((d / outs["summary"]).read_text())
    assert est["loss"]["train_images"] == est["eval"]["train_images"] == 18 + 2 * 2 * 2


def test_estimator_data_read_by_rows_equals_the_splits_in_memory(tiny_run):
    """The stage's images are read from the subject files when a batch indexes them: every index gives the
    tensors the whole splits in memory gave (uint8 images, labels, landmarks), the extra subjects after them."""
    from train.data.rows import RowImages
    from train.training.trainer import load_split

    run = TrainedRun.open(tiny_run)
    files = run.split("train"), run.split("test")
    res = run.config.data.res
    images, labels, lms, val = estimator_stage._estimator_data(run.config, *files, workers=2)
    try:
        to_u8 = lambda x: (x * 255).round().clamp(0, 255).to(torch.uint8)  # noqa: E731
        for (im, lab, lm), f in zip(((images, labels, lms), val), files):
            d = load_split(f, "all", res)
            assert isinstance(im, RowImages) and im.shape == d.image.shape and im.dtype == torch.uint8
            assert torch.equal(lab, torch.cat([d.gaze_cam, d.head_pose_cam], 1)) and torch.equal(lm, d.landmarks)
            idx = torch.randint(0, len(d), (2 * len(d),), generator=torch.Generator().manual_seed(0))
            assert torch.equal(im[idx], to_u8(d.image)[idx]) and torch.equal(im[0:len(d)], to_u8(d.image))
        extra = torch.randint(0, 256, (2, 3, res, res), dtype=torch.uint8)
        both = images.cat(extra)
        assert len(both) == len(images) + 2 and torch.equal(both[torch.tensor([len(images) + 1, 0])][0], extra[1])
    finally:
        estimator_stage._close_data((images, labels, lms, val))
