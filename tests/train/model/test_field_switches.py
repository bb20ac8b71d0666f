"""The paper-form switches of the Gaussian model: the face field reading each Gaussian's feature z₀
(``field_input="feature"``) and the eye field's gaze-driven appearance terms (``eye_field_terms``)."""

from __future__ import annotations

import math

import pytest
import torch

from tests.train.helpers import model_inputs, small_model
from toolkit.errors import ToolkitError
from toolkit.procedural import demo_head_scene
from train.model.fields import EyeGazeAppearanceField, FaceDeformationField
from train.model.gaussian_config import GaussianModelConfig
from train.model.gaussian_model import GaussianModel

SWITCHES = {"feature": {"field_input": "feature"}, "eye_terms": {"eye_field_terms": True},
            "both": {"field_input": "feature", "eye_field_terms": True},
            "eye_terms_eyeballs": {"eye_field_terms": True, "eyeball_colours": True},
            "eye_terms_appearance": {"eye_field_terms": True, "eye_appearance": True}}


@pytest.fixture(scope="module")
def scene():
    return demo_head_scene(500)


def _live(*mlps, seed: int = 3, std: float = 0.3):
    """Random last layers: the zero-initialized ones would make every delta zero whatever the input."""
    g = torch.Generator().manual_seed(seed)
    for mlp in mlps:
        mlp.last.weight.data = torch.randn(mlp.last.weight.shape, generator=g) * std
        mlp.last.bias.data = torch.randn(mlp.last.bias.shape, generator=g) * std


def _field_mlps(model):
    f = model.face_field
    mlps = [f.expr_mlp, f.pose_mlp, model.eye_field.mlp]
    mlps += [f.expr_attr_mlp, f.pose_attr_mlp] if f.field_input == "feature" else []
    mlps += [model.eye_gaze_terms.mlp] if model.eye_gaze_terms is not None else []
    mlps += [model.eye_appearance.mlp] if model.eye_appearance is not None else []
    return mlps


@pytest.mark.parametrize("switch", list(SWITCHES))
def test_each_switch_starts_as_the_model_without_it(scene, switch):
    """Zero-initialized last layers: at step 0 every render equals the default model's, bit for bit."""
    inputs = model_inputs(2, seed=1)
    base = {k: v for k, v in SWITCHES[switch].items() if k not in ("field_input", "eye_field_terms")}
    with torch.no_grad():
        ref = small_model(scene, **base)(*inputs, 64, 64)
        out = small_model(scene, **SWITCHES[switch])(*inputs, 64, 64)
    assert all(torch.equal(out[k], ref[k]) for k in ref), [k for k in ref if not torch.equal(out[k], ref[k])]


def test_feature_input_reads_z0_for_the_attributes_and_x_for_the_offset():
    """GazeGaussian's form: Δposition from PE(x), the other deltas from z₀; the position form ignores z₀."""
    torch.manual_seed(0)
    N, D = 40, 8
    x, z = torch.rand(N, 3) - 0.5, torch.randn(N, D)
    code, pose, lam = torch.randn(2, 12), torch.randn(2, 6) * 0.3, torch.rand(N)
    field = FaceDeformationField(D, 12, 6, 16, 3, 2, 2, field_input="feature")
    _live(field.expr_mlp, field.pose_mlp, field.expr_attr_mlp, field.pose_attr_mlp)
    attrs = ("feature", "log_scale", "rot", "opacity")
    ref = field(x, code, pose, lam, z)
    new_z = field(x, code, pose, lam, z + 0.5 * torch.randn(N, D))
    new_x = field(x + 0.1 * torch.randn(N, 3), code, pose, lam, z)
    assert torch.equal(new_z["pos"], ref["pos"]) and all(not torch.allclose(new_z[k], ref[k]) for k in attrs)
    assert not torch.allclose(new_x["pos"], ref["pos"]) and all(torch.equal(new_x[k], ref[k]) for k in attrs)
    assert not torch.allclose(field(x, -code, pose, lam, z)["feature"], ref["feature"])  # still code-driven
    with pytest.raises(ToolkitError, match=r"field_input='feature' needs z \[N=40, 8\]"):
        field(x, code, pose, lam)

    pos = FaceDeformationField(D, 12, 6, 16, 3, 2, 2)
    _live(pos.expr_mlp, pos.pose_mlp)
    a, b = pos(x, code, pose, lam, z), pos(x, code, pose, lam, z + 1.0)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_feature_input_in_the_model_trains_z0_through_the_field(scene):
    """z₀ is not detached (as GazeGaussian's): its gradient also comes through the deltas it conditions."""
    model = small_model(scene, field_input="feature")
    _live(model.face_field.expr_attr_mlp, model.face_field.pose_attr_mlp)
    code, pose, _, _, _ = model_inputs(2)
    face = model.face_stream(code, pose)
    g_all = torch.autograd.grad(face["scales"].sum() + face["opacities"].sum(), model.face_features)[0]
    assert float(g_all.abs().sum()) > 0  # scales and opacities reach z₀ only through the attribute MLPs


def test_eye_terms_get_gradients_and_trained_eyes_follow_the_gaze(scene):
    """The zero-initialized last layer still gets a gradient at step 0; a few steps later the eye Gaussians'
    features and opacities depend on the gaze (they did not before: the default eyes only rotate)."""
    model = small_model(scene, eye_field_terms=True)
    code, pose, gaze, vm, K = model_inputs(2, seed=2)
    target = torch.rand(2, model.config.feature_dim, 16, 16)
    opt = torch.optim.Adam(model.eye_gaze_terms.parameters(), lr=1e-2)
    for step in range(3):
        out = model(code, pose, gaze, vm, K, 64, 64, renders=("eyes",))
        loss = (out["eyes"] - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        if step == 0:
            assert float(model.eye_gaze_terms.mlp.last.weight.grad.abs().sum()) > 0
        opt.step()
    with torch.no_grad():
        a = model.eye_stream(code, torch.zeros(2, 2))
        b = model.eye_stream(code, torch.full((2, 2), 0.4))
    for k in ("features", "opacities", "scales"):
        assert not torch.allclose(a[k], b[k]), k
    bound = model.config.max_opacity_delta
    logits = torch.logit(a["opacities"].clamp(1e-6, 1 - 1e-6)) - model.eye_opacity_logits.detach()
    assert float(logits.abs().max()) <= bound + 1e-3  # the terms stay bounded


def test_eye_terms_with_eyeball_colours_leave_the_rgb_parametric(scene):
    model = small_model(scene, eye_field_terms=True, eyeball_colours=True)
    _live(model.eye_gaze_terms.mlp)
    code = model_inputs(2)[0]
    with torch.no_grad():
        a, b = model.eye_stream(code, torch.zeros(2, 2)), model.eye_stream(code, torch.full((2, 2), -0.5))
    assert torch.equal(a["features"][..., :3], b["features"][..., :3])
    assert not torch.allclose(a["features"][..., 3:], b["features"][..., 3:])


def test_eye_gaze_field_alone_shapes_and_zero_start():
    field = EyeGazeAppearanceField(feature_dim=6, hidden=8, depth=2, gaze_freqs=2)
    with torch.no_grad():
        d = field(torch.randn(10, 6), torch.randn(3, 2))
    assert d["feature"].shape == (3, 10, 6) and d["log_scale"].shape == (3, 10) and d["opacity"].shape == (3, 10)
    assert all(float(v.abs().max()) == 0 for v in d.values())


@pytest.mark.parametrize("autocast", [False, True], ids=["fp32", "bf16"])
def test_switches_stay_finite_at_extreme_gazes_and_huge_features(scene, autocast):
    model = small_model(scene, field_input="feature", eye_field_terms=True)
    _live(*_field_mlps(model), std=1.0)
    with torch.no_grad():
        model.face_features.mul_(1e4)
        model.eye_features.mul_(-1e4)
    code, pose, _, vm, K = model_inputs(4)
    deg89 = math.radians(89)
    gaze = torch.tensor([[deg89, deg89], [-deg89, -deg89], [deg89, -deg89], [0.0, 0.0]])
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        out = model(code * 1e3, pose, gaze, vm, K, 32, 32)
        loss = sum(v.float().mean() for v in out.values())
    assert all(torch.isfinite(v).all() for v in out.values())
    loss.backward()
    bad = [n for n, p in model.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
    assert not bad, bad
    assert float(model.eye_gaze_terms.mlp.first.weight.grad.abs().sum()) > 0
    assert float(model.face_field.expr_attr_mlp.last.weight.grad.abs().sum()) > 0


def test_save_and_load_round_trip_the_switches(scene, tmp_path):
    model = small_model(scene, field_input="feature", eye_field_terms=True)
    _live(*_field_mlps(model))
    path = tmp_path / "m.safetensors"
    model.save(path)
    back = GaussianModel.load(path)
    assert back.config.field_input == "feature" and back.config.eye_field_terms
    ref, got = model.state_dict(), back.state_dict()
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)
    assert any(k.startswith("eye_gaze_terms.") for k in got) and any(".expr_attr_mlp." in k for k in got)
    inputs = model_inputs(1)
    with torch.no_grad():
        assert torch.equal(model(*inputs, 32, 32)["head"], back(*inputs, 32, 32)["head"])


def test_a_file_written_before_the_switches_loads_with_them_off(scene, tmp_path):
    from toolkit.io import load_checkpoint, save_checkpoint

    path = tmp_path / "old.safetensors"
    small_model(scene).save(path)
    state, info = load_checkpoint(path)
    for key in ("field_input", "eye_field_terms"):
        del info["config"][key]
    save_checkpoint(path, state, info)
    back = GaussianModel.load(path)
    assert back.config.field_input == "position" and back.eye_gaze_terms is None
    # A file whose config asks for the terms but holds no weights for them is refused in one line.
    info["config"]["eye_field_terms"] = True
    save_checkpoint(path, state, info)
    with pytest.raises(ToolkitError, match=r"tensors do not match the stored config .*eye_gaze_terms"):
        GaussianModel.load(path)


def test_a_file_with_a_bad_switch_value_is_refused_naming_the_file_and_the_key(scene, tmp_path):
    from toolkit.io import load_checkpoint, save_checkpoint

    path = tmp_path / "bad.safetensors"
    small_model(scene).save(path)
    state, info = load_checkpoint(path)
    info["config"]["field_input"] = "z0"
    save_checkpoint(path, state, info)
    with pytest.raises(ToolkitError) as err:
        GaussianModel.load(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: ") and "field_input" in msg and "'z0'" in msg and "\n" not in msg


def test_config_errors_name_the_key():
    with pytest.raises(ToolkitError, match=r"GaussianModelConfig\.field_input: expected one of \['position', 'feature'\]"):
        GaussianModelConfig(field_input="z0").validate()
