"""Gaze estimator: shapes, differentiability, checkpoints (round trip and clear errors), trainer."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from toolkit.errors import ToolkitError
from toolkit.io import save_checkpoint
from toolkit.rotations import angular_error_deg
from train.estimator.augment import random_blur
from train.estimator.config import EYE_BAND, GazeEstimatorConfig, GazeEstimatorTrainConfig
from train.estimator.drawn_faces import draw_faces, drawn_face_dataset
from train.estimator.network import GazeEstimator
from train.estimator.training import evaluate_gaze_estimator, train_gaze_estimator

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
    with torch.no_grad():
        next(model.parameters()).fill_(float("nan"))
    model.save(tmp_path / "nan.safetensors")
    with pytest.raises(ToolkitError, match=r"nan\.safetensors: tensor '.*' holds NaN or inf"):
        GazeEstimator.load(tmp_path / "nan.safetensors")


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
    seen = []
    model, hist = train_gaze_estimator(imgs, labels, TINY, tc, val=val, callback=lambda step, rec: seen.append(rec))
    after = hist[-1]
    # The callback gets each record plus the evaluation's wall time, which the deterministic history leaves out.
    assert [r["step"] for r in seen] == [25, 50] and all(r["val_s"] > 0 for r in seen)
    assert [{k: v for k, v in r.items() if k != "val_s"} for r in seen] == hist and "val_s" not in after
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


def test_trainer_fine_tunes_from_init_weights():
    imgs, labels, _ = drawn_face_dataset(64, 32, n_subjects=2, seed=0)
    base, _ = train_gaze_estimator(imgs, labels, TINY, GazeEstimatorTrainConfig(steps=5, batch_size=8, seed=1))
    # A vanishing rate keeps the init's weights (AdamW's decay is scaled by the rate too): they were used.
    tc = GazeEstimatorTrainConfig(steps=2, batch_size=8, lr=1e-12, seed=2)
    tuned, _ = train_gaze_estimator(imgs, labels, TINY, tc, init=base)
    fresh, _ = train_gaze_estimator(imgs, labels, TINY, tc)
    for a, b in zip(tuned.parameters(), base.parameters()):
        torch.testing.assert_close(a, b)
    assert any(not torch.allclose(b, c) for b, c in zip(base.parameters(), fresh.parameters()))
    with pytest.raises(ToolkitError, match="init has configuration"):
        train_gaze_estimator(imgs, labels, dataclasses.replace(TINY, hidden=16), tc, init=base)


def test_warmup_ramps_the_first_steps_and_leaves_the_cosine_alone_without_it():
    """A freshly initialized estimator's first AdamW step moves each weight by about the rate (the update is
    m / sqrt(v) = sign(g)); a warm-up of w steps makes that step rate / w."""
    from train.estimator.training import _rate_factor

    for step in (0, 7, 99, 100, 250):  # no warm-up: the half cosine alone, as before the option existed
        assert _rate_factor(100, 0, step) == 0.5 * (1 + math.cos(math.pi * min(step, 100) / 100))
    assert _rate_factor(100, 10, 0) == pytest.approx(0.1) and _rate_factor(100, 10, 9) == pytest.approx(
        0.5 * (1 + math.cos(math.pi * 9 / 100)))
    assert _rate_factor(100, 10, 10) == _rate_factor(100, 0, 10)
    imgs, labels, _ = drawn_face_dataset(16, 32, n_subjects=2, seed=0)
    torch.manual_seed(5)
    start = GazeEstimator(TINY)
    moved = {}
    for warmup in (0, 10):
        tc = GazeEstimatorTrainConfig(steps=1, batch_size=8, lr=1e-2, weight_decay=0.0, seed=1, warmup_steps=warmup)
        model, _ = train_gaze_estimator(imgs, labels, TINY, tc, init=start)
        moved[warmup] = max(float((a - b).detach().abs().max()) for a, b in zip(model.parameters(), start.parameters()))
    assert moved[0] == pytest.approx(1e-2, rel=0.05) and moved[10] == pytest.approx(1e-3, rel=0.05)
    with pytest.raises(ToolkitError, match="warmup_steps"):
        train_gaze_estimator(imgs, labels, TINY, GazeEstimatorTrainConfig(warmup_steps=-1))


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
    with pytest.raises(ToolkitError, match="mirror"):
        train_gaze_estimator(torch.rand(4, 3, 32, 32), torch.zeros(4, 4), TINY, GazeEstimatorTrainConfig(mirror=1.5))
    for bad in ({"blur_prob": 1.5}, {"blur_prob": -0.1}, {"blur_sigma": -1.0}):
        with pytest.raises(ToolkitError, match="blur"):
            train_gaze_estimator(torch.rand(4, 3, 32, 32), torch.zeros(4, 4), TINY, GazeEstimatorTrainConfig(**bad))


def test_random_blur_keeps_mean_and_edges_and_skips_unchosen_images():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(6, 3, 24, 20, generator=g)
    assert torch.equal(random_blur(x, 0.0, 1.2, g), x) and torch.equal(random_blur(x, 1.0, 0.0, g), x)
    y = random_blur(x, 1.0, 1.5, torch.Generator().manual_seed(1))
    assert y.shape == x.shape and torch.isfinite(y).all()
    assert (y - x).abs().mean() > 0.02  # noise images lose contrast when blurred
    assert y.std() < x.std()
    const = torch.full((2, 3, 16, 16), 0.3)  # a flat image (and its replicated border) stays flat
    assert torch.allclose(random_blur(const, 1.0, 2.0, g), const, atol=1e-6)
    # A step edge: blurring spreads it symmetrically (the mean is kept away from the border).
    step = torch.zeros(1, 1, 1, 32).expand(1, 1, 8, 32).clone()
    step[..., 16:] = 1.0
    b = random_blur(step, 1.0, 2.0, torch.Generator().manual_seed(2))
    assert torch.allclose(b[..., 4:28].mean(), step[..., 4:28].mean(), atol=1e-5)
    # prob 0.5: some images of a batch are untouched, the others changed, independently per image.
    z = random_blur(x.repeat(8, 1, 1, 1), 0.5, 1.2, torch.Generator().manual_seed(3))
    same = ((z - x.repeat(8, 1, 1, 1)).flatten(1).abs().amax(1) == 0)
    assert 0 < int(same.sum()) < 48
    # Gradients flow, and extreme inputs stay finite.
    big = (torch.rand(2, 3, 16, 16) * 1e6).requires_grad_(True)
    out = random_blur(big, 1.0, 3.0, torch.Generator().manual_seed(4))
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(big.grad).all()


def _blur_every_image(images, prob, max_sigma, g):
    """random_blur's definition, run on every image (a unit impulse for the unchosen ones): the reference for
    the chosen-images-only implementation."""
    import math

    import torch.nn.functional as F

    B, C, H, W = images.shape
    sigma = torch.rand(B, generator=g) * max_sigma * (torch.rand(B, generator=g) < prob)
    r = max(1, math.ceil(3 * max_sigma))
    xs = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (xs / sigma.clamp_min(1e-3).unsqueeze(-1)) ** 2)
    k = (k / k.sum(-1, keepdim=True)).repeat_interleave(C, 0)
    x = F.pad(images.reshape(1, B * C, H, W), (r, r, r, r), mode="replicate")
    x = F.conv2d(F.conv2d(x, k.view(B * C, 1, 1, -1), groups=B * C), k.view(B * C, 1, -1, 1), groups=B * C)
    return x.reshape(B, C, H, W)


@pytest.mark.parametrize("prob", [0.0, 0.3, 0.5, 1.0])
def test_random_blur_of_the_chosen_images_equals_blurring_every_image(prob):
    x = torch.rand(16, 3, 40, 36, generator=torch.Generator().manual_seed(5))
    for seed in range(3):
        got = random_blur(x, prob, 1.2, torch.Generator().manual_seed(seed))
        want = _blur_every_image(x, prob, 1.2, torch.Generator().manual_seed(seed))
        torch.testing.assert_close(got, want, atol=1e-6, rtol=0)


def test_blurring_the_eye_patch_box_alone_gives_the_patches_of_the_whole_blurred_image():
    from train.estimator.augment import BLUR_BOX_MARGIN
    from train.estimator.crops import eye_patch_box, eye_patches

    g = torch.Generator().manual_seed(7)
    x = torch.rand(12, 3, 64, 64, generator=g)
    lm = torch.full((12, 68, 2), 32.0)
    eye = torch.tensor([[-4.0, 0.0], [-2.0, -1.0], [2.0, -1.0], [4.0, 0.0], [2.0, 1.0], [-2.0, 1.0]])
    lm[:, 36:42], lm[:, 42:48] = eye + torch.tensor([22.0, 26.0]), eye + torch.tensor([42.0, 26.0])
    lm = lm + torch.randn(lm.shape, generator=g)
    lm[:2] -= torch.tensor([20.0, 0.0])  # eyes at and beyond the image's left edge (reads clamp to the border)
    box = eye_patch_box(lm, 64, 64, margin=BLUR_BOX_MARGIN)
    y0, y1, x0, x1 = box
    assert x0 == 0 and 0 < y0 < y1 < 64  # a band of the image, cut at its edge
    whole = random_blur(x, 0.5, 1.2, torch.Generator().manual_seed(1))
    boxed = random_blur(x, 0.5, 1.2, torch.Generator().manual_seed(1), box)
    torch.testing.assert_close(boxed[:, :, y0:y1, x0:x1], whole[:, :, y0:y1, x0:x1], atol=1e-6, rtol=0)
    jittered = lm + torch.randn(lm.shape, generator=g) * 0.3  # the training's landmark noise, drawn after the blur
    torch.testing.assert_close(eye_patches(boxed, jittered), eye_patches(whole, jittered), atol=1e-6, rtol=0)
    # Outside the box nothing changed; a box outside the image is refused with its name.
    assert torch.equal(boxed[:, :, :y0], x[:, :, :y0]) and torch.equal(boxed[:, :, y1:], x[:, :, y1:])
    with pytest.raises(ToolkitError, match="box"):
        random_blur(x, 1.0, 1.2, torch.Generator().manual_seed(1), (10, 5, 0, 64))
    # Non-finite landmarks: the whole image, never an error mid-training.
    assert eye_patch_box(torch.full((1, 68, 2), float("nan")), 64, 64) == (0, 64, 0, 64)


def test_head_frame_output_is_composed_exactly():
    from toolkit.rotations import camera_to_head_gaze, head_to_camera_gaze

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
    direct = GazeEstimator(dataclasses.replace(TINY, head_frame=False)).eval()
    assert TINY.head_frame and torch.equal(direct(x), direct.forward_parts(x))


# ----------------------------------------------------------------------------- eye-patch design
def _eye_landmarks(B: int, W: int, roll: float = 0.0, scale: float = 1.0) -> torch.Tensor:
    """68 landmarks with the two eyes (36-41, 42-47) as 6-point ellipses, the rest on a ring, rolled about the centre."""
    lm = torch.zeros(B, 68, 2)
    t = torch.linspace(0, 2 * math.pi, 6 + 1)[:-1]
    eye = torch.stack([-torch.cos(t) * 6, torch.sin(t) * 2.5], -1)  # point 0 / 3 = outer / inner corner
    lm[:, 36:42] = eye + torch.tensor([-14.0, -6.0])
    lm[:, 42:48] = eye + torch.tensor([14.0, -6.0])
    other = torch.cat([torch.arange(36), torch.arange(48, 68)])
    ring = torch.linspace(0, 2 * math.pi, len(other) + 1)[:-1]
    lm[:, other] = torch.stack([torch.cos(ring) * 40, torch.sin(ring) * 45], -1)
    c, s = math.cos(roll), math.sin(roll)
    R = torch.tensor([[c, -s], [s, c]])
    return (lm * scale) @ R.T + W / 2


def _draw_eye_dots(lm: torch.Tensor, W: int) -> torch.Tensor:
    """White images with a dark Gaussian dot 2 px right of each eye's centre (in the eye's own frame)."""
    yy, xx = torch.meshgrid(torch.arange(W) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    img = torch.ones(lm.shape[0], 3, W, W)
    for sl in (slice(36, 42), slice(42, 48)):
        p = lm[:, sl]
        axis = p[:, 3] - p[:, 0]
        u = axis / axis.norm(dim=-1, keepdim=True)
        dot = p.mean(1) + 2.0 * u * axis.norm(dim=-1, keepdim=True) / 12
        d2 = (xx - dot[:, 0, None, None]) ** 2 + (yy - dot[:, 1, None, None]) ** 2
        img = img - 0.8 * torch.exp(-d2 / (2 * (axis.norm(dim=-1) / 12)[:, None, None] ** 2)).unsqueeze(1)
    return img.clamp(0, 1)


def test_eye_patches_follow_the_eyes_through_roll_and_scale():
    from train.estimator.crops import eye_patches

    W = 128
    base = _eye_landmarks(1, W)
    ref = eye_patches(_draw_eye_dots(base, W), base)
    assert ref.shape == (1, 6, 24, 36)
    for roll, scale in ((0.5, 1.0), (-0.9, 1.0), (0.0, 1.5), (0.3, 0.8)):
        lm = _eye_landmarks(1, W, roll, scale)
        got = eye_patches(_draw_eye_dots(lm, W), lm)
        assert float((got - ref).abs().mean()) < 0.01, (roll, scale)
    # The patch is not blind: the same image cut 3 px lower in the left eye moves that eye's dot.
    moved = base.clone()
    moved[:, 36:42, 1] += 3.0
    diff = (eye_patches(_draw_eye_dots(base, W), moved) - ref).abs()
    assert float(diff[:, :3].amax()) > 0.3 and float(diff[:, 3:].amax()) == 0.0


def test_eye_patches_are_differentiable_and_finite_for_degenerate_landmarks():
    from train.estimator.crops import eye_patches

    img = torch.rand(2, 3, 64, 64, requires_grad=True)
    lm = torch.full((2, 68, 2), 32.0, requires_grad=True)  # every landmark on one point: width clamps to 2 px
    out = eye_patches(img, lm)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert torch.isfinite(img.grad).all() and float(img.grad.abs().sum()) > 0 and torch.isfinite(lm.grad).all()
    far = torch.full((2, 68, 2), 1e6)  # far outside: border padding, still finite
    assert torch.isfinite(eye_patches(img.detach(), far)).all()
    with pytest.raises(ToolkitError, match="landmarks"):
        eye_patches(img, torch.zeros(2, 5, 2))


@pytest.mark.parametrize("size,patch,stages", [(128, (24, 36), 3), (64, (24, 36), 3), (256, (48, 72), 4),
                                               (512, (96, 144), 5)])
def test_eye_config_scales_the_patch_with_the_image(size, patch, stages):
    from train.estimator.config import eye_config

    cfg = eye_config(size)
    assert cfg.eyes and cfg.mirror_average and tuple(cfg.eye_patch) == patch and len(cfg.channels) == stages
    model = GazeEstimator(dataclasses.replace(cfg, hidden=16, channels=tuple(8 for _ in cfg.channels)))
    lm = _eye_landmarks(2, size, scale=size / 128)
    feats = model.blocks(model.stem(torch.zeros(2, 6, *patch)))
    assert feats.shape[2:] == (3, 5)  # the same final map at every size
    assert model(torch.rand(2, 3, size, size), lm).shape == (2, 4)
    with pytest.raises(ToolkitError, match="image size"):
        eye_config(8)


def test_eye_estimator_needs_landmarks_trains_and_round_trips(tmp_path):
    from train.estimator.config import eye_config

    cfg = dataclasses.replace(eye_config(64), channels=(8, 8, 8), hidden=16)
    lm = _eye_landmarks(8, 64, scale=0.5)
    x = _draw_eye_dots(lm, 64)
    y = (torch.rand(8, 4) - 0.5) * 0.5
    model, hist = train_gaze_estimator(x, y, cfg, GazeEstimatorTrainConfig(steps=3, batch_size=4, log_every=3,
                                                                            mirror=0.5),
                                       landmarks=lm, val=(x, y, lm))
    assert math.isfinite(hist[-1]["val_gaze_deg"])
    with pytest.raises(ToolkitError, match="landmarks"):
        model(x)
    with pytest.raises(ToolkitError, match="landmarks"):
        train_gaze_estimator(x, y, cfg, GazeEstimatorTrainConfig(steps=1, batch_size=4))
    with pytest.raises(ToolkitError, match="landmarks"):
        train_gaze_estimator(x, y, cfg, GazeEstimatorTrainConfig(steps=1, batch_size=4), landmarks=lm[:, :60])
    model.save(tmp_path / "eyes.safetensors")
    back = GazeEstimator.load(tmp_path / "eyes.safetensors")
    assert back.config.eye_patch == cfg.eye_patch and back.config.eyes
    torch.testing.assert_close(back(x, lm), model.eval()(x, lm))


def test_eye_augmentation_on_the_patches_matches_augmenting_the_image():
    """An integer shift of image and landmarks together leaves the patches as they were and moves the layout:
    augment_eye_inputs does exactly that on the small patches. Photometric jitter stays per sample."""
    from train.estimator.augment import augment_batch, augment_eye_inputs
    from train.estimator.config import eye_config

    model = GazeEstimator(dataclasses.replace(eye_config(64), channels=(8, 8, 8), hidden=16))
    lm = _eye_landmarks(4, 64, scale=0.5)
    x = _draw_eye_dots(lm, 64)
    still = GazeEstimatorTrainConfig(brightness=0, contrast=0, noise=0, landmark_noise=0, max_shift=0.1)
    patches, layout = model.eye_inputs(x, lm)
    shifted, lm_s = augment_batch(x, still, torch.Generator().manual_seed(3), lm)
    p_img, l_img = model.eye_inputs(shifted, lm_s)
    assert not torch.equal(l_img, layout)  # the draw did shift
    torch.testing.assert_close(p_img, patches)  # the eyes sit far from the replicated border
    p_aug, l_aug = augment_eye_inputs(x, lm, model, still, torch.Generator().manual_seed(3))
    torch.testing.assert_close(p_aug, patches)
    moved = (l_aug - layout).view(4, 68, 2) * 32  # layout units -> pixels of the 64 px image
    assert torch.equal(moved, moved[:, :1].expand_as(moved))  # one rigid shift per sample
    assert float(moved.abs().max()) <= round(0.1 * 64) + 1e-4 and len(set(moved[:, 0, 0].tolist())) > 1
    # Photometric jitter on the patches: per sample, bounded, reproducible from the generator.
    loud = dataclasses.replace(still, brightness=0.2, contrast=0.2, noise=0.05, max_shift=0.0)
    a, _ = augment_eye_inputs(x, lm, model, loud, torch.Generator().manual_seed(5))
    b, _ = augment_eye_inputs(x, lm, model, loud, torch.Generator().manual_seed(5))
    assert torch.equal(a, b) and not torch.equal(a, patches) and 0 <= float(a.min()) and float(a.max()) <= 1


def test_mirrored_face_is_the_mirrored_scene_with_exact_labels():
    """mirror_faces of a render equals the render of the mirrored scene (symmetric subject, mirrored pose, gaze,
    light and rig camera): pixels, landmarks and all four labels."""
    import numpy as np

    from toolkit.cameras import eth_xgaze_rig
    from train.data.generate import RIG_RADIUS, frame_cameras
    from train.data.synthetic import SubjectParams, build_subject, render_views
    from train.estimator.crops import IBUG_MIRROR, mirror_faces

    assert sorted(IBUG_MIRROR) == list(range(68)) and all(IBUG_MIRROR[IBUG_MIRROR[i]] == i for i in range(68))
    rig = eth_xgaze_rig(radius=RIG_RADIUS)
    centres = np.stack([c.center.numpy() for c in rig])
    twin = int(np.argmin(np.linalg.norm(centres - centres[1] * [-1, 1, 1], axis=1)))
    subject = build_subject(SubjectParams())  # the neutral identity is left-right symmetric

    def shot(s: float, cam: int):
        pose = np.array([0.0, 0.2 * s, 0.0, 0.0, 0.0, 0.0], np.float32)
        out = render_views(subject, [0.2, 0.3 * s], pose, [0, 0, 0, 0.2], frame_cameras(subject, pose, [rig[cam]], 64),
                           light_dirs=[0.3 * s, 0.1, -1.0])
        return (torch.from_numpy(out["rgb"]).permute(0, 3, 1, 2),
                torch.from_numpy(np.concatenate([out["pitchyaw_cam"], out["face_head_pose"]], 1)).float(),
                torch.from_numpy(out["landmarks_2d"]).float())

    (xa, ya, la), (xb, yb, lb) = shot(1.0, 1), shot(-1.0, twin)
    assert float((xa - xb).abs().mean()) > 0.05  # the two scenes do differ
    xm, ym, lmm = mirror_faces(xa, ya, la)
    assert float((xm - xb).abs().mean()) < 1e-3
    torch.testing.assert_close(ym, yb, atol=1e-5, rtol=0)
    torch.testing.assert_close(lmm, lb, atol=1e-3, rtol=0)
    # Only the chosen samples move.
    x2, y2, l2 = mirror_faces(torch.cat([xa, xa]), torch.cat([ya, ya]), torch.cat([la, la]), torch.tensor([False, True]))
    assert torch.equal(x2[0], xa[0]) and torch.equal(y2[0], ya[0]) and torch.equal(l2[1], lmm[0])
    assert torch.equal(x2[1], xm[0]) and torch.equal(mirror_faces(xa, which=torch.tensor([False]))[0], xa)
    # Gradients reach the mirrored and the untouched samples alike.
    src = torch.cat([xa, xa]).requires_grad_(True)
    mirror_faces(src, which=torch.tensor([True, False]))[0].sum().backward()
    assert torch.equal(src.grad, torch.ones_like(src))


@pytest.mark.parametrize("eyes", [False, True])
def test_mirror_average_makes_the_estimator_mirror_equivariant(eyes, tmp_path):
    from train.estimator.config import eye_config
    from train.estimator.crops import MIRROR_SIGNS, mirror_faces
    from train.estimator.frames import mean_direction

    torch.manual_seed(0)
    cfg = dataclasses.replace(eye_config(64), channels=(8, 8, 8), hidden=16) if eyes else TINY
    lm = _eye_landmarks(3, 64, roll=0.2, scale=0.5)
    x = torch.rand(3, 3, 64, 64)
    xm, _, lmm = mirror_faces(x, None, lm)
    signs = torch.tensor(MIRROR_SIGNS)
    plain = GazeEstimator(dataclasses.replace(cfg, mirror_average=False)).eval()
    assert not torch.allclose(plain(xm, lmm) * signs, plain(x, lm), atol=1e-4)  # a plain network is not
    avg = GazeEstimator(dataclasses.replace(cfg, mirror_average=True))
    avg.load_state_dict(plain.state_dict())
    avg.eval()
    out = avg(x, lm)
    torch.testing.assert_close(avg(xm, lmm) * signs, out, atol=1e-5, rtol=0)
    expected = torch.cat([mean_direction(plain(x, lm)[:, :2], plain(xm, lmm)[:, :2] * signs[:2]),
                          mean_direction(plain(x, lm)[:, 2:], plain(xm, lmm)[:, 2:] * signs[2:])], 1)
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)
    xg = x.clone().requires_grad_(True)
    avg(xg, lm).sum().backward()
    assert torch.isfinite(xg.grad).all() and float(xg.grad.abs().sum()) > 0
    avg.save(tmp_path / "avg.safetensors")
    assert GazeEstimator.load(tmp_path / "avg.safetensors").config.mirror_average
    # Opposite directions have no halfway direction: the first one is kept, finite.
    a = torch.tensor([[0.1, 0.2]])
    torch.testing.assert_close(mean_direction(a, torch.tensor([[-0.1, 0.2 - math.pi]])), a)


def test_mirror_average_rejects_bad_landmarks_clearly_and_face_designs_ignore_them():
    from train.estimator.config import eye_config

    eyes = GazeEstimator(dataclasses.replace(eye_config(64), channels=(8, 8, 8), hidden=16))
    x = torch.rand(4, 3, 64, 64)
    for bad in (None, _eye_landmarks(3, 64, scale=0.5), _eye_landmarks(1, 64, scale=0.5), torch.zeros(4, 5, 2)):
        with pytest.raises(ToolkitError, match="landmarks"):
            eyes(x, bad)
    face = GazeEstimator(dataclasses.replace(TINY, mirror_average=True)).eval()
    torch.testing.assert_close(face(x, torch.zeros(4, 5)), face(x))


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_benchmark_cuda_device_without_cuda_is_one_line_error(capsys):
    import benchmarks.gaze_estimator as bench
    from toolkit.errors import run_cli

    assert run_cli(bench.main, ["--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--device cuda: CUDA is not available" in err


def test_benchmark_cache_returns_the_rendered_set_and_probe_times_steps(tmp_path):
    import benchmarks.gaze_estimator as bench
    from train.estimator.config import eye_config

    kw = dict(n_frames=2, seed=0, res=64, workers=1, iris=True, cache=str(tmp_path))
    first = bench.procedural_set(range(7, 8), **kw)
    assert len(list(tmp_path.iterdir())) == 1
    again = bench.procedural_set(range(7, 8), **kw)  # read back from the cache
    assert len(first) == len(again) == 4
    for a, b in zip(first, again):
        assert a.dtype == b.dtype and torch.equal(a, b)
    cfg = dataclasses.replace(eye_config(64), channels=(8, 8, 8), hidden=16)
    tc = GazeEstimatorTrainConfig(batch_size=2)
    sec = bench.probe_step_s(first[:3], cfg, tc, "cpu", steps=4, skip=2)
    assert 0 < sec < 60


@pytest.mark.parametrize("argv, msg", [(["--channels", "8,x"], "--channels: expected a comma list"),
                                       (["--channels", "8,0"], "--channels: expected positive"),
                                       (["--budget-s", "0"], "--budget-s: expected a positive"),
                                       (["--steps", "0"], "--steps: expected an integer >= 1"),
                                       (["--init", "no/such/estimator.safetensors"], "no/such/estimator")])
def test_benchmark_bad_options_are_one_line_errors(capsys, argv, msg):
    import benchmarks.gaze_estimator as bench
    from toolkit.errors import run_cli

    assert run_cli(bench.main, argv + ["--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and msg in err


def test_benchmark_unknown_device_is_a_one_line_error(capsys):
    import benchmarks.gaze_estimator as bench
    from toolkit.errors import run_cli

    assert run_cli(bench.main, ["--device", "tpu"]) == 2
    assert capsys.readouterr().err == "error: --device: expected cpu, cuda or cuda:N, got 'tpu'\n"


def test_benchmark_fine_tunes_a_saved_estimator(tmp_path, monkeypatch, capsys):
    import benchmarks.gaze_estimator as bench
    from train.estimator.config import eye_config

    monkeypatch.setattr(bench, "OUT_DIR", tmp_path)  # the plot goes to tmp, not out/benchmarks
    torch.manual_seed(0)
    cfg = dataclasses.replace(eye_config(64), channels=(8, 8, 8), hidden=16, head_frame=False)
    GazeEstimator(cfg).save(tmp_path / "start.safetensors")
    argv = ["--init", str(tmp_path / "start.safetensors"), "--subjects", "1", "--frames", "2", "--test-subjects", "1",
            "--res", "64", "--steps", "2", "--batch", "4", "--workers", "1", "--device", "cpu",
            "--cache", str(tmp_path / "cache"), "--save", str(tmp_path / "out")]
    assert bench.main(argv) == 0
    out = capsys.readouterr().out
    assert "eyes: starting from" in out and "face:" not in out
    assert GazeEstimator.load(tmp_path / "out" / "eyes.safetensors").config == cfg


def test_a_diverging_estimator_stops_naming_the_step():
    """Never a silent NaN estimator: a non-finite loss mid-training (here from weights already NaN) stops it."""
    imgs, labels, _ = drawn_face_dataset(16, 32, n_subjects=2, seed=0)
    bad = GazeEstimator(TINY)
    with torch.no_grad():
        next(bad.parameters()).fill_(float("nan"))
    tc = GazeEstimatorTrainConfig(steps=3, batch_size=8, log_every=3, seed=3)
    with pytest.raises(ToolkitError, match=r"train_gaze_estimator: non-finite loss at step 1 \(nan\).*nothing was saved"):
        train_gaze_estimator(imgs, labels, TINY, tc, init=bad)


def test_on_step_sees_every_step_and_leaves_the_training_unchanged():
    """The progress hook gets each step's loss; the weights are those of a run without it."""
    imgs, labels, _ = drawn_face_dataset(16, 32, n_subjects=2, seed=0)
    tc = GazeEstimatorTrainConfig(steps=4, batch_size=8, log_every=4, seed=3)
    seen = []
    m1, hist = train_gaze_estimator(imgs, labels, TINY, tc, on_step=lambda s, loss: seen.append((s, loss)))
    m2, _ = train_gaze_estimator(imgs, labels, TINY, tc)
    assert [s for s, _ in seen] == [1, 2, 3, 4] and all(math.isfinite(v) for _, v in seen)
    assert seen[-1][1] == pytest.approx(hist[-1]["loss"])
    assert all(torch.equal(a, b) for a, b in zip(m1.parameters(), m2.parameters()))
