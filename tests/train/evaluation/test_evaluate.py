"""The eval protocol's test-time fitting: it fits the input image, leaves the weights alone, and the reported
rendering throughput does not count it."""

import math

import numpy as np
import pytest
import torch

from tests.train.evaluation.fit_inputs import pair_inputs, render_input_error
from tests.train.helpers import untrained_eval_parts
from toolkit.errors import ToolkitError


def test_test_time_fit_lowers_the_input_error_and_keeps_the_weights(subject_file):
    from train.evaluation.fitting import test_time_fit

    model, renderer, _ = untrained_eval_parts()
    batch, image, mask, _ = pair_inputs(subject_file, 3)
    weights = {k: v.clone() for k, v in {**model.state_dict(), **renderer.state_dict()}.items()}

    def input_error(code):
        return render_input_error(model, renderer, batch, image, mask, code)

    fitted = test_time_fit(model, renderer, batch, image, mask, 64, steps=15)
    assert torch.isfinite(fitted).all() and not torch.equal(fitted, batch["code"])
    assert input_error(fitted) < input_error(batch["code"])
    after = {**model.state_dict(), **renderer.state_dict()}
    assert all(torch.equal(after[k], v) for k, v in weights.items())


@pytest.mark.parametrize("tta_weights", [(), ("features",)])
def test_evaluate_with_fitting_reports_the_rendering_throughput(subject_file, monkeypatch, tta_weights):
    """The throughput counts the renders alone: on a fake clock that ticks 1 per reading and 1000 per fit, the
    3 pairs' render time stays a few ticks (1 batch of 3, or 3 renders of 1), never a fit's 1000."""
    import types

    import train.evaluation.protocol as ev

    clock = [0.0]

    def tick():
        clock[0] += 1.0
        return clock[0]

    real_fit = ev.test_time_fit

    def slow_fit(*args, **kwargs):
        clock[0] += 1000.0
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(ev, "time", types.SimpleNamespace(perf_counter=tick))
    monkeypatch.setattr(ev, "test_time_fit", slow_fit)
    model, renderer, est = untrained_eval_parts()
    out = ev.evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, tta_steps=2,
                      tta_weights=tta_weights, log=lambda s: None)
    m = out["metrics"]
    assert clock[0] > 1000  # the fits ran
    assert m["pairs"] == 3 and math.isfinite(m["psnr"])
    assert m["images_per_s"] == pytest.approx(1.0 if tta_weights else 3.0)  # 3 images in 1 or 3 ticks
    assert 0 <= m["gaze_error_median_deg"] <= 180 and math.isfinite(m["gaze_error_deg"])


def test_references_are_scored_like_the_renders_and_the_identity_scores_perfectly(subject_file):
    from train.evaluation.protocol import evaluate, reference_transforms

    model, renderer, est = untrained_eval_parts()
    refs = {"identity": lambda x: x, "dark": lambda x: x * 0.5, **reference_transforms(renderer)}
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, log=lambda s: None,
                   references=refs)
    r = out["references"]
    assert set(r) == {"identity", "dark", "target at half resolution"}  # the U-Net has no codec
    assert r["identity"]["gaze_error_deg"] < 1e-2 and r["identity"]["head_pose_error_deg"] < 1e-2
    assert r["identity"]["psnr"] > 60 and r["identity"]["ssim"] > 0.999
    assert r["dark"]["psnr"] < r["target at half resolution"]["psnr"] < r["identity"]["psnr"]
    assert all(math.isfinite(v) for m in r.values() for v in m.values())
    assert evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=1,
                    log=lambda s: None)["references"] == {}
    dit = _renderer("dit")
    assert set(reference_transforms(dit)) == {"target at half resolution", "target through the codec"}
    x = torch.rand(2, 3, 64, 64)
    assert reference_transforms(dit)["target through the codec"](x).shape == x.shape
    # In pixel space the "codec" is the identity: its row would read a perfect, meaningless score.
    from train.model.codec import PixelCodec
    from train.model.renderer import make_renderer

    pixel_dit = make_renderer("dit", PixelCodec(), output_size=64, upscale=4)
    assert set(reference_transforms(pixel_dit)) == {"target at half resolution"}


def _renderer(kind):
    from train.model.codec import AutoencoderConfig, KLAutoencoder
    from train.model.renderer import make_renderer

    torch.manual_seed(1)
    if kind == "baseline":
        return make_renderer("baseline").eval()
    codec = KLAutoencoder(AutoencoderConfig(downsample=4, base_channels=8))
    return make_renderer("dit", codec, output_size=64).eval()


@pytest.mark.parametrize("kind", ["baseline", "dit"])
def test_fitting_weights_changes_them_in_place_and_restored_weights_puts_them_back(subject_file, kind):
    from train.evaluation.fitting import restored_weights, test_time_fit

    model, _, _ = untrained_eval_parts()
    renderer = _renderer(kind)
    batch, image, mask, _ = pair_inputs(subject_file, 1)
    before = {k: v.clone() for k, v in {**model.state_dict(), **renderer.state_dict()}.items()}

    def input_error(code):
        return render_input_error(model, renderer, batch, image, mask, code)

    start = input_error(batch["code"])
    code_only = input_error(test_time_fit(model, renderer, batch, image, mask, 64, steps=15))
    with restored_weights(model, renderer):
        fitted = test_time_fit(model, renderer, batch, image, mask, 64, steps=15, weights=("features", "renderer"))
        changed = {**model.state_dict(), **renderer.state_dict()}
        assert not torch.equal(changed["face_features"], before["face_features"])
        # The loss never sees the eyes: their features are fitted only when asked for.
        assert torch.equal(changed["eye_features"], before["eye_features"])
        net = [k for k in renderer.state_dict() if kind == "baseline" or k.startswith("dit.")]
        assert any(not torch.equal(changed[k], before[k]) for k in net)
        assert all(torch.equal(changed[k], before[k]) for k in before if k.startswith("codec."))  # frozen
        assert all(p.grad is None for p in [*model.parameters(), *renderer.parameters()])
        with_weights = input_error(fitted)
    # More freedom fits the input image better than the code alone (which cannot move the untrained DiT's
    # output at all: the deformation field's zero-initialized last layer passes the code no gradient).
    assert code_only <= start and with_weights < code_only
    after = {**model.state_dict(), **renderer.state_dict()}
    assert all(torch.equal(after[k], v) for k, v in before.items())


def test_fitting_the_codec_decoder_tunes_it_alone_and_leaves_it_frozen(subject_file):
    from train.evaluation.fitting import restored_weights, test_time_fit

    model, _, _ = untrained_eval_parts()
    renderer = _renderer("dit")
    batch, image, mask, _ = pair_inputs(subject_file, 1)
    before = {k: v.clone() for k, v in renderer.state_dict().items()}

    def fit_error(weights):
        with restored_weights(model, renderer):
            code = test_time_fit(model, renderer, batch, image, mask, 64, steps=15, weights=weights)
            changed = {k: v.clone() for k, v in renderer.state_dict().items()}
            err = render_input_error(model, renderer, batch, image, mask, code)
        return err, changed

    dit_only, _ = fit_error(("renderer",))
    with_decoder, changed = fit_error(("renderer", "decoder"))
    assert any(not torch.equal(changed[k], before[k]) for k in before if k.startswith("codec.decoder."))
    assert all(torch.equal(changed[k], before[k]) for k in before if k.startswith("codec.encoder."))
    assert with_decoder < dit_only  # the decoder's freedom fits the input better
    # The codec is frozen again, with no gradients left, and restored_weights put it back.
    assert not any(p.requires_grad for p in renderer.codec.parameters())
    assert all(p.grad is None for p in renderer.parameters())
    assert all(torch.equal(renderer.state_dict()[k], v) for k, v in before.items())


def test_failed_fit_freezes_the_codec_decoder_again(subject_file, monkeypatch):
    import train.evaluation.fitting as ev

    model, _, _ = untrained_eval_parts()
    renderer = _renderer("dit")
    batch, image, mask, _ = pair_inputs(subject_file, 1)

    def boom(*a, **k):
        assert all(p.requires_grad for p in renderer.codec.decoder.parameters())  # unfrozen during the fit
        raise RuntimeError("boom")

    monkeypatch.setattr(ev, "_fit_steps", boom)
    with ev.restored_weights(model, renderer), pytest.raises(RuntimeError, match="boom"):
        ev.test_time_fit(model, renderer, batch, image, mask, 64, steps=2, weights=("renderer", "decoder"))
    assert not any(p.requires_grad for p in renderer.codec.parameters())


def test_decoder_group_needs_a_codec_with_a_decoder():
    from train.evaluation.fitting import fitted_weights
    from train.model.codec import PixelCodec
    from train.model.renderer import make_renderer

    model, baseline, _ = untrained_eval_parts()
    for renderer in (baseline, make_renderer("dit", PixelCodec(), output_size=64, upscale=4)):
        with pytest.raises(ToolkitError, match="'decoder' group needs a latent renderer"):
            fitted_weights(model, renderer, ["decoder"])
    dit = _renderer("dit")
    assert fitted_weights(model, dit, ["decoder"]) == list(dit.codec.decoder.parameters())


def test_unknown_fitting_group_is_a_clear_error(subject_file):
    from toolkit.errors import ToolkitError
    from train.evaluation.fitting import fitted_weights, test_time_fit

    model, renderer, _ = untrained_eval_parts()
    with pytest.raises(ToolkitError, match="unknown weight group 'geometry'"):
        fitted_weights(model, renderer, ["geometry"])
    with pytest.raises(ToolkitError, match=r"unknown weight group\(s\) \['renderr'\]"):  # not silently the code alone
        test_time_fit(model, renderer, {}, None, None, 64, 1, weights=("renderr",))
    assert fitted_weights(model, renderer, ["features", "features"]) == [model.face_features]  # each group once
    assert fitted_weights(model, renderer, ["eye_features"]) == [model.eye_features]
    renderer.requires_grad_(False)
    with pytest.raises(ToolkitError, match="'renderer' weights are all frozen"):
        fitted_weights(model, renderer, ["renderer"])


def test_failed_fit_leaves_no_gradients_on_the_weights(subject_file):
    from train.evaluation.fitting import restored_weights, test_time_fit

    model, renderer, _ = untrained_eval_parts()
    batch, image, mask, _ = pair_inputs(subject_file, 1)
    calls = {"n": 0}
    forward = renderer.training_forward

    def failing(*a, **k):  # the second step raises
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("boom")
        return forward(*a, **k)

    renderer.training_forward = failing
    with restored_weights(model, renderer), pytest.raises(RuntimeError, match="boom"):
        test_time_fit(model, renderer, batch, image, mask, 64, steps=3, weights=("features", "renderer"))
    assert all(p.grad is None for p in [*model.parameters(), *renderer.parameters()])


def test_evaluate_fitting_weights_per_pair_leaves_the_model_as_it_was(subject_file):
    from train.evaluation.protocol import evaluate

    model, renderer, est = untrained_eval_parts()
    before = {k: v.clone() for k, v in {**model.state_dict(), **renderer.state_dict()}.items()}
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=2, tta_steps=2,
                   tta_weights=("features", "renderer"), log=lambda s: None)
    m = out["metrics"]
    assert m["pairs"] == 2 and math.isfinite(m["psnr"]) and m["images_per_s"] > 0
    after = {**model.state_dict(), **renderer.state_dict()}
    assert all(torch.equal(after[k], v) for k, v in before.items())


def test_face_only_mask_removes_the_dilated_eyes():
    from train.evaluation.fitting import face_only_mask

    head = torch.ones(1, 1, 9, 9)
    eyes = torch.zeros(1, 1, 9, 9)
    eyes[0, 0, 4, 4] = 1
    m = face_only_mask(head, eyes, dilate=1)
    assert float(m.sum()) == 81 - 9 and m[0, 0, 3:6, 3:6].eq(0).all()


def test_fitting_ignores_what_the_input_shows_inside_the_mask_hole(subject_file):
    """The eyes are cut out of the fitting region: the input's eye pixels (its own gaze) cannot pull the fit."""
    from train.evaluation.fitting import face_only_mask, restored_weights, test_time_fit

    model, renderer, _ = untrained_eval_parts()
    batch, image, head, eyes = pair_inputs(subject_file, 1)
    assert eyes.sum() > 0
    mask = face_only_mask(head, eyes)
    scrambled = torch.where(mask > 0, image, torch.rand_like(image))
    fits = []
    for img in (image, scrambled):
        with restored_weights(model, renderer):
            fits.append(test_time_fit(model, renderer, batch, img, mask, 64, steps=3, weights=("features",)))
    assert torch.equal(fits[0], fits[1])


def test_fitting_rejects_learning_rates_that_are_not_positive(subject_file):
    from toolkit.errors import ToolkitError
    from train.evaluation.fitting import test_time_fit

    model, renderer, _ = untrained_eval_parts()
    batch, image, mask, _ = pair_inputs(subject_file, 1)
    with pytest.raises(ToolkitError, match="learning rate > 0 \\(code, features\\), got 0"):
        test_time_fit(model, renderer, batch, image, mask, 64, steps=1, lr=0.0)
    with pytest.raises(ToolkitError, match="renderer learning rate > 0, got -1"):
        test_time_fit(model, renderer, batch, image, mask, 64, steps=1, weights=("renderer",), renderer_lr=-1.0)


def test_spread_indices_cover_the_pairs_evenly():
    from train.evaluation.pairs import spread_indices

    idx = spread_indices(72, 12)
    assert idx[0] == 0 and idx[-1] == 71 and len(set(idx)) == 12 and idx == sorted(idx)
    gaps = [b - a for a, b in zip(idx, idx[1:])]
    assert max(gaps) - min(gaps) <= 1
    # With 18 cameras per frame, the first 12 rows would all be frame 0; the spread reaches every input frame.
    assert {i // 18 for i in idx} == {0, 1, 2, 3}
    assert spread_indices(5, 5) == [0, 1, 2, 3, 4] and spread_indices(5, 1) == [0] and spread_indices(3, 0) == []
    with pytest.raises(ToolkitError, match="n <= total"):
        spread_indices(3, 4)


def test_evaluate_takes_the_spread_pairs(subject_file, monkeypatch):
    from train.data.pairing import SyntheticRedirectionPairs
    from train.evaluation.pairs import spread_indices
    from train.evaluation.protocol import evaluate

    seen, get = [], SyntheticRedirectionPairs.__getitem__

    def recording(self, i):
        seen.append(i)
        return get(self, i)

    monkeypatch.setattr(SyntheticRedirectionPairs, "__getitem__", recording)
    model, renderer, est = untrained_eval_parts()
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, log=lambda s: None)
    total = len(SyntheticRedirectionPairs(subject_file, res=64, seed=0))
    assert total > 3 and seen == spread_indices(total, 3) and seen[-1] == total - 1
    # Each pair's scores are reported under its subject and index, and they average to the table's numbers.
    assert [(r["subject"], r["pair"]) for r in out["per_pair"]] == [(subject_file.name, i) for i in seen]
    for key in ("gaze_error_deg", "psnr", "ssim"):
        mean = sum(r[key] for r in out["per_pair"]) / 3
        assert math.isclose(mean, out["metrics"][key], rel_tol=1e-5)
    # Order-sensitive: the first pair alone (index 0, the first spread index) scores what its row says.
    first = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=1, log=lambda s: None)
    assert first["per_pair"][0]["pair"] == 0
    for key in ("gaze_error_deg", "psnr", "ssim"):
        assert math.isclose(first["per_pair"][0][key], out["per_pair"][0][key], rel_tol=1e-4, abs_tol=1e-4)


def test_own_gaze_batch_turns_the_render_back_on_the_input():
    from train.evaluation.pairs import own_gaze_batch

    b = {k: torch.full((2, 3), float(i)) for i, k in enumerate(
        ("code", "pose", "viewmat", "K", "gaze_head", "in_pose", "in_viewmat", "in_gaze_head"))}
    own = own_gaze_batch(b)
    assert own["pose"] is b["in_pose"] and own["viewmat"] is b["in_viewmat"] and own["gaze_head"] is b["in_gaze_head"]
    assert own["code"] is b["code"] and own["K"] is b["K"] and b["gaze_head"][0, 0] == 4  # the input batch is untouched


@pytest.mark.parametrize("tta_weights", [(), ("features",)])
def test_own_gaze_row_scores_the_input_rendered_at_its_own_gaze(two_frame_file, monkeypatch, tta_weights):
    """A stand-in model that reproduces exactly the input at the input's view and gaze (and a grey face
    elsewhere): the own-gaze row must score perfectly against the input, in both fitting paths, while the
    main row (the same stand-in at the target's gaze) does not."""
    import train.evaluation.protocol as ev
    from train.data.pairing import SyntheticRedirectionPairs
    from train.evaluation.pairs import spread_indices

    pairs = SyntheticRedirectionPairs(two_frame_file, res=64, seed=0)
    items = [pairs[i]["input"] for i in spread_indices(len(pairs), 3)]
    key = lambda gaze, viewmat: (tuple(gaze.tolist()), tuple(viewmat.flatten().tolist()))  # noqa: E731
    shown = {key(torch.as_tensor(it["pitchyaw_head"]).float(), torch.as_tensor(it["viewmat"]).float()):
             torch.as_tensor(it["image"]).float() for it in items}
    calls = []

    def fake_render(model, renderer, batch, res, steps):
        calls.append(batch["gaze_head"].shape[0])
        grey = torch.full((3, res, res), 0.5)
        return torch.stack([shown.get(key(g, v), grey) for g, v in zip(batch["gaze_head"], batch["viewmat"])])

    monkeypatch.setattr(ev, "render_pairs", fake_render)
    model, renderer, est = untrained_eval_parts()
    out = ev.evaluate(model, renderer, est, [two_frame_file], res=64, pairs_per_subject=3, tta_steps=1,
                      tta_weights=tta_weights, log=lambda s: None, own_gaze_row=True)
    own, main = out["own_gaze"], out["metrics"]
    assert own["psnr"] > 60 and own["ssim"] > 0.999 and own["gaze_error_deg"] < 1e-2
    assert main["psnr"] < 40
    assert sum(calls) == 6  # three renders at the target gaze, three at the input's
    assert "own_gaze" not in ev.evaluate(model, renderer, est, [two_frame_file], res=64, pairs_per_subject=1,
                                         log=lambda s: None)


@pytest.mark.parametrize("region", ["head", "face"])
def test_fitting_region_is_the_head_or_the_face_without_the_eyes(subject_file, monkeypatch, region):
    """``tta_region``: the mask the fitting compares holds the input's eye pixels for "head" and none for "face"."""
    import train.evaluation.protocol as ev

    seen = []

    def spy(model, renderer, batch, image, mask, *a, **k):
        seen.append(mask.clone())
        return batch["code"]

    monkeypatch.setattr(ev, "test_time_fit", spy)
    model, renderer, est = untrained_eval_parts()
    ev.evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=2, tta_steps=1, log=lambda s: None,
                tta_region=region)
    _, _, head, eyes = pair_inputs(subject_file, 1)
    mask = seen[0][:1]
    inside_eyes = float((mask * eyes).sum())
    assert eyes.sum() > 0 and mask.sum() > 0
    if region == "head":
        assert torch.equal(mask, head) and inside_eyes == float(eyes.sum())
    else:
        assert inside_eyes == 0 and float(mask.sum()) < float(head.sum())
    with pytest.raises(ToolkitError, match="tta_region"):
        ev.evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=1, log=lambda s: None,
                    tta_region="eyes")


def test_render_target_at_the_inputs_own_gaze_reproduces_the_input(subject_file):
    """``SyntheticRedirectionPairs.render_target`` renders a row at any gaze (apps' benchmarks use it as
    ground truth): at the row's own gaze it is the stored input image; at another it moves only the eyes."""
    import numpy as np

    from train.data.pairing import SyntheticRedirectionPairs

    pairs = SyntheticRedirectionPairs(subject_file, res=64, seed=0)
    inp = pairs.data[0]
    own = pairs.render_target(0, inp["pitchyaw_head"].numpy())
    assert (own["image"] - inp["image"]).abs().max() <= 1.5 / 255  # the stored image, up to u8 rounding
    assert torch.allclose(own["pitchyaw_head"], inp["pitchyaw_head"], atol=1e-6)
    turned = pairs.render_target(0, np.array([0.3, -0.4]))
    assert torch.allclose(turned["pitchyaw_head"], torch.tensor([0.3, -0.4]), atol=1e-6)
    moved = (turned["image"] - own["image"]).abs().amax(0) > 0.05
    eyes = (own["left_eye_mask"] + own["right_eye_mask"])[0] > 0
    assert moved.any() and moved[~torch.nn.functional.max_pool2d(eyes[None, None].float(), 5, 1, 2)[0, 0].bool()].sum() == 0
    # The pairs' targets are this function at the target row's gaze.
    a, b = (int(x) for x in pairs.pairs[0])
    t = pairs.render_target(a, pairs.data._file(0)["pitchyaw_head"][b])
    assert torch.equal(t["image"], pairs[0]["target"]["image"])


class _ColourReading(torch.nn.Module):
    """A stand-in evaluation estimator: gaze from the image's mean colour (as ``_ColourGaze``), a fixed head pose."""

    def forward(self, images, landmarks=None):
        rgb = images.mean((2, 3))
        head = torch.tensor([0.05, 0.2]).expand(images.shape[0], 2)
        return torch.cat([torch.stack([rgb[:, 0] - rgb[:, 2], rgb[:, 1] - 0.5], 1), head], 1)


def test_readings_against_the_labels_use_each_targets_own_labels(subject_file):
    """Each target's reading misses the target's own camera-frame gaze label, and the input's head pose, by
    exactly their angle to it; the render's reading (another image) is scored apart from it."""
    from toolkit.rotations import angular_error_deg
    from train.data.pairing import SyntheticRedirectionPairs
    from train.evaluation.pairs import spread_indices
    from train.evaluation.protocol import evaluate
    from train.losses.metrics import composite_on_white

    model, renderer, _ = untrained_eval_parts()
    est = _ColourReading()
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, log=lambda s: None)
    pairs = SyntheticRedirectionPairs(subject_file, res=64, seed=0)
    items = [pairs[i] for i in spread_indices(len(pairs), 3)]
    tgt = composite_on_white(torch.stack([it["target"]["image"] for it in items]),
                             torch.stack([it["target"]["head_mask"] for it in items]))
    gaze = torch.stack([it["target"]["pitchyaw_cam"] for it in items])
    head = torch.stack([torch.as_tensor(it["input"]["face_head_pose"]) for it in items]).float()
    reading = est(tgt)
    want_gaze = angular_error_deg(reading[:, :2], gaze)
    want_head = angular_error_deg(reading[:, 2:], head)
    assert want_gaze.min() > 1  # the check can fail: the readings are far from every label
    for r, w in zip(out["per_pair"], want_gaze.tolist()):
        assert math.isclose(r["target_vs_label_gaze_deg"], w, rel_tol=1e-4)
        assert abs(r["render_vs_label_gaze_deg"] - w) > 1e-3  # the render is read on its own
    assert math.isclose(out["labels"]["target"]["gaze_error_deg"], float(want_gaze.mean()), rel_tol=1e-4)
    assert math.isclose(out["labels"]["target"]["head_pose_error_deg"], float(want_head.mean()), rel_tol=1e-4)
    renders = [r["render_vs_label_gaze_deg"] for r in out["per_pair"]]
    assert math.isclose(out["labels"]["render"]["gaze_error_deg"], sum(renders) / 3, rel_tol=1e-6)


def test_worst_eye_views_are_the_worst_pairs_eye_patches_and_survive_a_merge():
    from train.estimator.crops import eye_patches
    from train.evaluation.figures import EYE_VIEW_HW, WORST_EYE_PAIRS, eye_views_grid, worst_eye_views
    from train.evaluation.summary import merge_raw_evaluations, summarize_evaluation

    g = torch.Generator().manual_seed(0)
    B, h, w = 8, *EYE_VIEW_HW
    inp, tgt, out = (torch.rand(B, 3, 64, 64, generator=g) for _ in range(3))
    lm = 20 + 24 * torch.rand(B, 68, 2, generator=g)
    err = torch.tensor([3.0, 9.0, 1.0, 7.0, 2.0, 8.0, 0.5, 4.0])
    views = worst_eye_views("a.h5", list(range(10, 18)), err, inp, tgt, out, lm)
    assert [v["pair"] for v in views] == [11, 15, 13, 17, 10, 14][:WORST_EYE_PAIRS]
    v = views[0]["views"]
    assert v.dtype == torch.uint8 and v.shape == (3, 3, h, 2 * w)
    p = eye_patches(tgt[1:2], lm[1:2], EYE_VIEW_HW)[0]  # the target's two eyes, side by side
    want = (torch.cat([p[:3], p[3:]], -1).clamp(0, 1) * 255).round()
    assert torch.equal(v[1].float(), want)
    # Two groups of subjects, merged: the summary keeps the overall worst pairs, worst first.
    other = worst_eye_views("b.h5", [0, 1], torch.tensor([8.5, 0.1]), inp[:2], tgt[:2], out[:2], lm[:2])
    empty = {"gaze_err": [], "head_err": [], "psnrs": [], "ssims": [], "reals": [], "fakes": [], "per_subject": [],
             "per_pair": [], "ref_scores": {}, "own_scores": {}, "label_scores": {}, "examples": None, "n_images": 0,
             "render_seconds": 0.0}
    raw = merge_raw_evaluations([dict(empty, worst_eyes=views), dict(empty, worst_eyes=other)])
    worst = summarize_evaluation(raw, log=lambda s: None)["worst_eyes"]
    assert [(r["subject"], r["pair"]) for r in worst] == [("a.h5", 11), ("b.h5", 0), ("a.h5", 15), ("a.h5", 13),
                                                         ("a.h5", 17), ("a.h5", 10)]
    grid = eye_views_grid(worst)
    assert grid.dtype == np.uint8 and grid.shape == (WORST_EYE_PAIRS * (h + 14), 3 * (2 * w + 6), 3)
    with pytest.raises(ToolkitError, match="no pairs"):
        eye_views_grid([])


def test_eye_colours_group_fits_the_parametric_eyeball_alone_and_is_restored(subject_file):
    """``eye_colours``: the parametric eyeball's eleven numbers (a model with ``eyeball_colours``), fitted at the
    code's rate and put back by ``restored_weights``; a model with free eye colours gets a clear error."""
    from tests.train.helpers import untrained_eval_parts
    from toolkit.errors import ToolkitError
    from toolkit.procedural import demo_head_scene
    from train.evaluation.fitting import fitted_weights, restored_weights, test_time_fit
    from train.model.gaussian_model import GaussianModel, GaussianModelConfig

    plain, renderer, _ = untrained_eval_parts()
    with pytest.raises(ToolkitError, match="'eye_colours' group needs a model trained with gaussian.eyeball_colours"):
        fitted_weights(plain, renderer, ["eye_colours"])
    torch.manual_seed(0)
    model = GaussianModel.from_scene(demo_head_scene(1500), GaussianModelConfig(hidden=16, eyeball_colours=True)).eval()
    assert fitted_weights(model, renderer, ["eye_colours"]) == list(model.eyeball_colours.parameters())
    seen = {}
    real_adam = torch.optim.Adam

    def spy(groups, *a, **k):  # which rate each fitted tensor gets
        seen.update({id(p): g["lr"] for g in groups for p in g["params"]})
        return real_adam(groups, *a, **k)
    batch, image, mask, eyes = pair_inputs(subject_file, 1)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with restored_weights(model, renderer), pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch.optim, "Adam", spy)
        code = test_time_fit(model, renderer, batch, image, eyes * mask, 64, steps=5, lr=0.05, renderer_lr=1e-4,
                             weights=("eye_colours",))
        assert all(seen[id(p)] == 0.05 for p in model.eyeball_colours.parameters())  # the code's rate
        assert torch.isfinite(code).all()
        changed = model.state_dict()
        moved = [k for k in before if not torch.equal(changed[k], before[k])]
        assert moved and all(k.startswith("eyeball_colours.") for k in moved), moved
        assert all(p.grad is None for p in model.parameters())
    assert all(torch.equal(model.state_dict()[k], v) for k, v in before.items())


def test_fid_is_reported_as_n_a_without_its_optional_package(monkeypatch):
    import train.evaluation.fid as ev

    def must_not_run(*a, **k):
        raise AssertionError("fid() called without its package")

    monkeypatch.setattr(ev, "fid_available", lambda: False)
    monkeypatch.setattr(ev, "fid", must_not_run)
    images = torch.rand(4, 3, 16, 16)
    assert ev.fid_or_none(images, images, log=lambda s: None) is None


def test_a_diverged_fit_stops_the_evaluation_naming_the_pair(subject_file, monkeypatch):
    """A non-finite render would drop out of the means and leave a NaN median: the evaluation stops instead."""
    import train.evaluation.protocol as ev

    real = ev._fit_and_render

    def diverged(*args, **kwargs):
        out, seconds, own = real(*args, **kwargs)
        out = out.clone()
        out[1] = float("nan")
        return out, seconds, own

    monkeypatch.setattr(ev, "_fit_and_render", diverged)
    model, renderer, est = untrained_eval_parts()
    with pytest.raises(ToolkitError, match=rf"{subject_file.name} pair\(s\) \[\d+\]: the render is not finite"):
        ev.evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, log=lambda s: None)


def test_groups_of_interleaved_subjects_summarize_as_one_process_in_turn():
    """Four subjects evaluated in two groups (s0, s2 | s1, s3) summarize exactly as one process evaluating
    s0..s3 in turn: the means and the bootstrap intervals draw from lists in the subjects' order."""
    from train.evaluation.summary import in_subject_order, merge_raw_evaluations, summarize_evaluation

    rng = np.random.default_rng(0)
    empty = {"reals": [], "fakes": [], "ref_scores": {}, "own_scores": {}, "label_scores": {}, "examples": None,
             "n_images": 0, "render_seconds": 0.0, "worst_eyes": []}

    def subject(name, n):
        pairs = [{"subject": name, "pair": i, "gaze_error_deg": float(rng.gamma(2, 3)),
                  "head_pose_error_deg": float(rng.random()), "psnr": float(30 + rng.random()),
                  "ssim": float(0.9 + 0.1 * rng.random())} for i in range(n)]
        lists = {k: [p[f] for p in pairs] for k, f in (("gaze_err", "gaze_error_deg"), ("head_err",
                 "head_pose_error_deg"), ("psnrs", "psnr"), ("ssims", "ssim"))}
        return dict(empty, **lists, per_pair=pairs, per_subject=[{"subject": name, "pairs": n}])

    s = [subject(f"s{i}.h5", n) for i, n in enumerate((5, 3, 4, 6))]
    one = merge_raw_evaluations(s)
    groups = [merge_raw_evaluations([s[0], s[2]]), merge_raw_evaluations([s[1], s[3]])]
    split = in_subject_order(merge_raw_evaluations(groups), [f"s{i}.h5" for i in range(4)])
    a, b = (summarize_evaluation(r, log=lambda m: None)["metrics"] for r in (one, split))
    assert a == b
    unsorted = summarize_evaluation(merge_raw_evaluations(groups), log=lambda m: None)["metrics"]
    assert unsorted["gaze_error_ci95_deg"] != a["gaze_error_ci95_deg"]  # what the re-ordering is for


def test_each_pairs_fit_draws_its_own_random_stream(subject_file, monkeypatch):
    """A pair's fit (and so its score) does not depend on which other pairs of its subject are evaluated: the
    random state each per-pair fit starts from is the same with 2 pairs a subject (the first and the last) as
    with 3 (the first, a middle one, the last)."""
    import train.evaluation.protocol as ev
    from tests.train.helpers import untrained_eval_parts

    real_fit = ev.test_time_fit
    draws: list[float] = []

    def spy(model, renderer, batch, *a, **kw):
        draws.append(torch.rand(1).item())
        return real_fit(model, renderer, batch, *a, **kw)

    monkeypatch.setattr(ev, "test_time_fit", spy)
    model, renderer, est = untrained_eval_parts()
    runs = []
    for n in (2, 3):
        draws.clear()
        ev.evaluate_raw(model, renderer, est, [subject_file], res=64, pairs_per_subject=n, tta_steps=1,
                        tta_weights=("features",), log=lambda s: None)
        runs.append(list(draws))
    two, three = runs
    assert len(two) == 2 and len(three) == 3
    assert three[0] == two[0] and three[2] == two[1] and len(set(three)) == 3


def test_lpips_is_scored_per_pair_when_its_weights_are_given(subject_file):
    """With an LPIPS module (the user's weights; here the untrained default) every pair gets an LPIPS against
    its target, both on white outside the target's mask, and the table's column is their mean; without, n/a."""
    from tests.train.helpers import untrained_eval_parts
    from train.evaluation.protocol import evaluate
    from train.losses.lpips import LPIPS

    model, renderer, est = untrained_eval_parts()
    lp = LPIPS()
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, log=lambda s: None, lpips=lp)
    per = [r["lpips"] for r in out["per_pair"]]
    assert len(per) == 3 and all(math.isfinite(v) and v >= 0 for v in per)
    assert out["metrics"]["lpips"] == pytest.approx(sum(per) / 3)
    assert evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3,
                    log=lambda s: None)["metrics"]["lpips"] is None


def test_identity_similarity_is_scored_per_pair_when_a_face_model_is_given(subject_file):
    """With an ArcFace model (the user's weights; here an untrained iresnet18) every pair gets the cosine
    similarity of its render's and target's embeddings, both aligned with the pair's landmarks; without, n/a."""
    from tests.train.helpers import untrained_eval_parts
    from train.evaluation.protocol import evaluate
    from train.losses.identity import IdentitySimilarity

    model, renderer, est = untrained_eval_parts()
    torch.manual_seed(0)
    ident = IdentitySimilarity(arch="iresnet18")
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=2, log=lambda s: None,
                   identity=ident)
    per = [r["identity_similarity"] for r in out["per_pair"]]
    assert len(per) == 2 and all(-1 <= v <= 1 for v in per)
    assert out["metrics"]["identity_similarity"] == pytest.approx(sum(per) / 2)
    assert evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=2,
                    log=lambda s: None)["metrics"]["identity_similarity"] is None


def test_a_pairing_gives_each_subject_its_pairs(subject_file, monkeypatch):
    """GazeNeRF's protocol: pairs from a pairing file ({subject stem: [[input_row, target_row], ...]}) instead of
    the generated ones; a test subject the file does not pair is an error naming it."""
    import train.data.pairing as pairing_mod
    from tests.train.helpers import untrained_eval_parts
    from train.evaluation.protocol import evaluate

    seen = []
    real = pairing_mod.SyntheticRedirectionPairs

    class Spy(real):
        def __init__(self, path, pairs=None, **kw):
            super().__init__(path, pairs, **kw)
            seen.append(self.pairs.tolist())

    monkeypatch.setattr(pairing_mod, "SyntheticRedirectionPairs", Spy)
    model, renderer, est = untrained_eval_parts()
    given = {subject_file.stem: np.array([[0, 3], [2, 1], [1, 2]])}
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=2, log=lambda s: None,
                   pairing=given)
    assert seen == [[[0, 3], [2, 1], [1, 2]]] and [r["pair"] for r in out["per_pair"]] == [0, 2]
    with pytest.raises(ToolkitError, match=r"no pairs for test subject\(s\) \['" + subject_file.stem):
        evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=2, log=lambda s: None,
                 pairing={"someone_else": np.array([[0, 1]])})
