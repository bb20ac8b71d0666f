"""Gaussian initialization: separate eyes (36–41 left, 42–47 right), eyeball metadata, scales, opacities."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geometry.init_gaussians import InitConfig, init_gaussians
from geometry.sdf import SDFNet, SDFNetConfig
from toolkit.errors import ToolkitError
from toolkit.eyes import eyeball_info, redirect_eyes
from toolkit.scene import PART_FACE, PART_LEFT_EYE, PART_RIGHT_EYE


@pytest.fixture(scope="module")
def subject():
    from train.data.synthetic import SubjectParams, build_subject

    s = build_subject(SubjectParams.sample(3), subdivisions=4)
    m = s.scene_mesh(None, (0.0, 0.0))  # head + eyeballs, as a silhouette fit sees them
    v = torch.tensor(m["verts"], dtype=torch.float32)
    f = torch.tensor(m["faces"].astype(np.int64))
    lmk = torch.tensor(s.landmarks(), dtype=torch.float32)
    return v, f, lmk, torch.tensor(s.eye_centers, dtype=torch.float32), float(s.eye_radius)


def test_eyes_separate_and_metadata(subject):
    v, f, lmk, centers, radius = subject
    net = SDFNet(SDFNetConfig(hidden=16, feature_dim=8, box_min=(-0.15,) * 3, box_max=(0.15,) * 3))
    scene = init_gaussians(v, f, lmk, net)
    assert scene.features.shape[1] == 8 and scene.metadata["feature_kind"] == "neural"
    eyes = scene.metadata["eyes"]
    assert set(eyes) == {"left", "right"} and eyes["left"]["part"] == PART_LEFT_EYE and eyes["right"]["part"] == PART_RIGHT_EYE
    for i, name in enumerate(("left", "right")):
        c = torch.tensor(eyes[name]["center"])
        assert float((c - centers[i]).norm()) < 0.004, (name, c, centers[i])
        assert eyes[name]["radius"] == pytest.approx(radius, rel=0.3)
        m = scene.part == eyes[name]["part"]
        assert int(m.sum()) >= InitConfig().min_eye_points
        # Eye Gaussians sit on their own eyeball, near their own landmarks.
        d = (scene.means[m] - c).norm(dim=-1)
        assert float((d - eyes[name]["radius"]).abs().max()) < 0.5 * eyes[name]["radius"]
        own = lmk[36:42] if name == "left" else lmk[42:48]
        assert float((scene.means[m].mean(0) - own.mean(0)).norm()) < 0.02
    assert eyes["left"]["center"][0] < 0 < eyes["right"]["center"][0]
    # toolkit.eyes reads the same metadata, and redirection rotates about these centres.
    info = eyeball_info(scene)
    assert torch.allclose(info["left"]["center"], torch.tensor(eyes["left"]["center"]))
    turned = redirect_eyes(scene, (0.2, -0.3))
    m = scene.part == PART_RIGHT_EYE
    c = info["right"]["center"]
    torch.testing.assert_close((turned.means[m] - c).norm(dim=-1), (scene.means[m] - c).norm(dim=-1), atol=1e-6, rtol=1e-5)
    assert torch.equal(turned.means[scene.part == PART_FACE], scene.means[scene.part == PART_FACE])


def test_opacity_scales_rotations(subject):
    v, f, lmk, _, _ = subject
    scene = init_gaussians(v, f, lmk)
    face, eye = scene.part == PART_FACE, scene.part != PART_FACE
    torch.testing.assert_close(scene.opacities[face], torch.full((int(face.sum()),), 0.3))
    torch.testing.assert_close(scene.opacities[eye], torch.full((int(eye.sum()),), 0.9))
    q = scene.quats
    assert torch.equal(q, torch.tensor([[1.0, 0, 0, 0]]).expand_as(q))
    s = scene.scales
    assert torch.allclose(s[eye], s[eye][:, :1].expand(-1, 3))  # isotropic eyes
    aniso = s[face].max(1).values / s[face].min(1).values
    assert float(aniso.median()) > 1.2  # anisotropic face
    assert bool(torch.isfinite(s).all()) and float(s.min()) > 0
    assert scene.metadata["feature_kind"] == "rgb" and scene.features.shape[1] == 3


def test_right_eye_uses_its_own_landmarks(subject):
    """The reference bug used 36–41 for both eyes: moving 42–47 must move only the right eyeball."""
    v, f, lmk, _, _ = subject
    base = init_gaussians(v, f, lmk).metadata["eyes"]
    lmk2 = lmk.clone()
    lmk2[42:48, 1] += 0.004
    moved = init_gaussians(v, f, lmk2).metadata["eyes"]
    assert moved["left"]["center"] == base["left"]["center"]
    assert moved["right"]["center"] != base["right"]["center"]


def test_sampled_points_and_bad_input(subject):
    v, f, lmk, _, _ = subject
    scene = init_gaussians(v, f, lmk, config=InitConfig(n_points=3000))
    assert 3000 <= scene.num_gaussians <= 3000 + 2 * InitConfig().min_eye_points
    with pytest.raises(ToolkitError, match="landmarks"):
        init_gaussians(v, f, lmk[:60])
    bad = lmk.clone()
    bad[5, 0] = float("nan")
    with pytest.raises(ToolkitError, match="landmarks"):
        init_gaussians(v, f, bad)
    with pytest.raises(ToolkitError, match="empty mesh"):
        init_gaussians(v, f[:0], lmk)


def test_duplicate_vertices_give_finite_positive_scales(subject):
    v, f, lmk, _, _ = subject
    v2 = torch.cat([v, v[:500] + 1e-9])  # near-duplicates, as DMTet produces where the surface grazes a vertex
    f2 = torch.cat([f, f[:200]])
    f2[-200:] = torch.where(f2[-200:] < 500, f2[-200:] + v.shape[0], f2[-200:])
    scene = init_gaussians(v2, f2, lmk)
    s = scene.scales
    assert torch.isfinite(s).all() and float(s.min()) > 1e-5


def test_dense_eyes_cover_the_front_cap_evenly(subject):
    v, f, lmk, _, _ = subject
    sparse = init_gaussians(v, f, lmk, config=InitConfig(n_points=3000))
    cfg = InitConfig(n_points=3000, eye_points=300, eye_cap_deg=60.0)
    scene = init_gaussians(v, f, lmk, config=cfg)
    eyes = scene.metadata["eyes"]
    # The mesh's eye points are replaced, the face keeps all of its own.
    n_face = int((sparse.part == PART_FACE).sum())
    assert int((scene.part == PART_FACE).sum()) == n_face and scene.num_gaussians == n_face + 2 * 300
    for name in ("left", "right"):
        m = scene.part == eyes[name]["part"]
        assert int(m.sum()) == 300
        c, r = torch.tensor(eyes[name]["center"]), eyes[name]["radius"]
        d = scene.means[m] - c
        torch.testing.assert_close(d.norm(dim=-1), torch.full((300,), r), atol=1e-6, rtol=1e-5)
        cos_front = -d[:, 2] / d.norm(dim=-1)  # the eye looks towards -z
        assert float(cos_front.min()) >= np.cos(np.radians(60.0)) - 1e-5
        # Even: equal-area halves of the cap hold half the points each, and the spacing varies little.
        half = 1 - 0.5 * (1 - np.cos(np.radians(60.0)))
        assert abs(int((cos_front > half).sum()) - 150) <= 2
        nn = torch.cdist(d, d).fill_diagonal_(float("inf")).min(1).values
        assert float(nn.max() / nn.min()) < 3.0
        assert torch.allclose(scene.scales[m], scene.scales[m][:, :1].expand(-1, 3))
    with pytest.raises(ToolkitError, match="eye_points"):
        init_gaussians(v, f, lmk, config=InitConfig(eye_points=2))
    with pytest.raises(ToolkitError, match="eye_cap_deg"):
        init_gaussians(v, f, lmk, config=InitConfig(eye_points=10, eye_cap_deg=0))


@pytest.mark.parametrize("n,cap", [(4, 180.0), (2000, 1.0)])
def test_dense_eyes_extremes_give_finite_positive_scales(subject, n, cap):
    v, f, lmk, _, _ = subject
    scene = init_gaussians(v, f, lmk, config=InitConfig(n_points=1500, eye_points=n, eye_cap_deg=cap))
    for pid in (PART_LEFT_EYE, PART_RIGHT_EYE):
        assert int((scene.part == pid).sum()) == n
    assert bool(torch.isfinite(scene.means).all()) and bool(torch.isfinite(scene.scales).all())
    assert float(scene.scales.min()) > 0


def test_lids_cover_the_eyeball_outside_the_opening(subject):
    """Lid points: face Gaussians on a shell just in front of each eyeball, none inside the opening polygon."""
    from geometry.init_gaussians import _polygon_contains, lid_polygon

    v, f, lmk, _, _ = subject
    base = init_gaussians(v, f, lmk, config=InitConfig(n_points=3000, eye_points=200))
    cfg = InitConfig(n_points=3000, eye_points=200, lid_points=400)
    scene = init_gaussians(v, f, lmk, config=cfg)
    n_face_base = int((base.part == PART_FACE).sum())
    face = torch.nonzero(scene.part == PART_FACE).squeeze(1)
    lids = face[n_face_base:]  # appended after the mesh's face points
    assert 0 < lids.numel() < 2 * 400 and scene.num_gaussians == base.num_gaussians + lids.numel()
    # The mesh's own points, eyes included, are unchanged.
    torch.testing.assert_close(scene.means[face[:n_face_base]], base.means[base.part == PART_FACE])
    eyes = scene.metadata["eyes"]
    p = scene.means[lids]
    on_shell = torch.zeros(p.shape[0], dtype=torch.bool)
    for name, ids in (("left", list(range(36, 42))), ("right", list(range(42, 48)))):
        c, r = torch.tensor(eyes[name]["center"]), eyes[name]["radius"]
        mine = ((p - c).norm(dim=-1) - r * (1 + cfg.lid_offset)).abs() < 1e-5
        on_shell |= mine
        assert not bool(_polygon_contains(lid_polygon(lmk[ids], cfg.lid_opening), p[mine, :2]).any())
        assert int(mine.sum()) > 100  # most of the cap is lid: the opening is small
        assert bool((-(p[mine] - c)[:, 2] > 0).all())  # in front of the eyeball's centre
    assert bool(on_shell.all())
    torch.testing.assert_close(scene.opacities[lids], torch.full((lids.numel(),), cfg.opacity_lid))
    torch.testing.assert_close(scene.opacities[face[:n_face_base]], base.opacities[base.part == PART_FACE])
    # The mesh points' scales are as without lids; the lids' are lid_scale x their own neighbour rule.
    torch.testing.assert_close(scene.scales[face[:n_face_base]], base.scales[base.part == PART_FACE])
    full = init_gaussians(v, f, lmk, config=InitConfig(n_points=3000, eye_points=200, lid_points=400, lid_scale=1.0))
    torch.testing.assert_close(scene.scales[lids], 0.5 * full.scales[lids])
    floor = 0.2 * float(base.scales[base.part == PART_FACE].median())  # the mesh face's, as without lids
    assert float(full.scales[lids].min()) >= floor * 0.9999 and bool(torch.isfinite(scene.scales).all())
    with pytest.raises(ToolkitError, match="lid_points"):
        init_gaussians(v, f, lmk, config=InitConfig(lid_points=100))  # lids need the dense eyes
    with pytest.raises(ToolkitError, match="lid_offset"):
        init_gaussians(v, f, lmk, config=InitConfig(eye_points=50, lid_points=100, lid_offset=0.0))
    with pytest.raises(ToolkitError, match="lid_cap_deg"):  # past 90 degrees the shell goes behind the eyeball
        init_gaussians(v, f, lmk, config=InitConfig(eye_points=50, lid_points=100, lid_cap_deg=120.0))


@pytest.mark.parametrize("n,cap,offset,empty", [(4, 1.0, 0.1, True), (3000, 90.0, 0.01, False),
                                                 (50, 75.0, 5.0, False)])
def test_lid_extremes_give_finite_positive_scales(subject, n, cap, offset, empty):
    """A cap inside the opening (no lids at all), a dense hemisphere, a shell far out: a valid scene each."""
    v, f, lmk, _, _ = subject
    base = init_gaussians(v, f, lmk, config=InitConfig(n_points=1500, eye_points=50))
    scene = init_gaussians(v, f, lmk, config=InitConfig(n_points=1500, eye_points=50, lid_points=n,
                                                        lid_cap_deg=cap, lid_offset=offset))
    if empty:
        assert scene.num_gaussians == base.num_gaussians
        torch.testing.assert_close(scene.scales, base.scales)
    else:
        assert base.num_gaussians < scene.num_gaussians <= base.num_gaussians + 2 * n
    assert bool(torch.isfinite(scene.means).all()) and bool(torch.isfinite(scene.scales).all())
    assert float(scene.scales.min()) > 0 and bool(((scene.opacities > 0) & (scene.opacities < 1)).all())
