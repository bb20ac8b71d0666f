"""Stress tests of toolkit.procedural, the analytic demo head. It generates data (no gradient flows through it
in training), so the checks are on finite outputs: surface points along the coordinate axes (the poles of the
direction sphere, where the socket floor divides by z) under the most extreme expressions and near-zero eye
openings, the smallest scene with flat or saturated Gaussians, and k-NN spacings of coincident or far points."""

from __future__ import annotations

import pytest
import torch

from toolkit.errors import ToolkitError
from toolkit.procedural import DEMO_EYE_OPENING, DemoHeadShape, demo_head_scene, knn_spacing

AXES = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])

SHAPES = [
    {},
    {"eye_opening": DEMO_EYE_OPENING},
    {"eye_opening": DEMO_EYE_OPENING, "mouth_open": 1.0, "smile": 1.0, "brow_raise": -1.0, "eyelid": 1.0},
    {"eye_opening": (1e-9, 1e-9), "mouth_open": 1.0, "smile": -1.0, "brow_raise": 1.0, "eyelid": 0.0},
]


@pytest.mark.parametrize("kw", SHAPES, ids=["demo", "sockets", "extreme-expression", "pinhole-sockets"])
def test_surface_points_along_the_axes_and_everywhere_are_finite(kw):
    shape = DemoHeadShape(**kw)
    g = torch.Generator().manual_seed(0)
    dirs = torch.cat([AXES, torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1)])
    p = shape.surface_points(dirs)
    r = (p - torch.tensor(shape.center)).norm(dim=-1)
    assert torch.isfinite(p).all() and float(r.min()) > 0.02 and float(r.max()) < 0.2
    for w in (shape.socket_weight(dirs), shape.mouth_weight(dirs)):
        assert torch.isfinite(w).all() and float(w.min()) >= 0 and float(w.max()) <= 1


@pytest.mark.parametrize("kw", [{"flatness": 0.0}, {"opacity_face": 1.0, "opacity_eye": 0.0}, {"eye_fraction": 0.0}])
def test_smallest_demo_scene_with_flat_or_saturated_gaussians(kw):
    """64 Gaussians (the minimum), discs of zero thickness, opacities of exactly 1 and 0, the fewest eye
    Gaussians: every field finite and the scene valid."""
    scene = demo_head_scene(64, **kw)
    assert scene.validate() is scene
    for name in ("means", "quats", "log_scales", "opacity_logits", "features"):
        assert torch.isfinite(getattr(scene, name)).all(), name
    assert torch.isfinite(scene.scales).all() and torch.isfinite(scene.unit_quats).all()


@pytest.mark.parametrize("n, fraction, match", [
    (64, 1.0, r"eye_fraction must be in \[0, 1\)"), (64, -0.1, r"eye_fraction must be in \[0, 1\)"),
    (64, float("nan"), r"eye_fraction must be in \[0, 1\)"),
    (64, 0.95, r"eye_fraction 0.95 leaves 4 of 64 Gaussians to the face; expected at least 8"),
])
def test_demo_scene_with_no_room_for_a_face_is_one_clear_error(n, fraction, match):
    with pytest.raises(ToolkitError, match=match):
        demo_head_scene(n, eye_fraction=fraction)


@pytest.mark.parametrize("n", [63, 100.5, "100"])
def test_demo_scene_counts_are_integers_of_at_least_64(n):
    with pytest.raises(ToolkitError, match=r"n_gaussians must be an integer >= 64"):
        demo_head_scene(n)


def test_demo_scenes_of_mostly_eyes():
    """A large head keeps a face at 0.99 (198 face Gaussians of 20000), the smallest at 0.9 (8 of 64)."""
    assert demo_head_scene(64, eye_fraction=0.9).validate() is not None
    assert demo_head_scene(20000, eye_fraction=0.99).validate() is not None


@pytest.mark.parametrize("scale", [0.0, 1e-30, 1.0, 1e30])
def test_knn_spacing_of_coincident_tiny_and_huge_clouds(scale):
    """All points coincident (spacing 0 is floored at 1e-7) or spread at 1e-30 / 1e30: finite, positive."""
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(40, 3, generator=g) * scale
    pts[:10] = pts[10]  # a cluster of duplicates
    sp = knn_spacing(pts)
    assert torch.isfinite(sp).all() and float(sp.min()) > 0
