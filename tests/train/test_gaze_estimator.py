"""Gaze estimator: shapes, differentiability, checkpoints (round trip and clear errors), trainer."""

from __future__ import annotations

import math

import pytest
import torch

from toolkit.errors import ToolkitError
from toolkit.io import save_checkpoint
from toolkit.rotations import angular_error_deg
from train.drawn_faces import draw_faces, drawn_face_dataset
from train.gaze_estimator import (
    EYE_BAND,
    GazeEstimator,
    GazeEstimatorConfig,
    GazeEstimatorTrainConfig,
    evaluate_gaze_estimator,
    train_gaze_estimator,
)

TINY = GazeEstimatorConfig(input_size=32, channels=(8, 16, 16), hidden=32)


def test_forward_shapes_any_input_size_and_gradient_to_the_image():
    model = GazeEstimator(TINY)
    for hw in ((32, 32), (48, 40), (20, 20)):
        x = torch.rand(3, 3, *hw, requires_grad=True)
        y = model(x)
        assert y.shape == (3, 4) and torch.isfinite(y).all()
        y.sum().backward()
        assert torch.isfinite(x.grad).all() and float(x.grad.abs().sum()) > 0
    assert model.gaze(torch.rand(2, 3, 32, 32)).shape == (2, 2)
    with pytest.raises(ToolkitError, match="images"):
        model(torch.rand(2, 1, 32, 32))


def test_crop_sees_only_the_band_and_round_trips(tmp_path):
    cfg = GazeEstimatorConfig(input_size=32, channels=(8, 16), hidden=16, crop=EYE_BAND)
    model = GazeEstimator(cfg).eval()
    top, bottom, left, right = EYE_BAND
    assert model.input_hw == (round(32 * (bottom - top) / (right - left)), 32)
    x = torch.rand(2, 3, 128, 128, requires_grad=True)
    model(x).sum().backward()
    touched = x.grad.abs().sum((0, 1)) > 0
    rows, cols = touched.any(1).nonzero().squeeze(1), touched.any(0).nonzero().squeeze(1)
    # Gradient reaches exactly the cropped rows/columns (bilinear resizing stays inside the band).
    assert int(rows.min()) == round(top * 128) and int(rows.max()) == round(bottom * 128) - 1
    assert int(cols.min()) == round(left * 128) and int(cols.max()) == round(right * 128) - 1
    model.save(tmp_path / "band.safetensors")
    back = GazeEstimator.load(tmp_path / "band.safetensors")
    assert back.config == cfg and torch.equal(back(x.detach()), model(x.detach()))
    for bad in ((0.5, 0.4, 0.0, 1.0), (0.0, 1.0, -0.1, 1.0), (0.0, 1.2, 0.0, 1.0)):
        with pytest.raises(ToolkitError, match="crop"):
            GazeEstimator(GazeEstimatorConfig(input_size=32, channels=(8,), crop=bad))


def test_checkpoint_round_trip_is_exact_and_frozen(tmp_path):
    torch.manual_seed(1)
    model = GazeEstimator(TINY).eval()
    path = tmp_path / "est.safetensors"
    model.save(path, {"note": "test"})
    back = GazeEstimator.load(path)
    x = torch.rand(2, 3, 32, 32)
    assert torch.equal(model(x), back(x))
    assert back.config == TINY and not back.training
    assert not any(p.requires_grad for p in back.parameters())
    assert any(p.requires_grad for p in GazeEstimator.load(path, frozen=False).parameters())


def test_checkpoint_errors_are_clear(tmp_path):
    with pytest.raises(ToolkitError, match="no such"):
        GazeEstimator.load(tmp_path / "missing.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"garbage")
    with pytest.raises(ToolkitError, match="not a valid safetensors"):
        GazeEstimator.load(tmp_path / "junk.safetensors")
    model = GazeEstimator(TINY)
    save_checkpoint(tmp_path / "other.safetensors", model.state_dict(), {"kind": "something.else"})
    with pytest.raises(ToolkitError, match="not a gaze estimator"):
        GazeEstimator.load(tmp_path / "other.safetensors")
    state = model.state_dict()
    info = {"kind": "ditgaze.gaze_estimator", "version": 1,
            "config": {"input_size": 32, "channels": [8, 16, 32], "hidden": 32, "dropout": 0.0}}
    save_checkpoint(tmp_path / "mismatch.safetensors", state, info)
    with pytest.raises(ToolkitError, match="shape"):
        GazeEstimator.load(tmp_path / "mismatch.safetensors")
    info["config"]["channels"] = [8, 16, 16]
    info["version"] = 99
    save_checkpoint(tmp_path / "future.safetensors", state, info)
    with pytest.raises(ToolkitError, match="version"):
        GazeEstimator.load(tmp_path / "future.safetensors")
    info["version"] = 1
    info["config"]["bogus"] = 1
    save_checkpoint(tmp_path / "bogus.safetensors", state, info)
    with pytest.raises(ToolkitError, match="bogus"):
        GazeEstimator.load(tmp_path / "bogus.safetensors")


def test_drawn_faces_follow_the_gaze_label():
    sid = torch.zeros(2, dtype=torch.long)
    head = torch.zeros(2, 2)
    left = draw_faces(64, sid, torch.tensor([[0.0, 0.5], [0.0, -0.5]]), head, n_subjects=1)
    # Positive yaw looks towards the image's -x: the dark pupil moves left.
    d = left[0].mean(0) - left[1].mean(0)  # < 0 where image 0 is darker (its iris), > 0 where image 1's is
    cols = torch.arange(64.0)
    x0 = float(((-d).clamp_min(0).sum(0) * cols).sum() / (-d).clamp_min(0).sum())
    x1 = float((d.clamp_min(0).sum(0) * cols).sum() / d.clamp_min(0).sum())
    assert x0 < x1 - 2
    with pytest.raises(ToolkitError):
        drawn_face_dataset(4, 32, n_subjects=3, subjects=[5])


def test_trainer_learns_and_is_deterministic():
    imgs, labels, _ = drawn_face_dataset(128, 32, n_subjects=4, seed=0)
    val = drawn_face_dataset(48, 32, n_subjects=4, seed=1)[:2]
    tc = GazeEstimatorTrainConfig(steps=50, batch_size=16, lr=3e-3, log_every=25, seed=3)
    before = evaluate_gaze_estimator(GazeEstimator(TINY), *val)
    model, hist = train_gaze_estimator(imgs, labels, TINY, tc, val=val)
    after = hist[-1]
    # 50 tiny steps learn the head pose (coarse layout) first; the fine iris cue needs the long runs of
    # benchmarks/gaze_estimator.py, so here gaze only has to improve on the untrained network.
    assert after["val_head_deg"] < 0.6 * before["val_head_deg"]
    assert after["val_gaze_deg"] < before["val_gaze_deg"]
    assert math.isfinite(after["loss"]) and not model.training
    short = GazeEstimatorTrainConfig(steps=3, batch_size=8, log_every=3, seed=3)
    m1, _ = train_gaze_estimator(imgs, labels, TINY, short)
    m2, _ = train_gaze_estimator(imgs, labels, TINY, short)
    for a, b in zip(m1.parameters(), m2.parameters()):
        assert torch.equal(a, b)


def test_trainer_rejects_bad_data():
    with pytest.raises(ToolkitError, match="labels"):
        train_gaze_estimator(torch.rand(4, 3, 32, 32), torch.zeros(4, 2), TINY)
    with pytest.raises(ToolkitError, match="NaN"):
        train_gaze_estimator(torch.rand(4, 3, 32, 32), torch.full((4, 4), float("nan")), TINY)
    with pytest.raises(ToolkitError, match="loss_space"):
        train_gaze_estimator(torch.rand(4, 3, 32, 32), torch.zeros(4, 4), TINY, GazeEstimatorTrainConfig(loss_space="x"))
    _, hist = train_gaze_estimator(torch.rand(8, 3, 32, 32), torch.rand(8, 4) - 0.5, TINY,
                                   GazeEstimatorTrainConfig(steps=2, batch_size=4, log_every=2, loss_space="angles"))
    assert math.isfinite(hist[-1]["loss"])
    with pytest.raises(ToolkitError, match="steps"):
        train_gaze_estimator(torch.rand(4, 3, 32, 32), torch.zeros(4, 4), TINY, GazeEstimatorTrainConfig(steps=0))


def test_head_frame_output_is_composed_exactly():
    from train.gaze_estimator import camera_to_head_gaze, head_to_camera_gaze

    torch.manual_seed(3)
    gh = (torch.rand(32, 2) * 2 - 1) * 0.8
    hp = (torch.rand(32, 2) * 2 - 1) * 1.2
    back = camera_to_head_gaze(head_to_camera_gaze(gh, hp), hp)
    assert float(angular_error_deg(back, gh).max()) < 1e-2
    torch.testing.assert_close(head_to_camera_gaze(gh, torch.zeros_like(hp)), gh, atol=1e-5, rtol=0)
    model = GazeEstimator(TINY).eval()
    x = torch.rand(4, 3, 32, 32)
    parts, out = model.forward_parts(x), model(x)
    torch.testing.assert_close(out[:, 2:], parts[:, 2:])
    torch.testing.assert_close(out[:, :2], head_to_camera_gaze(parts[:, :2], parts[:, 2:]))
    direct = GazeEstimator(GazeEstimatorConfig(input_size=32, channels=(8, 16, 16), hidden=32, head_frame=False)).eval()
    assert torch.equal(direct(x), direct.forward_parts(x))
