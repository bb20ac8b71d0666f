"""The eval protocol's test-time fitting: it fits the input image, leaves the weights alone, and the reported
rendering throughput does not count it."""

import math

import pytest
import torch

from tests.train.helpers import one_frame_subject_file, untrained_eval_parts


@pytest.fixture(scope="module")
def subject_file(tmp_path_factory):
    return one_frame_subject_file(tmp_path_factory.mktemp("eval"), subject_seed=5, frame_seed=2)


def test_test_time_fit_lowers_the_input_error_and_keeps_the_weights(subject_file):
    from train.data.pairing import SyntheticRedirectionPairs
    from train.evaluate import composite_on_white, test_time_fit

    model, renderer, _ = untrained_eval_parts()
    pairs = SyntheticRedirectionPairs(subject_file, res=64, seed=0)
    items = [pairs[i] for i in range(3)]
    st = lambda k: torch.stack([torch.as_tensor(it["input"][k]) for it in items]).float()  # noqa: E731
    batch = {"code": st("latent_code"), "in_pose": st("pose"), "in_viewmat": st("viewmat"), "K": st("K"),
             "in_gaze_head": st("pitchyaw_head")}
    image, mask = st("image"), st("head_mask")
    weights = {k: v.clone() for k, v in {**model.state_dict(), **renderer.state_dict()}.items()}

    def input_error(code):
        with torch.no_grad():
            maps = model(code, batch["in_pose"], batch["in_gaze_head"], batch["in_viewmat"], batch["K"], 64, 64,
                         renders=("head",))
            out = renderer.render(maps["head"], code, gaze=batch["in_gaze_head"], pose=batch["in_pose"])
        return float((composite_on_white(out, mask) - composite_on_white(image, mask)).abs().mean())

    fitted = test_time_fit(model, renderer, batch, image, mask, 64, steps=15)
    assert torch.isfinite(fitted).all() and not torch.equal(fitted, batch["code"])
    assert input_error(fitted) < input_error(batch["code"])
    after = {**model.state_dict(), **renderer.state_dict()}
    assert all(torch.equal(after[k], v) for k, v in weights.items())


def test_evaluate_with_fitting_reports_the_rendering_throughput(subject_file):
    from train.evaluate import evaluate

    model, renderer, est = untrained_eval_parts()
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, tta_steps=2,
                   log=lambda s: None)
    m = out["metrics"]
    assert m["pairs"] == 3 and math.isfinite(m["psnr"]) and m["images_per_s"] > 0
