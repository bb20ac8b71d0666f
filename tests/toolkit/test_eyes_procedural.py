import math

import pytest
import torch

from toolkit import ToolkitError
from toolkit.eyes import eyeball_info, fit_sphere, gaze_rotation, redirect_eyes
from toolkit.procedural import demo_camera, demo_head_scene, knn_spacing
from toolkit.rotations import pitchyaw_to_vector, quat_to_matrix


def test_fit_sphere_exact_and_degenerate():
    d = torch.nn.functional.normalize(torch.randn(200, 3, dtype=torch.float64), dim=-1)
    c0 = torch.tensor([10.0, -3.0, 2.5], dtype=torch.float64)
    c, r = fit_sphere(c0 + 0.012 * d)
    assert torch.allclose(c, c0, atol=1e-9) and r.item() == pytest.approx(0.012, rel=1e-7)
    with pytest.raises(ToolkitError, match="at least 4"):
        fit_sphere(torch.zeros(3, 3))
    # Coplanar points (here 5 in the z = 0 plane, not on one circle) or repeated ones determine no sphere.
    flat = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1.2, 0], [0.3, 0.5, 0]])
    for bad in (flat, torch.ones(6, 3), flat + torch.tensor([5.0, -2, 1])):
        with pytest.raises(ToolkitError, match="do not determine a sphere"):
            fit_sphere(bad)
    # A narrow cap (20 degrees across) still does, from float32 input.
    t = torch.linspace(0, 2 * math.pi, 40)
    cap = torch.stack([0.17 * t.cos(), 0.17 * t.sin(), torch.full_like(t, math.sqrt(1 - 0.17**2))], 1)
    cap = torch.cat([cap, torch.tensor([[0.0, 0.0, 1.0]])])
    c, r = fit_sphere(cap)
    assert torch.allclose(c, torch.zeros(3), atol=1e-4) and r.item() == pytest.approx(1.0, abs=1e-4)


def test_gaze_rotation_maps_frontal_to_gaze():
    py = torch.tensor([[0.3, -0.5], [-0.7, 1.2], [0.0, 0.0], [math.radians(89), 0.4]], dtype=torch.float64)
    R = gaze_rotation(py)
    g = R @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    assert torch.allclose(g, pitchyaw_to_vector(py), atol=1e-12)
    # No torsion: the eye's horizontal axis stays horizontal (y component 0).
    assert torch.allclose((R @ torch.tensor([1.0, 0, 0], dtype=torch.float64))[:, 1], torch.zeros(4, dtype=torch.float64))


def test_demo_head_is_valid_and_round_trips(tmp_path):
    s = demo_head_scene(2000, seed=3)
    assert len(s) == 2000 and set(s.part.unique().tolist()) == {0, 1, 2}
    info = eyeball_info(s)
    assert info["left"]["center"][0] < 0 < info["right"]["center"][0]  # left eye = image-left = x < 0
    for name, part in (("left", 1), ("right", 2)):
        d = (s.means[s.part == part] - info[name]["center"]).norm(dim=-1)
        assert torch.allclose(d, torch.full_like(d, 0.012), atol=1e-5)
    # Fitting from Gaussians (metadata removed) recovers the same centres.
    s2 = s.clone()
    s2.metadata.pop("eyes")
    info2 = eyeball_info(s2)
    assert torch.allclose(info2["left"]["center"], info["left"]["center"], atol=1e-5)
    s.save(tmp_path / "h.safetensors")
    s.to_ply(tmp_path / "h.ply")
    cam = demo_camera(128, 128)
    uv, z = cam.project(s.means)
    assert ((uv > 0) & (uv < 128)).all() and (z > 0).all()


def test_demo_head_deterministic():
    a, b = demo_head_scene(500, seed=1), demo_head_scene(500, seed=1)
    assert torch.equal(a.means, b.means) and torch.equal(a.features, b.features)
    assert not torch.equal(a.means, demo_head_scene(500, seed=2).means)


def test_redirect_eyes_rotates_about_each_centre():
    s = demo_head_scene(1000)
    info = eyeball_info(s)
    r = redirect_eyes(s, (0.3, -0.4))
    assert torch.equal(r.means[s.part == 0], s.means[s.part == 0])
    R = gaze_rotation(torch.tensor([0.3, -0.4]))
    for name, part in (("left", 1), ("right", 2)):
        m = s.part == part
        c = info[name]["center"]
        before, after = s.means[m] - c, r.means[m] - c
        # Rigid about this eye's own centre: the centre stays put and every offset turns by R.
        assert torch.allclose(after, before @ R.T, atol=1e-7)
        assert torch.allclose(quat_to_matrix(r.quats[m]), R @ quat_to_matrix(s.quats[m]), atol=1e-6)
    face_only = s.select(s.part == 0)
    with pytest.raises(ToolkitError, match="no eye Gaussians"):
        redirect_eyes(face_only, (0.1, 0.1))


def test_knn_spacing():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]])
    sp = knn_spacing(pts, k=3)
    assert sp[0].item() == pytest.approx(1.0)
    with pytest.raises(ToolkitError):
        knn_spacing(pts[:3])


@pytest.mark.parametrize("eyes, msg", [
    ({"left": {"center": "0 0 0", "radius": 0.012}}, r"eyes.left.center: expected 3 finite numbers"),
    ({"left": {"center": [0.0, 0.0], "radius": 0.012}}, r"eyes.left.center: expected 3 finite numbers"),
    ({"left": {"center": [0.0, float("nan"), 0.0], "radius": 0.012}}, r"eyes.left.center: expected 3 finite numbers"),
    ({"left": {"center": [0.0, 0.0, 0.0]}}, r"eyes.left.radius: expected a finite number > 0, got None"),
    ({"right": {"center": [0.0, 0.0, 0.0], "radius": -1}}, r"eyes.right.radius: expected a finite number > 0"),
    ({"right": [0.0, 0.0, 0.0]}, r"eyes.right: expected a mapping"),
    ([1, 2], r"scene metadata eyes: expected a mapping"),
])
def test_malformed_eye_metadata_is_one_clear_error(eyes, msg):
    s = demo_head_scene(300)
    s.metadata["eyes"] = eyes
    with pytest.raises(ToolkitError, match=msg):
        eyeball_info(s)
