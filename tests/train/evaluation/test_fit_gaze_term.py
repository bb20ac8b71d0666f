"""The test-time fit's gaze term: it turns the fitted input toward the target gaze, only through what it may
reach, reads the whole head, and renders once more only on its steps."""

import pytest
import torch

from tests.train.evaluation.fit_inputs import pair_inputs
from tests.train.helpers import untrained_eval_parts
from toolkit.errors import ToolkitError


def _target_batch(two_frame_file, n: int):
    """The first ``n`` pairs of the two-frame subject: the input batch plus each pair's target gaze and the
    input's landmarks (what :class:`train.evaluation.fitting.FitGaze` reads)."""
    from train.data.pairing import SyntheticRedirectionPairs

    batch, image, mask, _ = pair_inputs(two_frame_file, n)
    pairs = SyntheticRedirectionPairs(two_frame_file, res=64, seed=0)
    batch["gaze_head"] = torch.stack([torch.as_tensor(pairs[i]["target"]["pitchyaw_head"]) for i in range(n)]).float()
    batch["landmarks"] = torch.stack([torch.as_tensor(pairs[i]["input"]["landmarks"]) for i in range(n)]).float()
    return batch, image, mask


def _target_gaze_error(model, renderer, loss, batch, image, mask, code) -> float:
    """The loss estimator's angle (degrees) between its reading of the render at the target gaze (input view)
    and that gaze in the camera frame."""
    from train.evaluation.fitting import FitGaze

    with torch.no_grad():
        term = FitGaze(loss, 1.0, ("target",)).term(model, renderer, batch, code, None, image, mask, 64, None)
    return float(term)


class _ColourGaze(torch.nn.Module):
    """A stand-in loss estimator whose reading follows the image's mean colour (radians, pitch/yaw): unlike an
    untrained CNN, it responds strongly to what the fit changes."""

    def forward(self, images, landmarks=None):
        rgb = images.mean((2, 3))
        return torch.stack([rgb[:, 0] - rgb[:, 2], rgb[:, 1] - 0.5], 1)


def test_gaze_term_fits_toward_the_target_gaze(two_frame_file):
    """With the ``target`` term the fit lowers the loss estimator's error at the target gaze, well below where the
    photometric fit alone leaves it."""
    from train.evaluation.fitting import FitGaze, restored_weights, test_time_fit
    from train.losses import GazeLoss

    model, renderer, _ = untrained_eval_parts()
    loss = GazeLoss(_ColourGaze())
    batch, image, mask = _target_batch(two_frame_file, 2)
    assert not torch.allclose(batch["gaze_head"], batch["in_gaze_head"])
    before = _target_gaze_error(model, renderer, loss, batch, image, mask, batch["code"])
    errors = {}
    for name, gaze in (("plain", None), ("gaze", FitGaze(loss, 1.0))):
        with restored_weights(model, renderer):
            code = test_time_fit(model, renderer, batch, image, mask, 64, steps=10, lr=0.1, weights=("features",), gaze=gaze)
            assert torch.isfinite(code).all()
            errors[name] = _target_gaze_error(model, renderer, loss, batch, image, mask, code)
    # Measured: 55.3° before, 50.1° after the photometric fit, 42.6° with the gaze term.
    assert errors["gaze"] < errors["plain"] - 3 and errors["gaze"] < before - 5, (before, errors)


def test_eye_field_group_lets_the_gaze_term_turn_the_eyes_and_is_restored(two_frame_file):
    """``eye_field``: the eye rotation field's weights are fitted (at the renderer's rate) and put back by
    ``restored_weights``; the face deformation field is never touched."""
    from train.evaluation.fitting import FitGaze, fitted_weights, restored_weights, test_time_fit
    from train.losses import GazeLoss

    model, renderer, _ = untrained_eval_parts()
    assert fitted_weights(model, renderer, ["eye_field"]) == list(model.eye_field.parameters())
    loss = GazeLoss(_ColourGaze())
    batch, image, mask = _target_batch(two_frame_file, 1)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with restored_weights(model, renderer):
        code = test_time_fit(model, renderer, batch, image, mask, 64, steps=5, lr=0.1, renderer_lr=1e-2,
                             weights=("eye_field",), gaze=FitGaze(loss, 1.0))
        assert torch.isfinite(code).all()
        changed = model.state_dict()
        assert any(not torch.equal(changed[k], before[k]) for k in before if k.startswith("eye_field."))
        assert all(torch.equal(changed[k], before[k]) for k in before if k.startswith("face_field."))
        assert all(p.grad is None for p in model.parameters())
    assert all(torch.equal(model.state_dict()[k], v) for k, v in before.items())


def test_gaze_term_limited_to_its_reach_leaves_the_other_weights_to_the_photometric_fit(two_frame_file):
    """``FitGaze.reach``: one step (the term enters the last) with the term reaching the eye rotation field only
    moves the face features exactly as the photometric fit alone does, and the eye field otherwise; reaching
    everything (the default) moves the features too."""
    from train.evaluation.fitting import FitGaze, restored_weights, test_time_fit
    from train.losses import GazeLoss

    model, renderer, _ = untrained_eval_parts()
    loss = GazeLoss(_ColourGaze())
    batch, image, mask = _target_batch(two_frame_file, 1)
    weights = ("features", "eye_field")
    after = {}
    for name, gaze in (("plain", None), ("reach", FitGaze(loss, 1.0, reach=("eye_field",))), ("all", FitGaze(loss, 1.0))):
        with restored_weights(model, renderer):
            code = test_time_fit(model, renderer, batch, image, mask, 64, steps=1, lr=0.1, renderer_lr=1e-2,
                                 weights=weights, gaze=gaze)
            after[name] = (code, model.face_features.detach().clone(),
                           [p.detach().clone() for p in model.eye_field.parameters()])
    plain, reach, every = after["plain"], after["reach"], after["all"]
    assert torch.equal(reach[0], plain[0]) and torch.equal(reach[1], plain[1])  # code and features: photometric only
    assert any(not torch.equal(a, b) for a, b in zip(reach[2], plain[2]))  # the eye field: the term's too
    assert not torch.equal(every[1], plain[1])  # reaching everything, the term moves the features as well
    with pytest.raises(ToolkitError, match="may reach only the code and fitted weights"):
        test_time_fit(model, renderer, batch, image, mask, 64, steps=1, weights=("features",),
                      gaze=FitGaze(loss, 1.0, reach=("eye_field",)))
    with pytest.raises(ToolkitError, match="may reach some of"):
        FitGaze(loss, 1.0, reach=("eyes",))


def test_own_gaze_term_reaches_the_code_without_another_render(two_frame_file, monkeypatch):
    """``own`` reads the fitting render itself: the model runs once per step, and the fitted code differs from
    the photometric fit's."""
    from train.evaluation.fitting import FitGaze, test_time_fit
    from train.losses import GazeLoss

    model, renderer, est = untrained_eval_parts()
    batch, image, mask = _target_batch(two_frame_file, 2)
    plain = test_time_fit(model, renderer, batch, image, mask, 64, steps=3)
    calls = []
    forward = type(model).forward
    monkeypatch.setattr(type(model), "forward", lambda self, *a, **k: calls.append(1) or forward(self, *a, **k))
    own = test_time_fit(model, renderer, batch, image, mask, 64, steps=3, gaze=FitGaze(GazeLoss(est), 1.0, ("own",)))
    assert len(calls) == 3
    assert torch.isfinite(own).all() and not torch.allclose(own, plain)


@pytest.mark.parametrize("every,renders", [(1, 10), (2, 8), (3, 7), (5, 6)])
def test_target_term_renders_once_more_on_every_kth_step_the_last_included(two_frame_file, monkeypatch, every,
                                                                          renders):
    """``every``: 5 steps, the turned render on steps 5, 5-k, ... only -- the model runs 5 + ceil(5 / k) times."""
    from train.evaluation.fitting import FitGaze, test_time_fit
    from train.losses import GazeLoss

    model, renderer, est = untrained_eval_parts()
    batch, image, mask = _target_batch(two_frame_file, 1)
    gazes = []
    forward = type(model).forward
    monkeypatch.setattr(type(model), "forward",
                        lambda self, code, pose, gaze, *a, **k: gazes.append(gaze.clone()) or forward(self, code, pose, gaze, *a, **k))
    test_time_fit(model, renderer, batch, image, mask, 64, steps=5, gaze=FitGaze(GazeLoss(est), 1.0, every=every))
    assert len(gazes) == renders
    assert torch.equal(gazes[-1], batch["gaze_head"])  # the last step ends on the turned render


def test_fit_gaze_rejects_bad_weights_and_terms():
    from train.evaluation.fitting import FitGaze

    for weight, terms, match in ((-1.0, ("target",), "weight must be >= 0"), (float("nan"), ("target",), "weight"),
                                 (1.0, ("eyes",), "gaze terms must be some of"), (1.0, (), "gaze terms")):
        with pytest.raises(ToolkitError, match=match):
            FitGaze(None, weight, terms)
    for every in (0, -1, 1.5):
        with pytest.raises(ToolkitError, match="'every' must be an integer >= 1"):
            FitGaze(None, 1.0, every=every)


def test_target_gaze_in_the_camera_frame_matches_the_generator_label(two_frame_file):
    """The turned render's label: the target's head-frame gaze through the input's view and head pose is the
    generator's own camera-frame gaze of the target (the pair shares the input's view)."""
    from toolkit.rotations import angular_error_deg, so3_exp
    from train.data.pairing import SyntheticRedirectionPairs
    from train.losses import gaze_to_camera

    pairs = SyntheticRedirectionPairs(two_frame_file, res=64, seed=0)
    items = [pairs[i] for i in range(4)]
    st = lambda part, k: torch.stack([torch.as_tensor(it[part][k]) for it in items]).float()  # noqa: E731
    R = st("input", "viewmat")[:, :3, :3] @ so3_exp(st("input", "pose")[:, :3])
    cam = gaze_to_camera(st("target", "pitchyaw_head"), R)
    assert float(angular_error_deg(cam, st("target", "pitchyaw_cam")).max()) < 0.01


def test_gaze_term_reads_the_whole_head_whatever_region_the_fit_compares(two_frame_file):
    """With ``batch["in_head_mask"]`` the estimator sees the renders inside the input's head mask even when the
    fitting mask (here empty: everything white) leaves the eyes out."""
    from train.evaluation.fitting import FitGaze

    class Spy(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.images = []

        def forward(self, render, target_image=None, target_gaze=None, landmarks=None):
            self.images.append(render.detach())
            return render.mean() * 0

    model, renderer, _ = untrained_eval_parts()
    batch, image, _ = _target_batch(two_frame_file, 1)
    empty = torch.zeros_like(image[:, :1])
    spy = Spy()
    term = FitGaze(spy, 1.0, ("own", "target"))
    with torch.no_grad():
        term.term(model, renderer, batch, batch["code"], image, image, empty, 64, None)
        assert all(bool((x == 1).all()) for x in spy.images)  # no head mask: the fitting mask, all white
        spy.images.clear()
        term.term(model, renderer, {**batch, "in_head_mask": torch.ones_like(empty)}, batch["code"], image, image,
                  empty, 64, None)
    assert len(spy.images) == 2 and all(bool((x != 1).any()) for x in spy.images)
