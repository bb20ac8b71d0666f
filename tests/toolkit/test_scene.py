import pytest
import torch

from tests.conftest import random_scene
from toolkit import ToolkitError
from toolkit.scene import FORMAT_VERSION, GaussianScene


def _assert_scene_equal(a: GaussianScene, b: GaussianScene):
    for name in ("means", "quats", "log_scales", "opacity_logits", "features", "part"):
        ta, tb = getattr(a, name), getattr(b, name)
        assert ta.dtype == tb.dtype, name
        assert torch.equal(ta, tb), name
    assert (a.sh is None) == (b.sh is None)
    if a.sh is not None:
        assert torch.equal(a.sh, b.sh)
    assert a.metadata == b.metadata


@pytest.mark.parametrize("d,sh", [(3, None), (32, None), (3, 2), (1, 0)])
def test_safetensors_round_trip_is_exact(tmp_path, d, sh):
    s = random_scene(40, d=d, sh_degree=sh)
    p = tmp_path / "s.safetensors"
    s.save(p)
    _assert_scene_equal(s, GaussianScene.load(p))


def test_activated_properties():
    s = random_scene(10)
    assert torch.allclose(s.scales, s.log_scales.exp())
    assert torch.allclose(s.opacities, torch.sigmoid(s.opacity_logits))
    assert torch.allclose(s.unit_quats.norm(dim=-1), torch.ones(10))
    t = GaussianScene.from_activated(s.means, s.scales, s.opacities, s.features, s.quats, s.part)
    assert torch.allclose(t.opacities, s.opacities, atol=1e-6)
    assert torch.allclose(t.scales, s.scales, rtol=1e-6)
    # Saturated opacities (a trained model's sigmoid at a large logit) invert to finite logits in float32.
    sat = GaussianScene.from_activated(s.means[:3], s.scales[:3], torch.tensor([1.0, 0.0, 0.5]), s.features[:3])
    assert torch.isfinite(sat.opacity_logits).all() and sat.validate()
    assert sat.opacities[0] > 0.9999 and sat.opacities[1] < 1e-6


def test_select_cat_clone_to():
    s = random_scene(30)
    eyes = s.select(s.part_mask(1, 2))
    face = s.select(s.part == 0)
    assert len(eyes) + len(face) == 30
    both = GaussianScene.cat([face, eyes])
    assert len(both) == 30 and both.validate()
    c = s.clone()
    c.means += 1
    assert not torch.equal(c.means, s.means)
    assert s.to("cpu").device.type == "cpu"
    with pytest.raises(ToolkitError, match="mask"):
        s.select(torch.ones(5, dtype=torch.bool))
    with pytest.raises(ToolkitError, match="feature widths"):
        GaussianScene.cat([random_scene(3, d=3), random_scene(3, d=4)])


@pytest.mark.parametrize(
    "field,value,msg",
    [
        ("means", torch.zeros(5, 2), "means: expected shape"),
        ("quats", torch.zeros(4, 4), r"quats: expected shape \[5, 4\]"),
        ("log_scales", torch.zeros(5, 3, dtype=torch.int32), "log_scales: expected a floating"),
        ("opacity_logits", torch.tensor([0.0, float("nan"), 0, 0, 0]), "opacity_logits: 1 Gaussian"),
        ("features", torch.zeros(6, 3), "features: expected shape"),
        ("part", torch.zeros(5, dtype=torch.int64), "part: expected int8"),
        ("part", torch.full((5,), 7, dtype=torch.int8), "part: labels"),
        ("sh", torch.zeros(5, 3, 3), "sh: expected shape"),
    ],
)
def test_validate_names_field(field, value, msg):
    s = random_scene(5)
    setattr(s, field, value)
    with pytest.raises(ToolkitError, match=msg):
        s.validate()


def test_inf_means_rejected_on_save(tmp_path):
    s = random_scene(5)
    s.means[2, 1] = float("inf")
    with pytest.raises(ToolkitError, match="means"):
        s.save(tmp_path / "x.safetensors")
    assert not list(tmp_path.iterdir()), "no file (not even a temp file) may be left behind"


def test_empty_scene_round_trip(tmp_path):
    s = random_scene(0)
    s.save(tmp_path / "e.safetensors")
    assert len(GaussianScene.load(tmp_path / "e.safetensors")) == 0
    s.to_ply(tmp_path / "e.ply")
    assert len(GaussianScene.from_ply(tmp_path / "e.ply")) == 0


def test_newer_version_is_clear_error(tmp_path):
    from toolkit.io import save_tensors

    s = random_scene(4)
    meta = {"format": "ditgaze.gaussian_scene", "format_version": FORMAT_VERSION + 1}
    save_tensors(tmp_path / "new.safetensors", s.tensors(), meta)
    with pytest.raises(ToolkitError, match="version 2 is not supported"):
        GaussianScene.load(tmp_path / "new.safetensors")
    save_tensors(tmp_path / "other.safetensors", s.tensors(), {"format": "something"})
    with pytest.raises(ToolkitError, match="not a GaussianScene"):
        GaussianScene.load(tmp_path / "other.safetensors")


@pytest.mark.parametrize("content", [b"", b"garbage" * 10, bytes(range(256)) * 4])
def test_garbage_safetensors(tmp_path, content):
    p = tmp_path / "bad.safetensors"
    p.write_bytes(content)
    with pytest.raises(ToolkitError, match="bad.safetensors"):
        GaussianScene.load(p)


def test_truncated_safetensors(tmp_path):
    s = random_scene(100)
    p = tmp_path / "s.safetensors"
    s.save(p)
    p.write_bytes(p.read_bytes()[:-50])
    with pytest.raises(ToolkitError, match="s.safetensors"):
        GaussianScene.load(p)


def test_directory_and_missing_file(tmp_path):
    with pytest.raises(ToolkitError, match="is a directory"):
        GaussianScene.load(tmp_path)
    with pytest.raises(ToolkitError, match="no such"):
        GaussianScene.read(tmp_path / "missing.ply")
    with pytest.raises(ToolkitError, match="unknown scene extension"):
        GaussianScene.read(tmp_path / "x.obj")
    with pytest.raises(ToolkitError, match="is a directory"):
        random_scene(3).save(tmp_path)


def _eyed_scene():
    from toolkit.procedural import demo_head_scene

    s = demo_head_scene(2000)
    assert int((s.part == 1).sum()) == int((s.part == 2).sum()) == 80
    return s


@pytest.mark.parametrize("eyes,msg", [
    ([1, 2], r"metadata.eyes: expected a mapping of left/right eyeballs, got list"),
    ("left", r"metadata.eyes: expected a mapping"),
    ({"left": {"center": [0, 0], "radius": 0.01}}, r"metadata.eyes.left.center: expected 3 finite numbers"),
    ({"right": {"center": [0, 0, 0], "radius": 0}}, r"metadata.eyes.right.radius: expected a finite number > 0"),
    ({"right": 5}, r"metadata.eyes.right: expected a mapping"),
])
def test_invalid_eye_metadata_is_refused_naming_it_not_taken_for_no_eyes(tmp_path, eyes, msg):
    from toolkit.eyes import eyeball_info
    from toolkit.io import save_tensors

    s = _eyed_scene()
    s.metadata["eyes"] = eyes
    with pytest.raises(ToolkitError, match=msg):
        eyeball_info(s)  # never {} ("no eye Gaussians") for a scene with hundreds of them
    with pytest.raises(ToolkitError, match="GaussianScene." + msg):
        s.validate()
    with pytest.raises(ToolkitError, match=msg):
        s.save(tmp_path / "w.safetensors")
    meta = dict(s.metadata, format="ditgaze.gaussian_scene", format_version=FORMAT_VERSION)
    save_tensors(tmp_path / "e.safetensors", s.tensors(), meta)
    with pytest.raises(ToolkitError, match=r"e.safetensors: GaussianScene." + msg):
        GaussianScene.load(tmp_path / "e.safetensors")
    assert not (tmp_path / "w.safetensors").exists()


def test_an_eye_that_gives_no_sphere_says_so(tmp_path):
    from toolkit.eyes import eyeball_info

    s = random_scene(20)
    s.part[:] = 0
    s.part[:3] = 1
    s.metadata.pop("eyes", None)
    with pytest.raises(ToolkitError, match=r"scene left eye: its 3 Gaussians give no eyeball sphere"):
        eyeball_info(s)


def _forge(tmp_path, name, tensors, **meta):
    from toolkit.io import save_tensors

    s = random_scene(5)
    t = s.tensors()
    t.update(tensors)
    save_tensors(tmp_path / name, t, {"format": "ditgaze.gaussian_scene", "format_version": FORMAT_VERSION, **meta})
    return tmp_path / name


@pytest.mark.parametrize("tensors,meta,msg", [
    ({"means": torch.zeros(5, 2)}, {}, r"GaussianScene.means: expected shape \[N, 3\], got \[5, 2\]"),
    ({"means": torch.zeros(5, 3, 1)}, {}, r"GaussianScene.means: expected shape"),
    ({"part": torch.full((5,), 3, dtype=torch.int8)}, {}, r"GaussianScene.part: labels must be 0"),
    ({"part": torch.zeros(5, dtype=torch.int64)}, {}, r"GaussianScene.part: expected int8"),
    ({"quats": torch.zeros(5, 4, dtype=torch.float8_e4m3fn)}, {}, r"GaussianScene.quats: expected a floating"),
    ({"opacity_logits": torch.zeros(5, dtype=torch.int32)}, {}, r"GaussianScene.opacity_logits: expected a floating"),
    ({"sh": torch.zeros(5, 5, 3)}, {}, r"GaussianScene.sh: expected shape"),
    ({"features": torch.zeros(4, 3)}, {}, r"GaussianScene.features: expected shape \[N=5, D\]"),
    ({}, {"format_version": True}, r"scene format version True is not supported"),
    ({}, {"format_version": "1"}, r"scene format version '1' is not supported"),
])
def test_a_scene_file_with_wrong_tensors_names_the_file_and_the_field(tmp_path, tensors, meta, msg):
    p = _forge(tmp_path, "bad.safetensors", tensors, **meta)
    with pytest.raises(ToolkitError, match=r"bad.safetensors: " + msg):
        GaussianScene.load(p)


def test_over_deep_metadata_is_refused_by_validate(tmp_path):
    import json

    s = random_scene(3)
    s.metadata["deep"] = json.loads("[" * 70 + "]" * 70)
    with pytest.raises(ToolkitError, match=r"GaussianScene.metadata: nested deeper than 64 levels"):
        s.save(tmp_path / "d.safetensors")
