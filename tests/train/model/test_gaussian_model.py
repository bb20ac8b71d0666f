"""Two-stream Gaussian model: initialization, eye rotation about each eye's own centre, face cache, renders,
orthogonality through the real fields."""

from __future__ import annotations

import math

import pytest
import torch

from tests.train.helpers import model_inputs, rasterizer_for_tests, small_model
from toolkit.errors import ToolkitError
from toolkit.eyes import gaze_rotation, rotate_about
from toolkit.procedural import demo_head_scene
from train.losses import OrthogonalityLoss
from train.model.gaussian_config import GaussianModelConfig
from train.model.gaussian_model import GaussianModel


def test_from_scene_splits_streams_and_lifts_features():
    scene = demo_head_scene(600)
    model = small_model(scene)
    n_face = int((scene.part == 0).sum())
    assert model.num_face == n_face and model.num_eye == scene.num_gaussians - n_face
    assert model.face_features.shape == (n_face, 32)
    assert torch.allclose(model.face_features[:, :3], scene.features[scene.part == 0])
    assert float(model.face_features.detach()[:, 3:].abs().sum()) == 0
    # Eyes isotropic: one log-scale per Gaussian; sides follow the part labels.
    assert model.eye_log_scales.dim() == 1
    assert int((model.eye_side == 0).sum()) == int((scene.part == 1).sum())
    c = torch.tensor([scene.metadata["eyes"]["left"]["center"], scene.metadata["eyes"]["right"]["center"]])
    assert torch.allclose(model.eye_centers, c)


def test_from_scene_rejects_bad_scenes():
    scene = demo_head_scene(600)
    with pytest.raises(ToolkitError, match="eye"):
        GaussianModel.from_scene(scene.select(scene.part != 2), GaussianModelConfig(hidden=16))
    bad = scene.clone()
    bad.metadata["units"] = "furlong"
    with pytest.raises(ToolkitError, match="units"):
        GaussianModel.from_scene(bad)
    with pytest.raises(ToolkitError, match="near_m"):
        GaussianModel.from_scene(scene, GaussianModelConfig(near_m=0.05, far_m=0.01))
    with pytest.raises(ToolkitError, match="from_scene: landmarks contain NaN/inf"):
        GaussianModel.from_scene(scene, GaussianModelConfig(hidden=16), landmarks=torch.full((5, 3), float("nan")))


def test_eyes_rotate_rigidly_about_their_own_centres():
    scene = demo_head_scene(600)
    model = small_model(scene)
    code, pose, _, _, _ = model_inputs(1)
    gaze = torch.tensor([[0.4, -0.6]])
    eyes = model.gaussians(code, pose, gaze)["eyes"]
    for side, name, part in ((0, "left", 1), (1, "right", 2)):
        sel = model.eye_side == side
        c = torch.tensor(scene.metadata["eyes"][name]["center"])
        canon = model.eye_means[sel].detach()
        moved = eyes["means"][0, sel].detach()
        # Zero-initialized residual: exactly the analytic rotation about this eye's own centre.
        expect, _ = rotate_about(canon, torch.zeros(len(canon), 4), gaze_rotation(gaze[0]), c)
        assert torch.allclose(moved, expect, atol=1e-6)
        # The eye moved, its centre did not: distances to its own centre are preserved.
        assert float((moved - canon).norm(dim=-1).max()) > 0.003
        assert torch.allclose((moved - c).norm(dim=-1), (canon - c).norm(dim=-1), atol=1e-6)
        assert torch.equal(scene.means[scene.part == part], canon)


def test_eye_centres_are_fixed_points_and_each_eye_uses_its_own():
    scene = demo_head_scene(600)
    model = small_model(scene)
    torch.nn.init.normal_(model.eye_field.mlp.last.weight, std=1.0)
    with torch.no_grad():  # put one Gaussian of each eye exactly on its eyeball centre
        for side in (0, 1):
            first = int(torch.nonzero(model.eye_side == side)[0])
            model.eye_means[first] = model.eye_centers[side]
    code, pose, _, _, _ = model_inputs(1)
    g = model.gaussians(code, pose, torch.tensor([[0.7, -1.2]]))["eyes"]["means"][0].detach()
    for side in (0, 1):
        first = int(torch.nonzero(model.eye_side == side)[0])
        assert torch.allclose(g[first], model.eye_centers[side], atol=1e-6)
    # Swapping which Gaussians belong to which eye changes the result (no shared landmarks or centre).
    model.eye_side = 1 - model.eye_side
    g2 = model.gaussians(code, pose, torch.tensor([[0.7, -1.2]]))["eyes"]["means"][0].detach()
    assert float((g2 - g).abs().max()) > 0.01


def test_learned_residual_keeps_each_eye_rigid_about_its_own_centre():
    scene = demo_head_scene(600)
    model = small_model(scene)
    torch.nn.init.normal_(model.eye_field.mlp.last.weight, std=1.0)  # a non-trivial residual rotation
    code, pose, _, _, _ = model_inputs(2, seed=1)
    gaze = torch.tensor([[0.3, 0.2], [-0.5, 0.9]])
    g = model.gaussians(code, pose, gaze)["eyes"]
    R = g["rotations"]
    assert not torch.allclose(R[:, 0], R[:, 1], atol=1e-3)  # left and right get their own rotations
    for side in (0, 1):
        sel = model.eye_side == side
        c = model.eye_centers[side]
        canon = model.eye_means[sel].detach()
        for b in range(2):
            expect = (canon - c) @ R[b, side].T + c
            assert torch.allclose(g["means"][b, sel].detach(), expect.detach(), atol=1e-6)
            assert torch.allclose(torch.linalg.det(R[b, side]).detach(), torch.tensor(1.0), atol=1e-5)


def test_frontal_gaze_and_zero_pose_leave_canonical_geometry():
    scene = demo_head_scene(600)
    model = small_model(scene)
    code, pose, _, _, _ = model_inputs(1)
    g = model.gaussians(code, pose, torch.zeros(1, 2))
    assert torch.allclose(g["eyes"]["means"][0], model.eye_means, atol=1e-6)
    assert torch.allclose(g["face"]["means"][0], model.face_means, atol=1e-6)


def test_head_pose_is_a_rigid_transform_of_everything():
    scene = demo_head_scene(600)
    model = small_model(scene)
    model.face_field.pose_mlp.last.weight.data.zero_()
    code = torch.zeros(1, 144)
    pose = torch.tensor([[0.1, -0.3, 0.05, 0.01, 0.02, -0.03]])
    g = model.gaussians(code, pose, torch.zeros(1, 2))
    from toolkit.rotations import so3_exp

    R = so3_exp(pose[0, :3])
    # Zero-init fields: the posed face is exactly R x + t of the canonical one.
    assert torch.allclose(g["face"]["means"][0].detach(), model.face_means.detach() @ R.T + pose[0, 3:], atol=1e-6)
    assert torch.allclose(g["eyes"]["means"][0].detach(), model.eye_means.detach() @ R.T + pose[0, 3:], atol=1e-6)


def test_expression_weights_follow_landmark_distance():
    scene = demo_head_scene(600)
    model = small_model(scene)
    lam = model.expression_weights()
    d = torch.cdist(model.face_means.detach(), model.landmarks).min(1).values
    assert bool((lam[d < 0.02] == 1).all()) and bool((lam[d > 0.05] == 0).all())
    mid = (d > 0.021) & (d < 0.049)
    assert bool(((lam[mid] > 0) & (lam[mid] < 1)).all())
    # Units: the same scene in millimetres gives the same weights.
    mm = scene.clone()
    mm.means = mm.means * 1000
    mm.metadata["units"] = "mm"
    mm.metadata["eyes"] = {k: {"center": [1000 * x for x in v["center"]], "radius": 1000 * v["radius"]}
                           for k, v in scene.metadata["eyes"].items()}
    assert torch.allclose(small_model(mm).expression_weights(), lam, atol=1e-5)


def test_face_stream_cached_when_only_gaze_changes():
    scene = demo_head_scene(600)
    model = small_model(scene)
    code, pose, gaze, viewmats, Ks = model_inputs(1)
    r = ("face", "eyes")
    with torch.no_grad():
        out1 = model(code, pose, gaze, viewmats, Ks, 64, 64, renders=r)
        misses = model.cache_misses
        out2 = model(code, pose, gaze + 0.2, viewmats, Ks, 64, 64, renders=r)
        assert model.cache_misses == misses and model.cache_hits >= 1
        assert torch.equal(out1["face"], out2["face"])
        assert not torch.equal(out1["eyes"], out2["eyes"])
        model.gaussians(code + 0.1, pose, gaze)  # a new code: recomputed
        assert model.cache_misses == misses + 1
        model.gaussians(code + 0.1, pose * 1.1 + 0.01, gaze)  # a new pose: recomputed
        assert model.cache_misses == misses + 2
        model.gaussians(code + 0.1, pose * 1.1 + 0.01, gaze - 0.3)  # gaze only: hit
        assert model.cache_misses == misses + 2


def test_cache_invalidated_when_parameters_change():
    scene = demo_head_scene(600)
    model = small_model(scene)
    code, pose, gaze, _, _ = model_inputs(1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    for _ in range(2):
        opt.zero_grad()
        g = model.gaussians(code, pose, gaze)
        (g["face"]["features"].square().mean() + g["face"]["means"].square().mean()).backward()
        opt.step()
    assert model.cache_misses == 2 and model.cache_hits == 0
    # Gaze-only change within one step reuses the face output and backward through the sum works.
    opt.zero_grad()
    a = model.gaussians(code, pose, gaze)
    b = model.gaussians(code, pose, gaze + 0.3)
    assert model.cache_hits == 1
    (a["face"]["means"].sum() + b["face"]["means"].sum() + b["eyes"]["means"].sum()).backward()
    assert torch.isfinite(model.face_means.grad).all()


def test_renders_shapes_skipping_and_white_background():
    scene = demo_head_scene(800)
    model = small_model(scene)
    code, pose, gaze, viewmats, Ks = model_inputs(2, width=128, height=96)
    with torch.no_grad():
        out = model(code, pose, gaze, viewmats, Ks, 128, 96)
    for r in ("head", "face", "eyes"):
        assert out[r].shape == (2, 32, 24, 32) and out[r + "_alpha"].shape == (2, 1, 24, 32)
        assert torch.isfinite(out[r]).all()
    assert torch.equal(out["rgb"], out["head"][:, :3])
    # Corners are background: RGB white, other channels 0.
    assert torch.allclose(out["head"][:, :3, 0, 0], torch.ones(2, 3), atol=1e-3)
    assert float(out["head"][:, 3:, 0, 0].abs().max()) < 1e-3
    # The head covers the centre; the eyes-only render covers less than the head.
    assert float(out["head_alpha"][:, 0, 12, 16].min()) > 0.5
    assert float(out["eyes_alpha"].sum()) < float(out["head_alpha"].sum())
    model.clear_cache()
    calls = []
    model._rasterizer = _counting(rasterizer_for_tests(), calls)
    with torch.no_grad():
        only = model(code, pose, gaze, viewmats, Ks, 128, 96, renders=("head",))
    assert set(only) == {"head", "head_alpha", "rgb"} and len(calls) == 1  # one call for the batch, head only
    misses = model.cache_misses
    with torch.no_grad():
        eyes_only = model(code, pose, gaze, viewmats, Ks, 128, 96, renders=("eyes",))
    assert set(eyes_only) == {"eyes", "eyes_alpha"} and model.cache_misses == misses  # face stream not evaluated
    with pytest.raises(ToolkitError, match="renders"):
        model(code, pose, gaze, viewmats, Ks, 128, 96, renders=("mouth",))


def _counting(fn, calls):
    def wrapped(*a, **k):
        calls.append(1)
        return fn(*a, **k)
    return wrapped


def test_gaze_changes_only_the_eye_region_of_the_head_render():
    scene = demo_head_scene(1500)
    model = small_model(scene)
    code, pose, _, viewmats, Ks = model_inputs(1, width=128, height=128)
    with torch.no_grad():
        a = model(code, pose, torch.zeros(1, 2), viewmats, Ks, 128, 128, renders=("head", "face"))
        b = model(code, pose, torch.tensor([[0.0, 0.6]]), viewmats, Ks, 128, 128, renders=("head", "face"))
    assert torch.equal(a["face"], b["face"])
    diff = (a["head"][0, :3] - b["head"][0, :3]).abs().sum(0)
    assert float(diff.max()) > 0.05
    # All changed pixels lie in the upper-middle band where the eyes are (rows above the image centre).
    rows = torch.nonzero(diff > 0.05)[:, 0]
    assert int(rows.max()) < 20


def test_auto_decoder_codes_and_camera_offsets():
    scene = demo_head_scene(600)
    model = small_model(scene, num_images=5)
    torch.nn.init.normal_(model.face_field.expr_mlp.last.weight, std=0.1)  # zero-init would block the code's gradient
    code, pose, gaze, viewmats, Ks = model_inputs(2)
    idx = torch.tensor([1, 3])
    out = model(code, pose, gaze, viewmats, Ks, 64, 64, image_index=idx, renders=("head",))
    out["head"].mean().backward()
    assert model.image_codes.weight.grad is not None
    g = model.image_codes.weight.grad
    assert float(g[[0, 2, 4]].abs().sum()) == 0 and float(g[idx].abs().sum()) > 0
    assert model.camera_offsets.weight.grad is not None and float(model.camera_offsets.weight.grad[idx].abs().sum()) > 0
    with pytest.raises(ToolkitError, match="num_images"):
        small_model(scene)(code, pose, gaze, viewmats, Ks, 64, 64, image_index=idx)


def test_orthogonality_loss_on_the_real_fields():
    scene = demo_head_scene(600)
    model = small_model(scene)
    ortho = OrthogonalityLoss(*model.orthogonality_layers())
    code, pose, gaze, _, _ = model_inputs(2)
    code = code.clone().requires_grad_(True)
    model.gaussians(code, pose, gaze)
    loss = ortho()
    loss.backward()
    first = {id(p) for layer in model.orthogonality_layers() for p in layer.parameters()}
    for name, p in model.named_parameters():
        if id(p) in first:
            assert p.grad is not None and float(p.grad.abs().sum()) > 0, name
        else:
            assert p.grad is None, name
    assert code.grad is None
    ortho.remove()


def test_input_shapes_are_checked():
    scene = demo_head_scene(600)
    model = small_model(scene)
    code, pose, gaze, viewmats, Ks = model_inputs(2)
    with pytest.raises(ToolkitError, match="code"):
        model.gaussians(code[:, :10], pose, gaze)
    with pytest.raises(ToolkitError, match="gaze"):
        model.gaussians(code, pose, gaze[:, :1])
    with pytest.raises(ToolkitError, match="viewmats"):
        model(code, pose, gaze, viewmats[:1], Ks, 64, 64)


@pytest.mark.parametrize("field, value, match", [
    ("max_offset", float("nan"), r"GaussianModelConfig.max_offset: expected a finite number, got nan"),
    ("near_m", float("nan"), r"GaussianModelConfig.near_m: expected a finite number, got nan"),
    ("max_eye_residual", float("nan"), r"GaussianModelConfig.max_eye_residual: expected a finite number"),
    ("max_opacity_delta", float("nan"), r"GaussianModelConfig.max_opacity_delta: expected a finite number"),
    ("max_offset", -1.0, r"GaussianModelConfig.max_offset: expected a bound >= 0, got -1.0"),
    ("pose_dim", 3, r"GaussianModelConfig.pose_dim: expected 6 \(axis-angle 3 \+ translation 3\), got 3"),
    ("depth", -1, r"GaussianModelConfig.depth: expected a layer count >= 1, got -1"),
    ("hidden", 0, r"GaussianModelConfig.hidden: expected a layer width >= 1, got 0"),
    ("pos_freqs", -1, r"GaussianModelConfig.pos_freqs: expected a frequency count >= 0, got -1"),
    ("num_images", -1, r"GaussianModelConfig.num_images: expected an image count >= 0"),
    ("feature_dim", -1, r"GaussianModelConfig.feature_dim: expected a channel count >= 3")])
def test_config_values_no_model_can_use_are_refused_by_name(field, value, match):
    """Each is one line naming the field, when the model is built: not a splatter error at the first render
    (NaN bounds), a shape error there (pose_dim), or a model built silently (negative sizes)."""
    with pytest.raises(ToolkitError, match=match):
        GaussianModelConfig(**{"hidden": 16, field: value}).validate()
    with pytest.raises(ToolkitError, match=match):
        GaussianModel.from_scene(demo_head_scene(300), GaussianModelConfig(**{"hidden": 16, field: value}))


def test_render_calls_without_a_camera_size_or_image_are_refused_by_name():
    """B = 0 cameras, an empty or negative output size and bad auto-decoder indices name the argument, instead of a
    division by zero in the splatter or the intrinsics, an 8x1 map, or an embedding's IndexError."""
    scene = demo_head_scene(300)
    model = small_model(scene, num_images=2)
    code, pose, gaze, viewmats, Ks = model_inputs(1, width=16, height=16)
    with pytest.raises(ToolkitError, match=r"code: expected at least one camera to render \(B >= 1\), got \[0, 144\]"):
        model(code[:0], pose[:0], gaze[:0], viewmats[:0], Ks[:0], 16, 16)
    for w, h in ((0, 16), (-8, 16), (16, 0)):
        with pytest.raises(ToolkitError, match=r"width/height: expected an output size >= 1 pixel each"):
            model(code, pose, gaze, viewmats, Ks, w, h)
    with pytest.raises(ToolkitError, match=r"image_index: expected indices in \[0, 2\) \(config.num_images = 2\), got \[5\]"):
        model(code, pose, gaze, viewmats, Ks, 16, 16, image_index=torch.tensor([5]))
    with pytest.raises(ToolkitError, match=r"image_index: expected indices in \[0, 2\).*got \[-1\]"):
        model.gaussians(code, pose, gaze, image_index=torch.tensor([-1]))
    with pytest.raises(ToolkitError, match=r"image_index: expected \[B=1\] training-image indices, got \[2\]"):
        model(code, pose, gaze, viewmats, Ks, 16, 16, image_index=torch.tensor([0, 1]))
    assert model(code, pose, gaze, viewmats, Ks, 16, 16, image_index=torch.tensor([1]))["head"].shape == (1, 32, 4, 4)
    assert model(code[:0], pose[:0], gaze[:0], viewmats[:0], Ks[:0], 16, 16, renders=()) == {}


def test_export_scene_round_trips_through_the_scene_format(tmp_path):
    from toolkit.scene import GaussianScene

    scene = demo_head_scene(600)
    model = small_model(scene)
    code, pose, gaze, _, _ = model_inputs(1)
    out = model.export_scene(code, pose, torch.tensor([[0.2, math.radians(30)]]))
    out.save(tmp_path / "s.safetensors")
    back = GaussianScene.load(tmp_path / "s.safetensors")
    assert back.num_gaussians == scene.num_gaussians and back.features.shape[1] == 32
    assert torch.equal(back.part.sort().values, scene.part.sort().values)


def test_checkpoint_round_trip(tmp_path):
    scene = demo_head_scene(600)
    model = small_model(scene, num_images=3)
    torch.nn.init.normal_(model.face_field.expr_mlp.last.weight, std=0.1)
    with torch.no_grad():
        model.image_codes.weight.normal_()
    path = tmp_path / "gm.safetensors"
    model.save(path, {"step": 7})
    back = GaussianModel.load(path, rasterizer=model._rasterizer)
    code, pose, gaze, _, _ = model_inputs(2)
    idx = torch.tensor([0, 2])
    a = model.gaussians(code, pose, gaze, idx)
    b = back.gaussians(code, pose, gaze, idx)
    for s in ("face", "eyes"):
        for k in a[s]:
            assert torch.equal(a[s][k], b[s][k]), (s, k)
    from toolkit.io import save_checkpoint

    save_checkpoint(tmp_path / "other.safetensors", {"x": torch.zeros(1)}, {"kind": "nope"})
    with pytest.raises(ToolkitError, match="not a Gaussian model"):
        GaussianModel.load(tmp_path / "other.safetensors")
    with pytest.raises(ToolkitError, match="no such"):
        GaussianModel.load(tmp_path / "missing.safetensors")


def test_eyes_follow_the_socket_the_face_field_moves():
    scene = demo_head_scene(600)
    plain, follow = small_model(scene), small_model(scene, eyes_follow_face=True)
    code, pose, gaze, viewmats, Ks = model_inputs(2)
    # A face field that moves each face Gaussian by its own offset: the left half by t_l, the right by t_r.
    t_l, t_r = torch.tensor([0.004, -0.002, 0.001]), torch.tensor([-0.003, 0.001, 0.002])
    real = follow.face_stream

    def shifted(c, p):
        out = dict(real(c, p))
        right = (follow.face_means[:, 0] > 0).float()[:, None]
        out["means"] = (follow.face_means + (1 - right) * t_l + right * t_r).expand(c.shape[0], -1, -1)
        return out

    follow.face_stream = shifted
    a = plain.gaussians(code, pose, gaze)["eyes"]["means"]
    b = follow.gaussians(code, pose, gaze)["eyes"]["means"]
    # Each eye translates rigidly by its socket's displacement (the weights sit on its own side: the other
    # side's share is ~1e-4, so ~1e-6 m of leakage).
    for side, t in ((0, t_l), (1, t_r)):
        sel = follow.eye_side == side
        assert torch.allclose(b[:, sel] - a[:, sel], t.expand(2, int(sel.sum()), 3), atol=1e-5)
    assert torch.allclose(follow.socket_weights.sum(-1), torch.ones(2))


def test_eye_pixels_train_the_face_field_only_when_eyes_follow():
    scene = demo_head_scene(600)
    grads = {}
    for flag in (False, True):
        model = small_model(scene, eyes_follow_face=flag)
        torch.nn.init.normal_(model.face_field.expr_mlp.last.weight, std=0.1)  # not the zero-initialized field
        code, pose, gaze, viewmats, Ks = model_inputs(1)
        out = model(code * 50, pose, gaze, viewmats, Ks, 64, 64, renders=("eyes",))  # huge code: still finite
        assert torch.isfinite(out["eyes"]).all()
        out["eyes"][:, :3].sum().backward()
        g = model.face_field.expr_mlp.last.weight.grad
        grads[flag] = 0.0 if g is None else float(g.abs().sum())
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    assert grads[False] == 0.0 and grads[True] > 0.0
    with pytest.raises(ToolkitError, match="socket_sigma_m"):
        small_model(scene, socket_sigma_m=0.0)


@pytest.mark.parametrize("key,value,match", [
    ("eye_centers", torch.zeros(3), r"tensor 'eye_centers' has shape \[3\], expected \[2, 3\]"),
    ("face_means", torch.zeros(5, 2), r"tensor 'face_means' has shape \[5, 2\], expected \[N, 3\]"),
    ("eye_side", torch.zeros(3, dtype=torch.long), r"tensor 'eye_side' has shape \[3\], expected \[N\] with N = "),
    ("landmarks", torch.zeros(4, 2), r"tensor 'landmarks' has shape \[4, 2\], expected \[\*, 3\]"),
    ("config", {"hidden": "32"}, r"cannot build the model from its config"),
])
def test_a_checkpoint_whose_parts_disagree_is_one_clear_error(tmp_path, key, value, match):
    from toolkit.io import load_checkpoint, save_checkpoint

    small_model(demo_head_scene(600)).save(tmp_path / "gm.safetensors")
    state, info = load_checkpoint(tmp_path / "gm.safetensors")
    if key == "config":
        info["config"] = {**info["config"], **value}
    else:
        state[key] = value
    save_checkpoint(tmp_path / "bad.safetensors", state, info)
    with pytest.raises(ToolkitError, match=r"bad\.safetensors: " + match):
        GaussianModel.load(tmp_path / "bad.safetensors")


def test_checkpoint_without_socket_weights_still_loads(tmp_path):
    from toolkit.io import load_checkpoint, save_checkpoint

    model = small_model(demo_head_scene(600), eyes_follow_face=True)
    model.save(tmp_path / "new.safetensors")
    state, info = load_checkpoint(tmp_path / "new.safetensors")
    del state["socket_weights"]
    info["config"] = {k: v for k, v in info["config"].items() if k not in ("eyes_follow_face", "socket_sigma_m")}
    save_checkpoint(tmp_path / "old.safetensors", state, info)
    old = GaussianModel.load(tmp_path / "old.safetensors")
    assert not old.config.eyes_follow_face and torch.allclose(old.socket_weights, model.socket_weights)


def test_batch_renders_each_sample_with_its_own_camera_and_pose():
    """One rasterize call renders the batch; sample b must come out as if rendered alone."""
    from toolkit.procedural import demo_camera

    model = small_model(demo_head_scene(600))
    code, pose, gaze, viewmats, Ks = model_inputs(2, seed=5)
    pose[1, :3] = torch.tensor([0.1, -0.2, 0.05])
    viewmats[1] = demo_camera(64, 64, distance=0.7).viewmat
    with torch.no_grad():
        both = model(code, pose, gaze, viewmats, Ks, 64, 64)
        for b in range(2):
            alone = model(code[b:b + 1], pose[b:b + 1], gaze[b:b + 1], viewmats[b:b + 1], Ks[b:b + 1], 64, 64)
            for r in ("head", "face", "eyes", "head_alpha"):
                torch.testing.assert_close(both[r][b:b + 1], alone[r], atol=1e-5, rtol=0)
    assert not torch.allclose(both["head"][0], both["head"][1], atol=1e-3)



def test_eye_appearance_gives_each_code_its_own_eyes(tmp_path):
    scene = demo_head_scene(600)
    plain = small_model(scene)
    model = small_model(scene, eye_appearance=True)
    code, pose, gaze, _, _ = model_inputs(2)
    # Zero-initialized: at the start the eyes are the shared ones, whatever the code.
    a, b = model.gaussians(code, pose, gaze)["eyes"], plain.gaussians(code, pose, gaze)["eyes"]
    assert torch.equal(a["features"], b["features"])
    # Eyeball-frame positions in units of each eye's own extent: both eyes reach exactly 1.
    x = (model.eye_means.detach() - model.eye_centers[model.eye_side]) / model.eye_radius[model.eye_side, None]
    for side in (0, 1):
        assert float(x[model.eye_side == side].norm(dim=-1).max()) == pytest.approx(1.0, abs=1e-5)
    torch.nn.init.normal_(model.eye_appearance.mlp.last.weight, std=0.1)
    f = model.gaussians(code, pose, gaze)["eyes"]["features"]
    assert not torch.allclose(f[0], f[1])  # two codes, two sets of eye colours
    assert (f - model.eye_features).abs().max() <= model.config.max_feature_delta + 1e-6
    # Colours only: the eye geometry is the same as without the field.
    g = model.gaussians(code, pose, gaze)["eyes"]
    for k in ("means", "scales", "opacities"):
        assert torch.equal(g[k], b[k]), k
    # A colour loss reaches the code and the field, never the eye Gaussians' positions.
    c = code.clone().requires_grad_(True)
    model.eye_stream(c, gaze)["features"].square().sum().backward()
    assert c.grad is not None and float(c.grad.abs().sum()) > 0
    assert model.eye_appearance.mlp.first.weight.grad is not None
    assert model.eye_means.grad is None or float(model.eye_means.grad.abs().sum()) == 0
    # The stored radius comes back as saved, not recomputed from the (since trained) eye centres.
    with torch.no_grad():
        model.eye_means.mul_(1.1)
    f = model.gaussians(code, pose, gaze)["eyes"]["features"]
    path = tmp_path / "gm.safetensors"
    model.save(path)
    back = GaussianModel.load(path, rasterizer=model._rasterizer)
    assert back.eye_radius.tolist() == model.eye_radius.tolist()
    assert torch.equal(back.gaussians(code, pose, gaze)["eyes"]["features"], f)


def test_eye_appearance_field_equals_its_mlp_on_the_joined_input():
    from train.model.fields import EyeAppearanceField, positional_encoding

    torch.manual_seed(0)
    field = EyeAppearanceField(8, 12, 16, 3, 2).double()
    for p in field.parameters():
        torch.nn.init.normal_(p, std=0.3)
    x, side, code = torch.randn(10, 3).double(), torch.tensor([0, 1] * 5), torch.randn(3, 12).double()
    where = torch.cat([positional_encoding(x, 2), torch.nn.functional.one_hot(side, 2).double()], -1)
    joined = torch.cat([where[None].expand(3, -1, -1), code[:, None].expand(-1, 10, -1)], -1)
    assert torch.allclose(field(x, side, code), field.mlp(joined), atol=1e-12)


def test_eyeball_colours_draw_a_pupil_an_iris_and_a_sclera_about_each_axis(tmp_path):
    scene = demo_head_scene(600)
    model = small_model(scene, eyeball_colours=True)
    ball = model.eyeball_colours
    # Three Gaussians of each eye moved onto its pupil, its iris and its sclera (the sparse test head has few there).
    with torch.no_grad():
        for side in (0, 1):
            k = torch.nonzero(model.eye_side == side)[:3, 0]
            c = model.eye_centers[side]
            r = float((model.eye_means[k[0]] - c).norm())
            for i, a in zip(k.tolist(), (0.0, 0.35, 0.9)):
                model.eye_means[i] = c + r * torch.tensor([math.sin(a) * 0.6, math.sin(a) * 0.8, -math.cos(a)])
    theta = model.eye_polar_angles()
    d = model.eye_means.detach() - model.eye_centers[model.eye_side]
    assert torch.allclose(theta, torch.acos((-d[:, 2] / d.norm(dim=-1)).clamp(-1, 1)), atol=1e-4)
    code, pose, gaze, _, _ = model_inputs(2)
    f = model.gaussians(code, pose, gaze)["eyes"]["features"]
    t_pupil, t_iris = (float(t.detach()) for t in ball.boundaries())
    e = 4 * ball.edge
    for where, colour in ((theta < t_pupil - e, ball.pupil), ((theta > t_pupil + e) & (theta < t_iris - e), ball.iris),
                          (theta > t_iris + e, ball.sclera)):
        assert int(where.sum()) > 0
        torch.testing.assert_close(f[0, where, :3], torch.sigmoid(colour.detach()).expand(int(where.sum()), 3),
                                   atol=0.02, rtol=0)
    assert torch.equal(f[0, :, 3:], model.eye_features[:, 3:].detach())  # the other channels stay free
    # A colour loss reaches the eyeball's numbers, not the Gaussians' positions or their free RGB.
    f[..., :3].square().sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() and float(p.grad.abs().sum()) > 0
               for p in ball.parameters())
    assert model.eye_means.grad is None or float(model.eye_means.grad.abs().sum()) == 0
    assert model.eye_features.grad is None or float(model.eye_features.grad[:, :3].abs().sum()) == 0
    path = tmp_path / "gm.safetensors"
    with torch.no_grad():
        ball.iris.fill_(2.0)
    model.save(path)
    back = GaussianModel.load(path, rasterizer=model._rasterizer)
    assert torch.equal(back.gaussians(code, pose, gaze)["eyes"]["features"], model.gaussians(code, pose, gaze)["eyes"]["features"])
    with pytest.raises(ToolkitError, match="eyeball_colours and eye_appearance"):
        small_model(scene, eyeball_colours=True, eye_appearance=True)


def test_eyeball_colours_keep_their_edges_ordered_and_finite_at_any_value():
    from train.model.fields import EyeballColours

    ball = EyeballColours()
    with torch.no_grad():
        for p, v in ((ball.pupil, 1e6), (ball.iris, -1e6), (ball.sclera, float("inf")),
                     (ball.theta_pupil, 50.0), (ball.theta_iris, -50.0)):
            p.fill_(v)
    t_pupil, t_iris = (t.detach() for t in ball.boundaries())
    assert ball.MIN_ANGLE <= float(t_pupil) < float(t_iris) <= ball.MAX_ANGLE
    theta = torch.tensor([0.0, 1e-9, 0.3, math.pi / 2, math.pi, 100.0])
    rgb = ball(theta).detach()
    assert torch.isfinite(rgb).all() and float(rgb.min()) >= 0 and float(rgb.max()) <= 1
    for bad in (dict(edge=0.0), dict(theta_pupil=0.6, theta_iris=0.5), dict(theta_iris=2.0), dict(edge=2.0),
                dict(theta_pupil=0.49, theta_iris=0.5)):
        with pytest.raises(ToolkitError, match="EyeballColours"):
            EyeballColours(**bad)
