"""Stress tests of geometry.render_sheet: the contact sheet frames any mesh by centring it and dividing by its
bounding-box diagonal (float64) before GL's float32. Meshes 1e-30 and 1e30 units across, a flat one (zero
extent on one axis) and a needle: the sheet of a scaled mesh is the sheet of the unit mesh (a NaN would turn
into arbitrary bytes in the uint8 image, so equality is the check), and the orbit cameras are finite rotations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from geometry.render_sheet import contact_sheet, orbit_cameras
from tests.gl import require_gl


def _ball():
    m = trimesh.creation.icosphere(1)
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.long)


@pytest.mark.parametrize("scale", [1e-30, 1e-10, 1e10, 1e30])
def test_contact_sheet_of_tiny_and_huge_meshes_is_the_unit_sheet(tmp_path, scale):
    require_gl()
    v, f = _ball()
    unit = contact_sheet(v, f, tmp_path / "unit.png", n_views=2, size=16)
    scaled = contact_sheet(v * scale, f, tmp_path / "scaled.png", n_views=2, size=16)
    assert np.abs(unit.astype(int) - scaled.astype(int)).max() <= 1
    assert unit.min() < 255  # something was drawn


@pytest.mark.parametrize("squash", [(1.0, 1.0, 0.0), (1.0, 1e-7, 1e-7)], ids=["flat", "needle"])
def test_contact_sheet_of_flat_and_needle_meshes(tmp_path, squash):
    require_gl()
    v, f = _ball()
    img = contact_sheet(v * torch.tensor(squash), f, tmp_path / "s.png", n_views=3, size=16)
    assert img.shape == (16, 48, 3)
    if squash[2] == 0.0:  # the disc faces the first (frontal) view; a needle covers no pixel centre
        assert img.min() < 255


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_orbit_cameras_are_finite_rotations(scale):
    v, _ = _ball()
    viewmats, K = orbit_cameras(v * scale, 5, 32)
    R = viewmats[:, :3, :3]
    assert torch.isfinite(viewmats).all() and torch.isfinite(K).all()
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(5, 3, 3), atol=1e-5)
