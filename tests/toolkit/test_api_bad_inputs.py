"""The toolkit's public functions given what a user's own values look like (lists and arrays for tensors,
devices this machine lacks, NaN or misshapen gazes, metadata that is not JSON): one ToolkitError naming the
argument, never an error from inside torch or a silent NaN."""

from __future__ import annotations

import pytest
import torch

from toolkit.errors import ToolkitError
from toolkit.eyes import redirect_eyes
from toolkit.io import check_device
from toolkit.procedural import demo_head_scene
from toolkit.scene import GaussianScene


@pytest.fixture(scope="module")
def scene():
    return demo_head_scene(200)


def test_a_device_string_that_names_no_device():
    with pytest.raises(ToolkitError, match=r"^device: expected cpu, cuda or cuda:N, got 'bogus'$"):
        check_device("bogus")
    assert check_device(torch.device("cpu")) == torch.device("cpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
def test_scenes_asked_onto_a_missing_gpu_say_so(tmp_path, scene):
    scene.save(tmp_path / "s.safetensors")
    scene.to_ply(tmp_path / "s.ply")
    for path in (tmp_path / "s.safetensors", tmp_path / "s.ply"):
        with pytest.raises(ToolkitError, match=r"^device cuda: CUDA is not available here"):
            GaussianScene.read(path, device="cuda")
    assert check_device("cpu") == torch.device("cpu")


def test_a_scene_of_lists_is_named(scene):
    with pytest.raises(ToolkitError, match=r"GaussianScene: means must be a torch tensor, got list"):
        GaussianScene(means=scene.means.tolist(), quats=scene.quats, log_scales=scene.log_scales,
                      opacity_logits=scene.opacity_logits, features=scene.features)


def test_metadata_that_is_not_json_writes_nothing(tmp_path, scene):
    bad = scene.clone()
    bad.metadata["weights"] = torch.ones(2)
    with pytest.raises(ToolkitError, match=r"s.safetensors: metadata must hold JSON values only"):
        bad.save(tmp_path / "s.safetensors")
    assert list(tmp_path.iterdir()) == []


def test_a_sphere_through_nan_points_is_named():
    from toolkit.eyes import fit_sphere

    points = torch.randn(10, 3, generator=torch.Generator().manual_seed(0))
    points[3, 1] = float("nan")
    with pytest.raises(ToolkitError, match=r"^fit_sphere: the points contain NaN/inf$"):
        fit_sphere(points)


@pytest.mark.parametrize("gaze", [(float("nan"), 0.0), (0.1, 0.2, 0.3), 0.5, [[0.1, 0.2], [0.0, 0.0]]])
def test_redirected_eyes_need_two_finite_angles(scene, gaze):
    with pytest.raises(ToolkitError, match=r"redirect_eyes: pitchyaw expected two finite angles"):
        redirect_eyes(scene, gaze)
