"""The procedural demo head: an analytic head surface plus two eyeballs, as a GaussianScene.

The embedded default that needs no data: ``make demo``, the preview benchmark and many tests use it.
Units are metres in the head frame of ``toolkit.eyes`` (x image-right, y down, face towards -z).
Gaussians are placed on the surface with area-uniform density; each one's scale comes from the mean
distance to its 3 nearest neighbours (as the Gaussian initialization of geometry/ does): face Gaussians
are flat discs in the tangent plane, eye Gaussians isotropic.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

from toolkit.errors import ToolkitError
from toolkit.rotations import matrix_to_quat
from toolkit.scene import PART_FACE, PART_LEFT_EYE, PART_RIGHT_EYE, GaussianScene


@dataclass(frozen=True)
class DemoHeadShape:
    """Analytic head: a star-shaped surface around ``center`` plus two spherical eyeballs (metres).

    The defaults are the demo head. Identity fields (head size, nose, brow, chin, eyes, mouth) and
    expression fields (``mouth_open``, ``smile``, ``brow_raise``, ``eyelid``) let ``train.data.synthetic``
    build many subjects from the same surface. Features are placed by *base* coordinates: the (x, y) of
    the ellipsoid point in each direction (:meth:`base_xy`), so they stay put when expressions recess or
    bulge the surface. ``eye_opening`` = (half-width, half-height) of an almond-shaped socket through
    which the eyeball shows; (0, 0), the demo default, means no socket (the surface covers the eyes).
    """

    center: tuple[float, float, float] = (0.0, 0.01, 0.0)
    semi_axes: tuple[float, float, float] = (0.075, 0.10, 0.09)
    eye_offset_x: float = 0.031
    eye_y: float = -0.005
    eye_z: float = -0.068
    eye_radius: float = 0.012
    nose_height: float = 0.024
    skin: tuple[float, float, float] = (0.86, 0.66, 0.55)
    iris: tuple[float, float, float] = (0.30, 0.20, 0.10)
    # Identity (direction-space widths as in the demo formula; metres otherwise).
    nose_width: float = 0.09
    brow_height: float = 0.006
    brow_y: float = -0.12  # direction-space height of the brow ridge (subjects: higher, above the eyes)
    chin_height: float = 0.008
    eye_opening: tuple[float, float] = (0.0, 0.0)
    mouth_width: float = 0.024
    mouth_y: float = 0.062
    # Expression: mouth_open, eyelid in [0, 1]; smile, brow_raise in [-1, 1]. Zero is neutral.
    mouth_open: float = 0.0
    smile: float = 0.0
    brow_raise: float = 0.0
    eyelid: float = 0.0

    SOCKET_SHARPNESS = 1.0 / 0.0004  # 1/m: the lid rim spans about a millimetre
    SOCKET_BEHIND_CENTER = 0.001  # the socket floor lies this far behind the eyeball centres (m)
    MOUTH_DEPTH = 0.015  # recess of a fully open mouth (m)

    def eye_centers(self) -> torch.Tensor:
        """[2, 3] centres of the left (image-left, x < 0) and right eyeballs."""
        return torch.tensor([[-self.eye_offset_x, self.eye_y, self.eye_z], [self.eye_offset_x, self.eye_y, self.eye_z]])

    def ellipsoid_radius(self, dirs: torch.Tensor) -> torch.Tensor:
        a = torch.tensor(self.semi_axes, dtype=dirs.dtype)
        return 1.0 / torch.sqrt(((dirs / a) ** 2).sum(-1))

    def base_xy(self, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[M, 3] unit directions -> metric (x, y) of the ellipsoid point in each direction."""
        p = torch.tensor(self.center, dtype=dirs.dtype) + self.ellipsoid_radius(dirs)[:, None] * dirs
        return p[:, 0], p[:, 1]

    def dirs_from_base_xy(self, xy: torch.Tensor) -> torch.Tensor:
        """[M, 2] metric (x, y) on the front of the ellipsoid -> [M, 3] unit directions (inverse of base_xy)."""
        a = torch.tensor(self.semi_axes, dtype=xy.dtype)
        c = torch.tensor(self.center, dtype=xy.dtype)
        rho = ((xy[:, 0] - c[0]) / a[0]) ** 2 + ((xy[:, 1] - c[1]) / a[1]) ** 2
        z = c[2] - a[2] * torch.sqrt((1 - rho).clamp_min(1e-4))
        p = torch.stack([xy[:, 0], xy[:, 1], z], -1)
        return torch.nn.functional.normalize(p - c, dim=-1)

    def opening_half_height(self, dx: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
        """Almond lid profile: half-height of the eye opening at horizontal offset dx (upper lid closes)."""
        aw, ah = self.eye_opening
        # Signed profile: negative beyond the corners, so the opening closes there instead of thinning to 0.
        q = 1 - (dx / max(aw, 1e-9)) ** 2
        prof = torch.sign(q) * q.abs() ** 0.8
        h_up = ah * (1 - 0.9 * self.eyelid) * prof
        return torch.where(upper, h_up, ah * (1 - 0.3 * self.eyelid) * prof)

    def mouth_centerline(self, x: torch.Tensor) -> torch.Tensor:
        """y of the line between the lips at x (corners rise with ``smile``)."""
        return self.mouth_y - self.smile * 0.008 * (x / self.mouth_width) ** 2

    def mouth_half_opening(self, x: torch.Tensor) -> torch.Tensor:
        q = 1 - (x / self.mouth_width) ** 2
        return 0.010 * self.mouth_open * torch.sign(q) * q.abs() ** 0.5

    def socket_weight(self, dirs: torch.Tensor) -> torch.Tensor:
        """[M] in [0, 1]: how far each direction lies inside an eye opening (0 with no sockets)."""
        if self.eye_opening[0] <= 0 or self.eye_opening[1] <= 0:
            return torch.zeros(dirs.shape[0], dtype=dirs.dtype)
        x, y = self.base_xy(dirs)
        w = torch.zeros_like(x)
        for ex in (-self.eye_offset_x, self.eye_offset_x):
            dx, dy = x - ex, y - self.eye_y
            h = self.opening_half_height(dx, dy < 0)
            w = torch.maximum(w, torch.sigmoid(self.SOCKET_SHARPNESS * (h - dy.abs())) * (dirs[:, 2] < 0))
        return w

    def mouth_weight(self, dirs: torch.Tensor) -> torch.Tensor:
        """[M] in [0, 1]: how far each direction lies inside the open mouth."""
        x, y = self.base_xy(dirs)
        q = 1 - (x / self.mouth_width) ** 2
        h = self.mouth_half_opening(x) + 0.0015 * q.clamp(max=0)  # the corners close within ~1 mm
        inside = torch.sigmoid(self.SOCKET_SHARPNESS * (h - (y - self.mouth_centerline(x)).abs()))
        return inside * (dirs[:, 2] < 0) * (self.mouth_open > 0)

    def radius(self, dirs: torch.Tensor) -> torch.Tensor:
        """[M, 3] unit directions from ``center`` -> [M] surface distance (ellipsoid + nose, brow, chin)."""
        r = self.ellipsoid_radius(dirs)
        x, y, z = dirs.unbind(-1)
        front = torch.sigmoid(-z * 20)
        nose = self.nose_height * torch.exp(-(x / self.nose_width) ** 2 - ((y - 0.22) / 0.16) ** 2) * front
        by = y - self.brow_y + 0.05 * self.brow_raise
        brow = self.brow_height * torch.exp(-(by / 0.06) ** 2) * torch.exp(-(x / 0.45) ** 2) * front
        jaw = 0.72 + 0.12 * self.mouth_open
        chin = self.chin_height * torch.exp(-(x / 0.2) ** 2 - ((y - jaw) / 0.12) ** 2) * front
        r = r + nose + brow + chin
        if self.mouth_open > 0:
            # The jaw drops: the surface below the mouth moves out along its directions.
            bx, bl = self.base_xy(dirs)
            below = torch.sigmoid((bl - self.mouth_y) / 0.006) * torch.exp(-(bx / 0.05) ** 2) * front
            r = r + 0.010 * self.mouth_open * below
            r = r - self.MOUTH_DEPTH * self.mouth_open * self.mouth_weight(dirs)
        if self.smile != 0:
            bx, bl = self.base_xy(dirs)
            cheeks = torch.exp(-((bx.abs() - 0.040) / 0.012) ** 2 - ((bl - 0.035) / 0.012) ** 2) * front
            r = r + 0.004 * self.smile * cheeks
        w = self.socket_weight(dirs)
        if bool((w > 0).any()):
            # Socket floor: the plane just behind the eyeball centres, so their front halves show.
            floor_z = self.eye_z + self.SOCKET_BEHIND_CENTER - self.center[2]
            t = floor_z / torch.where(z < -1e-3, z, torch.full_like(z, -1e-3))
            r = r - w * (r - torch.minimum(r, t))
        return r

    def surface_points(self, dirs: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.center, dtype=dirs.dtype) + self.radius(dirs)[:, None] * dirs


# Almond-shaped lid openings (half-width, half-height in metres) for the demo head: without them the face
# surface covers most of each eyeball and the iris hides behind the lids beyond ~20° of gaze.
DEMO_EYE_OPENING = (0.0135, 0.0062)


def _fibonacci_sphere(m: int) -> torch.Tensor:
    i = torch.arange(m, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * i / m)
    theta = math.pi * (1 + 5**0.5) * i
    return torch.stack([torch.cos(theta) * torch.sin(phi), torch.cos(phi), torch.sin(theta) * torch.sin(phi)], -1).float()


def _area_weights(shape: DemoHeadShape, dirs: torch.Tensor, h: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-direction area element (up to a constant) and outward unit normals, by finite differences."""
    p = shape.surface_points(dirs)
    # Two tangent directions of the unit sphere at each dir.
    helper = torch.where(dirs[:, 1:2].abs() < 0.9, torch.tensor([[0.0, 1.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]))
    t1 = torch.nn.functional.normalize(torch.linalg.cross(dirs, helper), dim=-1)
    t2 = torch.linalg.cross(dirs, t1)
    d1 = shape.surface_points(torch.nn.functional.normalize(dirs + h * t1, dim=-1)) - p
    d2 = shape.surface_points(torch.nn.functional.normalize(dirs + h * t2, dim=-1)) - p
    n = torch.linalg.cross(d1, d2)
    area = n.norm(dim=-1)
    n = n / area.clamp_min(1e-20)[:, None]
    n = torch.where(((n * dirs).sum(-1, keepdim=True) < 0), -n, n)
    return area, n


def knn_spacing(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """[M, 3] -> [M] mean distance to the k nearest other points (a KD-tree; exact)."""
    from scipy.spatial import cKDTree

    if points.shape[0] <= k:
        raise ToolkitError(f"knn_spacing: need more than {k} points, got {points.shape[0]}")
    pts = points.detach().cpu().double().numpy()
    d, _ = cKDTree(pts).query(pts, k=k + 1)
    return torch.from_numpy(d[:, 1:].mean(1)).to(points.dtype).clamp_min(1e-7)


def _frame_from_normal(n: torch.Tensor) -> torch.Tensor:
    """[M, 3] unit normals -> [M, 3, 3] rotations whose third column is the normal."""
    helper = torch.where(n[:, 0:1].abs() < 0.9, torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]))
    t1 = torch.nn.functional.normalize(torch.linalg.cross(helper, n), dim=-1)
    t2 = torch.linalg.cross(n, t1)
    return torch.stack([t1, t2, n], -1)


def demo_head_scene(
    n_gaussians: int = 20000,
    *,
    eye_fraction: float = 0.08,
    seed: int = 0,
    shape: DemoHeadShape | None = None,
    flatness: float = 0.15,
    opacity_face: float = 0.9,
    opacity_eye: float = 0.95,
) -> GaussianScene:
    """The procedural demo head as a GaussianScene with RGB features and part labels.

    Args:
        n_gaussians: total count (face + both eyes), >= 64.
        eye_fraction: share of the Gaussians placed on the two eyeballs, in [0, 1); the face keeps at least 8.
        flatness: face disc thickness relative to its in-plane scale.
    """
    if not isinstance(n_gaussians, numbers.Integral) or n_gaussians < 64:
        raise ToolkitError(f"demo_head_scene: n_gaussians must be an integer >= 64, got {n_gaussians!r}")
    if not 0 <= eye_fraction < 1:
        raise ToolkitError(f"demo_head_scene: eye_fraction must be in [0, 1), got {eye_fraction}")
    shape = shape or DemoHeadShape(eye_opening=DEMO_EYE_OPENING)
    g = torch.Generator().manual_seed(seed)
    n_eye_each = max(8, int(n_gaussians * eye_fraction / 2))
    n_face = n_gaussians - 2 * n_eye_each
    if n_face < 8:  # the face's spacing needs a few neighbours of each point
        raise ToolkitError(f"demo_head_scene: eye_fraction {eye_fraction} leaves {n_face} of {n_gaussians} Gaussians "
                           "to the face; expected at least 8")
    centers = shape.eye_centers()
    r_eye = shape.eye_radius
    face_pts, face_n = _face_points(shape, n_face, g)
    eye_pts, eye_parts, eye_cols = _eye_points(shape, n_eye_each, g)
    eye_pts_t = torch.cat(eye_pts)

    # Scales from 3-NN spacing, per part so face Gaussians never size themselves on the eyeball.
    s_face = knn_spacing(face_pts)
    s_eye = torch.cat([knn_spacing(p) for p in eye_pts])
    face_scales = torch.stack([s_face, s_face, flatness * s_face], -1)
    eye_scales = s_eye[:, None].expand(-1, 3)
    face_quats = matrix_to_quat(_frame_from_normal(face_n))
    eye_quats = torch.zeros(eye_pts_t.shape[0], 4)
    eye_quats[:, 0] = 1

    face_cols = _skin_colors(face_pts, shape, g)
    scene = GaussianScene.from_activated(
        means=torch.cat([face_pts, eye_pts_t]),
        scales=torch.cat([face_scales, eye_scales]),
        opacities=torch.cat([torch.full((n_face,), opacity_face), torch.full((eye_pts_t.shape[0],), opacity_eye)]),
        features=torch.cat([face_cols, torch.cat(eye_cols)]).clamp(0, 1),
        quats=torch.cat([face_quats, eye_quats]),
        part=torch.cat([torch.full((n_face,), PART_FACE, dtype=torch.int8), torch.cat(eye_parts)]),
        metadata={
            "units": "m",
            "feature_kind": "rgb",
            "source": "toolkit.procedural.demo_head_scene",
            "seed": seed,
            "frame": "head: x image-right, y down, face towards -z; canonical gaze (0, 0, -1)",
            "eyes": {
                "left": {"center": centers[0].tolist(), "radius": r_eye, "part": PART_LEFT_EYE},
                "right": {"center": centers[1].tolist(), "radius": r_eye, "part": PART_RIGHT_EYE},
            },
        },
    )
    return scene.validate()


def _face_points(shape: DemoHeadShape, n_face: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``n_face`` points area-uniform on the head surface outside the eye sockets -> (points, unit normals),
    both [n_face, 3]: oversampled directions, the sockets dropped, resampled by area, jittered in-plane."""
    m = 4 * n_face + 1000
    dirs = _fibonacci_sphere(m)
    area, normals = _area_weights(shape, dirs)
    pts = shape.surface_points(dirs)
    socket = torch.cdist(pts, shape.eye_centers()).min(1).values < 1.25 * shape.eye_radius
    area = torch.where(socket, torch.zeros_like(area), area)
    idx = torch.multinomial(area, n_face, replacement=False, generator=g)
    face_pts, face_n = pts[idx], normals[idx]
    jitter = torch.randn(n_face, 3, generator=g) * 1e-4
    return face_pts + jitter - (jitter * face_n).sum(-1, keepdim=True) * face_n, face_n


def _eye_points(shape: DemoHeadShape, n_each: int, g: torch.Generator
                ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """Each eyeball's ``n_each`` points, area-uniform on its front cap (within 100° of the frontal gaze -z)
    -> per eye (left, right): points [n_each, 3], part labels [n_each] int8, RGB [n_each, 3] (sclera, iris,
    pupil by the angle from the gaze axis)."""
    eye_pts, eye_parts, eye_cols = [], [], []
    centers, r_eye = shape.eye_centers(), shape.eye_radius
    cap = math.radians(100)
    for part, c in ((PART_LEFT_EYE, centers[0]), (PART_RIGHT_EYE, centers[1])):
        u = torch.rand(n_each, generator=g)
        cos_t = 1 - u * (1 - math.cos(cap))
        ang = torch.rand(n_each, generator=g) * 2 * math.pi
        sin_t = torch.sqrt((1 - cos_t**2).clamp_min(0))
        d = torch.stack([sin_t * torch.cos(ang), sin_t * torch.sin(ang), -cos_t], -1)
        eye_pts.append(c + r_eye * d)
        eye_parts.append(torch.full((n_each,), part, dtype=torch.int8))
        theta = torch.acos(cos_t.clamp(-1, 1))
        col = torch.tensor([0.95, 0.94, 0.92]).expand(n_each, 3).clone()
        iris = theta < 0.50
        col[iris] = torch.tensor(shape.iris) * (0.8 + 0.4 * torch.rand(int(iris.sum()), 1, generator=g))
        col[theta < 0.2] = torch.tensor([0.03, 0.03, 0.03])
        eye_cols.append(col)
    return eye_pts, eye_parts, eye_cols


def _skin_colors(p: torch.Tensor, shape: DemoHeadShape, g: torch.Generator) -> torch.Tensor:
    col = torch.tensor(shape.skin).expand(p.shape[0], 3).clone()
    col = col * (0.95 + 0.1 * torch.rand(p.shape[0], 1, generator=g))
    x, y, z = p.unbind(-1)
    front = z < -0.04
    # Hair: the top and back of the head.
    hair = (y < -0.055) & ~(front & (y > -0.07))
    hair |= (z > 0.03) & (y < 0.05)
    col[hair] = torch.tensor([0.18, 0.12, 0.08])
    # Brows, lips and cheeks so the face reads as a face in renders.
    brow = front & ((y + 0.026).abs() < 0.005) & ((x.abs() - 0.031).abs() < 0.017)
    col[brow] = torch.tensor([0.25, 0.17, 0.12])
    lips = front & ((y - 0.062).abs() < 0.007) & (x.abs() < 0.024 - 200 * (y - 0.062) ** 2)
    col[lips] = torch.tensor([0.72, 0.32, 0.32])
    cheek = front & (((x.abs() - 0.045) ** 2 + (y - 0.03) ** 2) < 0.015**2)
    col[cheek] = col[cheek] * torch.tensor([1.0, 0.9, 0.9])
    return col


def demo_camera(width: int = 256, height: int = 256, distance: float = 0.6, fov_y_deg: float = 25.0):
    """A frontal camera framing the demo head (the head fills most of the image)."""
    from toolkit.cameras import Camera, intrinsics_from_fov, look_at

    eye = torch.tensor([0.0, 0.01, -distance])
    return Camera(intrinsics_from_fov(fov_y_deg, width, height), look_at(eye, torch.tensor([0.0, 0.01, 0.0])), width, height)

