"""The eval protocol's test-time fitting: it fits the input image, leaves the weights alone, and the reported
rendering throughput does not count it."""

import math

import pytest
import torch

from toolkit.errors import ToolkitError


@pytest.fixture(scope="module")
def subject_file(tmp_path_factory):
    from render.mesh_gl import shared_context

    try:
        shared_context()
    except ToolkitError:
        pytest.skip("no headless EGL OpenGL context")
    from train.data.format import write_subject_h5
    from train.data.generate import generate_subject
    from train.data.synthetic import SubjectParams

    rows, subj, attrs = generate_subject(SubjectParams.sample(5), n_frames=1, res=64, seed=2)
    return write_subject_h5(tmp_path_factory.mktemp("eval") / "subject0000.h5", rows, subject=subj, attrs=attrs)


def _parts():
    from toolkit.procedural import demo_head_scene
    from train.gaussian_model import GaussianModel, GaussianModelConfig
    from train.gaze_estimator import GazeEstimator, GazeEstimatorConfig
    from train.renderer import make_renderer

    torch.manual_seed(0)
    model = GaussianModel.from_scene(demo_head_scene(300), GaussianModelConfig(hidden=16)).eval()
    return model, make_renderer("baseline").eval(), GazeEstimator(GazeEstimatorConfig(input_size=32))


def test_test_time_fit_lowers_the_input_error_and_keeps_the_weights(subject_file):
    from train.data.pairing import SyntheticRedirectionPairs
    from train.evaluate import composite_on_white, test_time_fit

    model, renderer, _ = _parts()
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

    model, renderer, est = _parts()
    out = evaluate(model, renderer, est, [subject_file], res=64, pairs_per_subject=3, tta_steps=2,
                   log=lambda s: None)
    m = out["metrics"]
    assert m["pairs"] == 3 and math.isfinite(m["psnr"]) and m["images_per_s"] > 0
