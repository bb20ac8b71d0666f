"""Drawn 2D face crops with exact gaze and head labels: a cheap, download-free source for the gaze estimator.

Not a substitute for the rendered synthetic dataset (``train.data``): faces are flat drawings (skin ellipse,
brows, mouth, two eyeballs with iris and pupil), but the geometry follows the labels exactly, so an
estimator's error on them is meaningful for tests and quick experiments:

- head (pitch, yaw) moves the facial features across the face ellipse by the projection of the head's
  facing direction (orthographic), and foreshortens the eye spacing by cos(yaw);
- gaze (pitch, yaw) is in the camera frame (ETH-XGaze convention); the iris centre sits at the eyeball
  centre plus eyeball radius times the image-plane components (g_x, g_y) of the gaze direction.

A *subject* fixes the appearance (skin, iris colour, eye size and spacing, face shape, background), so a split
by subject gives held-out people. Edges are anti-aliased (sigmoid of the signed distance), so sub-pixel iris
shifts change pixel values continuously.
"""

from __future__ import annotations

import math

import torch

from toolkit.errors import ToolkitError
from toolkit.rotations import pitchyaw_to_vector


def _subject_params(n_subjects: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    return {
        "skin": torch.stack([0.55 + 0.4 * u(n_subjects), 0.35 + 0.35 * u(n_subjects), 0.25 + 0.35 * u(n_subjects)], -1),
        "iris": 0.05 + 0.5 * u(n_subjects, 3),
        "bg": 0.6 + 0.4 * u(n_subjects, 3),
        "eye_r": 0.062 + 0.016 * u(n_subjects),  # eyeball radius, fraction of the image size
        "eye_dx": 0.17 + 0.04 * u(n_subjects),  # half the distance between the eyes
        "face_a": 0.36 + 0.06 * u(n_subjects),
        "face_b": 0.44 + 0.06 * u(n_subjects),
    }


def draw_faces(size: int, subjects: torch.Tensor, gaze: torch.Tensor, head: torch.Tensor, *, n_subjects: int,
               subject_seed: int = 0) -> torch.Tensor:
    """Draw faces -> [B, 3, size, size] RGB in [0, 1].

    Args:
        subjects: [B] long subject ids in [0, n_subjects); gaze, head: [B, 2] (pitch, yaw) radians.
    """
    if size < 16:
        raise ToolkitError(f"draw_faces: size must be >= 16, got {size}")
    B = subjects.shape[0]
    if gaze.shape != (B, 2) or head.shape != (B, 2):
        raise ToolkitError(f"draw_faces: gaze and head must be [B={B}, 2], got {list(gaze.shape)}, {list(head.shape)}")
    p = {k: v[subjects] for k, v in _subject_params(n_subjects, subject_seed).items()}
    aa = 1.0 / size  # edge softness: one pixel
    ys, xs = torch.meshgrid(torch.linspace(-0.5, 0.5, size), torch.linspace(-0.5, 0.5, size), indexing="ij")
    xs, ys = xs[None], ys[None]  # [1, H, W], y down

    def inside(d):  # signed distance (negative inside) -> coverage
        return torch.sigmoid(-d / aa)

    h = pitchyaw_to_vector(head)  # [B, 3] facing direction; image-plane shift = (h_x, h_y)
    hx, hy = h[:, 0, None, None], h[:, 1, None, None]
    cos_yaw = torch.cos(head[:, 1])[:, None, None]
    a, b = p["face_a"][:, None, None], p["face_b"][:, None, None]
    face_d = torch.sqrt((xs / a) ** 2 + ((ys - 0.03) / b) ** 2 + 1e-12) - 1
    img = p["bg"][:, :, None, None].expand(B, 3, size, size).clone()
    img = _over(img, p["skin"], inside(face_d * a))
    # Features sit on the front of the head: they move by the projected facing direction.
    fx, fy = 0.25 * hx, 0.25 * hy
    # Mouth and brows (darker skin) for layout cues.
    mouth_d = torch.sqrt(((xs - fx) / (0.11 * cos_yaw + 0.01)) ** 2 + ((ys - 0.2 - fy) / 0.025) ** 2) - 1
    img = _over(img, p["skin"] * 0.55, inside(mouth_d * 0.025))
    r = p["eye_r"][:, None, None]
    dx = p["eye_dx"][:, None, None] * cos_yaw
    gv = pitchyaw_to_vector(gaze)
    gx, gy = gv[:, 0, None, None], gv[:, 1, None, None]
    for side in (-1.0, 1.0):
        cx, cy = fx + side * dx, fy - 0.05
        brow_d = torch.maximum((xs - cx).abs() - 1.4 * r, (ys - cy + 1.9 * r).abs() - 0.25 * r)  # box SDF
        img = _over(img, p["skin"] * 0.35, inside(brow_d))
        eye_d = torch.sqrt((xs - cx) ** 2 + (ys - cy) ** 2) - r
        img = _over(img, torch.full_like(p["skin"], 0.95), inside(eye_d))
        ix, iy = cx + r * gx, cy + r * gy
        iris_d = torch.sqrt((xs - ix) ** 2 + (ys - iy) ** 2) - 0.45 * r
        cover = inside(iris_d) * inside(eye_d)
        img = _over(img, p["iris"], cover)
        pupil_d = torch.sqrt((xs - ix) ** 2 + (ys - iy) ** 2) - 0.2 * r
        img = _over(img, torch.full_like(p["skin"], 0.03), inside(pupil_d) * inside(eye_d))
    return img.clamp(0, 1)


def _over(img: torch.Tensor, color: torch.Tensor, cover: torch.Tensor) -> torch.Tensor:
    c = cover[:, None]
    return img * (1 - c) + color[:, :, None, None] * c


def drawn_face_dataset(n: int, size: int = 64, *, n_subjects: int = 20, subjects: list[int] | None = None,
                       max_gaze_deg: float = 30.0, max_head_deg: float = 20.0, seed: int = 0,
                       subject_seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n random samples -> (images [n, 3, size, size] float, labels [n, 4] radians, subject ids [n]).

    ``subjects`` restricts the subject ids (e.g. a held-out split); gaze and head angles are uniform in
    ±max_gaze_deg / ±max_head_deg per axis.
    """
    g = torch.Generator().manual_seed(seed)
    pool = torch.tensor(subjects if subjects is not None else list(range(n_subjects)), dtype=torch.long)
    if pool.numel() == 0 or int(pool.max()) >= n_subjects or int(pool.min()) < 0:
        raise ToolkitError(f"drawn_face_dataset: subjects must be ids in [0, {n_subjects}), got {pool.tolist()}")
    sid = pool[torch.randint(0, pool.numel(), (n,), generator=g)]
    gaze = (torch.rand(n, 2, generator=g) * 2 - 1) * math.radians(max_gaze_deg)
    head = (torch.rand(n, 2, generator=g) * 2 - 1) * math.radians(max_head_deg)
    images = torch.cat([draw_faces(size, sid[i:i + 512], gaze[i:i + 512], head[i:i + 512], n_subjects=n_subjects,
                                   subject_seed=subject_seed) for i in range(0, n, 512)])
    return images, torch.cat([gaze, head], -1), sid
