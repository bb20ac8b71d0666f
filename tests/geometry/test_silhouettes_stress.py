"""Stress tests of geometry.silhouettes: the visual-hull SDF (the silhouette fit's regression target; no
gradient flows through it) divides by camera depth and by the focal length and takes square roots of pixel
distances. Queries exactly at camera centres, on a camera plane, a million units away and at 1e-30, rigs at
1e-4 and 1e4 scale, a mask filling the whole image and a one-pixel mask: finite distances and bounds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geometry.silhouettes import Views, hull_bounds, mask_signed_distance, visual_hull_sdf
from toolkit.cameras import orbit_rig


def _views(scale: float, size: int = 16) -> Views:
    cams = orbit_rig(3, 2, radius=0.6 * scale, yaw_range_deg=60, pitch_range_deg=30, width=size, height=size)
    jj, ii = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    disc = torch.from_numpy(((jj - size / 2) ** 2 + (ii - size / 2) ** 2) < (size / 4) ** 2)
    masks = torch.stack([disc] * (len(cams) - 1) + [torch.ones(size, size, dtype=torch.bool)])  # one full mask
    return Views(masks, torch.stack([c.K for c in cams]), torch.stack([c.viewmat for c in cams]))


@pytest.mark.parametrize("scale", [1e-4, 1.0, 1e4])
def test_visual_hull_sdf_at_camera_centres_planes_and_far_away(scale):
    views = _views(scale)
    centres = torch.stack([-v[:3, :3].T @ v[:3, 3] for v in views.viewmats])
    R0, t0 = views.viewmats[0, :3, :3], views.viewmats[0, :3, 3]
    on_plane = R0.T @ (torch.tensor([0.1 * scale, 0.0, 0.0]) - t0)  # camera 0's z = 0 plane
    q = torch.cat([centres, on_plane[None], torch.zeros(1, 3),
                   torch.tensor([[0.0, 0.0, 1e6 * scale], [1e-30, 0.0, 0.0], [0.0, 0.0, -0.6 * scale]])])
    d = visual_hull_sdf(q, views)
    assert d.shape == (q.shape[0],) and torch.isfinite(d).all()
    assert float(d[len(centres) + 1]) < 0 < float(d[len(centres) + 2])  # the centre inside, far away outside
    lo, hi = hull_bounds(views, None)
    assert torch.isfinite(lo).all() and torch.isfinite(hi).all() and bool((hi > lo).all())


def test_visual_hull_sdf_behind_every_camera_is_called_outside():
    """A query no camera sees (behind all of them) has no evidence: it gets a finite positive distance."""
    views = _views(1.0)
    d = visual_hull_sdf(torch.tensor([[0.0, 0.0, -50.0], [0.0, 0.0, 0.0]]), views)
    assert torch.isfinite(d).all() and float(d[0]) > 0


@pytest.mark.parametrize("kind", ["full", "pixel", "corner", "row"])
def test_mask_signed_distance_of_degenerate_masks(kind):
    m = np.zeros((9, 7), bool)
    if kind == "full":
        m[:] = True
    elif kind == "pixel":
        m[4, 3] = True
    elif kind == "corner":
        m[0, 0] = True
    else:
        m[8, :] = True
    sd = mask_signed_distance(m)
    assert sd.shape == m.shape and np.isfinite(sd).all()
    assert (sd[m] < 0).all() and (sd[~m] > 0).all()
    if kind == "full":  # no boundary in the image: its edge, one pixel beyond, is the nearest known one
        assert float(sd.min()) == pytest.approx(-3.5, abs=0.05) and float(sd[0, 0]) == pytest.approx(-0.5, abs=0.05)
