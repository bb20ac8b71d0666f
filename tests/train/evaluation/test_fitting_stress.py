"""Stress tests of train.evaluation.fitting (test-time fitting: Adam on the shape code, the Gaussians'
features, the eye rotation field and the renderer, with both gaze terms): zero and 1e6 codes, input gazes and
target gazes at ±89°, a large head rotation, a white input with an empty mask and a black one with a full
mask. The fitted code and every fitted weight stay finite (a NaN gradient would poison them at the first step)."""

from __future__ import annotations

import math

import pytest
import torch
import torch._dynamo  # noqa: F401  (the first torch optimizer imports it, ~1 s once per process: pay it here)

from tests.train.helpers import untrained_eval_parts
from toolkit.procedural import demo_camera
from train.evaluation import fitting  # the module, not its test_time_fit: pytest would collect that name
from train.evaluation.fitting import FitGaze, face_only_mask, restored_weights
from train.losses import GazeLoss

R89 = math.radians(89.0)
B, RES = 2, 64


@pytest.fixture(scope="module")
def parts():
    return untrained_eval_parts()


def _batch(code_dim: int, code_scale: float) -> dict[str, torch.Tensor]:
    cam = demo_camera(RES, RES)
    return {"code": torch.ones(B, code_dim) * code_scale * torch.tensor([[1.0], [-1.0]]),
            "in_pose": torch.tensor([[0.5, -0.5, 0.2, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]),
            "in_gaze_head": torch.tensor([[R89, R89], [-R89, -R89]]),
            "in_viewmat": cam.viewmat.expand(B, 4, 4).clone(), "K": cam.K.expand(B, 3, 3).clone(),
            "gaze_head": torch.tensor([[-R89, R89], [R89, -R89]]), "landmarks": torch.zeros(B, 68, 2)}


@pytest.mark.parametrize("code_scale", [0.0, 1e6])
@pytest.mark.parametrize("fill,mask_value", [(1.0, 0.0), (0.0, 1.0)], ids=["white-empty-mask", "black-full-mask"])
def test_fit_with_both_gaze_terms_at_extreme_codes_gazes_and_masks(parts, code_scale, fill, mask_value):
    model, renderer, estimator = parts
    torch.manual_seed(0)
    batch = _batch(model.config.code_dim, code_scale)
    image = torch.full((B, 3, RES, RES), fill)
    mask = torch.full((B, 1, RES, RES), mask_value)
    gaze = FitGaze(GazeLoss(estimator), 1.0, ("own", "target"))
    with restored_weights(model, renderer):
        code = fitting.test_time_fit(model, renderer, batch, image, mask, RES, steps=2, lr=0.1,
                                     weights=("features", "eye_field", "renderer"), gaze=gaze)
        assert torch.isfinite(code).all()
        bad = [n for n, p in [*model.named_parameters(), *renderer.named_parameters()] if not torch.isfinite(p).all()]
        assert not bad, bad


@pytest.mark.parametrize("dilate", [0, 1, 1000])
def test_face_only_mask_of_full_empty_and_fractional_masks(dilate):
    """Eye masks that are empty, cover everything, or are fractional, dilated by more than the image."""
    g = torch.Generator().manual_seed(1)
    head = torch.rand(3, 1, 8, 8, generator=g)
    eyes = torch.stack([torch.zeros(1, 8, 8), torch.ones(1, 8, 8), torch.rand(1, 8, 8, generator=g) * 1e-30])
    m = face_only_mask(head, eyes, dilate)
    assert torch.isfinite(m).all() and float(m.min()) >= 0 and float(m.max()) <= 1
