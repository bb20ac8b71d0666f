"""Procedural subjects: identity + expression parameters -> head mesh, eyeball meshes, exact labels.

A subject is the analytic head of :class:`toolkit.procedural.DemoHeadShape` (one shape for the demo head
and every subject) with identity parameters, meshed by mapping a warped icosphere through its
star-shaped radius function (so the head mesh is watertight by construction, with extra vertices
around the eyes and mouth), plus two eyeball meshes: spheres with a sclera, an iris and a pupil, whose
boundaries are exact rings. Gaze is a rigid rotation of each eyeball about its centre
(``toolkit.eyes.gaze_rotation``), the same rotation for both eyes (a gaze target at infinity).

Frames (see docs/data.md): the head frame is the toolkit's (metres, x image-right in a frontal view,
y down, the face looks towards -z, canonical gaze (0, 0, -1)); ``pose`` = axis-angle (3) + translation
(3) maps head to world: x_world = scale · R(pose[:3]) · x_head + pose[3:]; cameras are world-to-camera
OpenCV. "Left eye" is the image-left eye (x < 0, iBUG 36-41).

The parameters (identity, expression, latent code) are :mod:`train.data.subject_params`; poses and the
normalized camera :mod:`train.data.poses`; the mesh pieces (lens warp, eyeball, landmarks)
:mod:`train.data.head_mesh`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from toolkit.cameras import Camera
from toolkit.errors import ToolkitError
from toolkit.eyes import gaze_rotation
from toolkit.procedural import DemoHeadShape
from toolkit.rotations import vector_to_pitchyaw
from train.data.head_mesh import (
    EYE_IRIS,
    EYE_PUPIL,
    EYE_SCLERA,
    eyeball_mesh,
    landmark_base_xy,
    lens_warp,
    smoothstep,
)
from train.data.poses import pose_matrix
from train.data.subject_params import EXPRESSION_NAMES, SubjectParams, check_expression

# Parts of the rendered scene (as in toolkit.scene): face 0, left eye 1, right eye 2.
PART_HEAD, PART_LEFT_EYE, PART_RIGHT_EYE = 0, 1, 2


# ----------------------------------------------------------------------------------------------
# Meshes
# ----------------------------------------------------------------------------------------------


@dataclass
class Subject:
    """A built subject: neutral meshes in the head frame plus everything needed to pose them.

    Attributes:
        params: the identity.
        head_dirs: [V, 3] unit directions from the head centre (the mesh vertices are
            ``shape.surface_points(head_dirs)`` for the expression's shape).
        head_faces: [F, 3] int64, outward winding, watertight.
        eye_local: [Ve, 3] unit eyeball vertices looking along -z; eye_faces [Fe, 3]; eye_region [Fe].
        eye_centers: [2, 3] head frame (left = image-left first); eye_radius: metres.
    """

    params: SubjectParams
    head_dirs: np.ndarray
    head_faces: np.ndarray
    eye_local: np.ndarray
    eye_faces: np.ndarray
    eye_region: np.ndarray
    eye_theta: np.ndarray
    eye_colors: np.ndarray
    eye_centers: np.ndarray
    eye_radius: float
    face_center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    # -- shape ------------------------------------------------------------------------------
    def shape(self, expression=None) -> DemoHeadShape:
        return self.params.shape(expression)

    def head_vertices(self, expression=None) -> np.ndarray:
        """[V, 3] head-frame vertices for ``expression`` [4] (default neutral)."""
        d = torch.from_numpy(self.head_dirs)
        return self.shape(expression).surface_points(d).numpy().astype(np.float32)

    def neutral_vertices(self) -> np.ndarray:
        return self.head_vertices(None)

    def head_colors(self, expression=None) -> np.ndarray:
        """[V, 3] albedo of the head vertices (skin, hair, brows, lips, eye sockets, mouth)."""
        shape = self.shape(expression)
        cols = self.params.colors()
        d = torch.from_numpy(self.head_dirs)
        x, y = (t.numpy() for t in shape.base_xy(d))
        z = self.head_dirs[:, 2]
        pz = shape.center[2] + shape.ellipsoid_radius(d).numpy() * z
        c = np.tile(cols["skin"], (len(x), 1))
        front = z < -0.35
        # Hair: top and back (hairline raised over the forehead).
        hair = ((y < shape.eye_y - 0.048) & ~(front & (y > shape.eye_y - 0.062))) | ((pz > 0.02) & (y < 0.06))
        c[hair] = cols["hair"]
        # Brows follow brow_raise.
        by = shape.eye_y - 0.020 - 0.004 * shape.brow_raise
        for ex in (-shape.eye_offset_x, shape.eye_offset_x):
            dx = x - ex
            brow = front & (np.abs(y - (by - 0.004 * (1 - (dx / 0.018) ** 2))) < 0.0028) & (np.abs(dx) < 0.018)
            c[brow] = cols["hair"] * 1.1
        # Lips: between the outer lip line and the mouth opening.
        xt = torch.from_numpy(x)
        yc = shape.mouth_centerline(xt).numpy()
        h_open = shape.mouth_half_opening(xt).numpy()
        prof = np.sqrt(np.clip(1 - (x / (shape.mouth_width * 1.05)) ** 2, 0, 1))
        upper = (y < yc) & (yc - y < h_open + 0.0045 * prof)
        lower = (y >= yc) & (y - yc < h_open + 0.0060 * prof)
        lips = front & (np.abs(x) < shape.mouth_width * 1.05) & (upper | lower)
        c[lips] = cols["lips"]
        # Inside the mouth and the eye sockets: dark, reddish.
        mouth_in = shape.mouth_weight(d).numpy()
        c = c * (1 - mouth_in[:, None]) + mouth_in[:, None] * np.array([0.25, 0.06, 0.07])
        sock = shape.socket_weight(d).numpy()
        c = c * (1 - 0.6 * sock[:, None]) + 0.6 * sock[:, None] * np.array([0.55, 0.30, 0.30])
        cheek = front & (((np.abs(x) - 0.045) ** 2 + (y - 0.03) ** 2) < 0.015**2)
        c[cheek] *= np.array([1.0, 0.92, 0.92])
        return np.clip(c, 0, 1).astype(np.float32)

    # -- eyes -------------------------------------------------------------------------------
    def eyeball_vertices(self, pitchyaw) -> np.ndarray:
        """[2, Ve, 3] head-frame eyeball vertices turned to head-frame gaze ``pitchyaw`` [2] (radians): each
        eye's optical axis is the gaze plus the subject's κ (``SubjectParams.kappa``), its yaw temporal (the
        image-left eye, at x < 0, towards -x: + yaw; the other - yaw)."""
        py = np.array(pitchyaw, np.float64)
        kp, ky = self.params.kappa
        if not (kp or ky):
            R = gaze_rotation(torch.as_tensor(py)).numpy()
            local = self.eye_radius * self.eye_local @ R.T
            return (local[None] + self.eye_centers[:, None, :]).astype(np.float32)
        eyes = []
        for centre, sign in zip(self.eye_centers, (1.0, -1.0)):
            R = gaze_rotation(torch.as_tensor(py + np.array([kp, sign * ky]))).numpy()
            eyes.append(self.eye_radius * self.eye_local @ R.T + centre)
        return np.stack(eyes).astype(np.float32)

    # -- landmarks --------------------------------------------------------------------------
    def landmarks(self, expression=None) -> np.ndarray:
        """[68, 3] iBUG-68 landmarks in the head frame on the expression's surface."""
        shape = self.shape(expression)
        xy = landmark_base_xy(shape)
        d = shape.dirs_from_base_xy(torch.from_numpy(xy))
        return shape.surface_points(d).numpy().astype(np.float32)

    # -- whole scene ------------------------------------------------------------------------
    def scene_mesh(self, expression, pitchyaw) -> dict[str, np.ndarray]:
        """Head + both eyeballs as one mesh in the head frame.

        Returns verts [V', 3], faces [F', 3], colors [V', 3], face_part [F'] (0 head, 1 left eye,
        2 right eye) and face_eye_region [F'] (-1 head, else 0 sclera / 1 iris / 2 pupil).
        """
        hv = self.head_vertices(expression)
        hc = self.head_colors(expression)
        ev = self.eyeball_vertices(pitchyaw)
        nv, ne = len(hv), len(self.eye_local)
        verts = np.concatenate([hv, ev[0], ev[1]])
        faces = np.concatenate([self.head_faces, self.eye_faces + nv, self.eye_faces + nv + ne])
        colors = np.concatenate([hc, self.eye_colors, self.eye_colors])
        F, Fe = len(self.head_faces), len(self.eye_faces)
        part = np.concatenate([np.full(F, PART_HEAD), np.full(Fe, PART_LEFT_EYE), np.full(Fe, PART_RIGHT_EYE)])
        region = np.concatenate([np.full(F, -1), self.eye_region, self.eye_region])
        return {"verts": verts, "faces": faces, "colors": colors, "face_part": part.astype(np.int8),
                "face_eye_region": region.astype(np.int8)}


def build_subject(params: SubjectParams, *, subdivisions: int = 5) -> Subject:
    """Mesh a subject: warped icosphere head (watertight) + eyeball template with exact iris rings.

    ``subdivisions`` in [0, 7]: the head has 10 · 4^subdivisions + 2 vertices (7: 163842; each step is 4x the
    memory and time of every render)."""
    import trimesh

    from toolkit.limits import check_count

    check_count(subdivisions, "subdivisions", 0, 7, "icosphere subdivisions")

    shape = params.shape()
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    dirs = np.asarray(ico.vertices, np.float64)
    faces = np.asarray(ico.faces, np.int64)
    c = np.asarray(shape.center)
    for focus_xy, strength, sigma in (
        ((-shape.eye_offset_x, shape.eye_y), 0.72, 0.22),
        ((shape.eye_offset_x, shape.eye_y), 0.72, 0.22),
        ((0.0, shape.mouth_y), 0.55, 0.25),
    ):
        focus = shape.dirs_from_base_xy(torch.tensor([focus_xy], dtype=torch.float64)).numpy()[0]
        dirs = lens_warp(dirs, focus, strength, sigma)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # Outward winding survives the bijective warp; enforce it anyway against the surface.
    p = shape.surface_points(torch.from_numpy(dirs)).numpy()
    n = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    if ((n * (p[faces].mean(1) - c)).sum(1) < 0).mean() > 0.5:
        faces = faces[:, ::-1].copy()

    u = params._u
    theta_iris = 0.50 + 0.05 * u("iris_size")
    theta_pupil = 0.19 + 0.04 * u("pupil_size")
    ev, ef, region, theta = eyeball_mesh(theta_pupil, theta_iris)
    iris_col = params.colors()["iris"]
    ecol = np.tile(np.array([0.95, 0.94, 0.91], np.float32), (len(ev), 1))
    t_iris = np.clip((theta - theta_pupil) / (theta_iris - theta_pupil), 0, 1)
    # Vertex colours by region; a vertex on a boundary ring belongs to the band that created it.
    vreg = np.zeros(len(ev), np.int8)
    for reg in (EYE_PUPIL, EYE_IRIS, EYE_SCLERA):
        vreg[np.unique(ef[region == reg])] = reg
    iris_v = vreg == EYE_IRIS
    ecol[iris_v] = iris_col * (1.15 - 0.55 * smoothstep(0.6, 1.0, t_iris[iris_v]))[:, None]
    ecol[vreg == EYE_PUPIL] = (0.03, 0.03, 0.03)
    sclera_back = (vreg == EYE_SCLERA) & (theta > 1.2)
    ecol[sclera_back] = (0.93, 0.80, 0.78)
    subject = Subject(
        params=params, head_dirs=dirs.astype(np.float64), head_faces=faces, eye_local=ev, eye_faces=ef,
        eye_region=region, eye_theta=theta, eye_colors=np.clip(ecol, 0, 1).astype(np.float32),
        eye_centers=shape.eye_centers().numpy().astype(np.float64), eye_radius=float(shape.eye_radius),
    )
    lm = subject.landmarks()
    subject.face_center = lm[[36, 39, 42, 45, 48, 54]].mean(0).astype(np.float64)
    return subject


# ----------------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------------


_RASTERIZERS: dict = {}


SUPERSAMPLE = 3
"""Samples per pixel side of the synthetic images. Anti-aliased like a camera's pixels: at 128² an eye is ~12 px
wide and the iris moves ~0.1 px per degree of gaze, which an aliased render turns into pixel steps (the eye
estimator's held-out error drops from 6.2° to 4.9° with 3 x 3 samples, same data otherwise), and a splatter's
smooth edges are compared with smooth targets."""

VIEW_KEYS = ("rgb", "head_mask", "left_eye_mask", "right_eye_mask", "eye_region", "depth", "landmarks_2d",
             "landmarks_3d", "vertice", "K", "w2c_R", "w2c_T", "pitchyaw_cam", "face_head_pose")
"""The per-view outputs of :func:`render_views` (it adds the per-row inputs ``pitchyaw_head``, ``pose``,
``scale`` and ``expression``)."""

_VIEW_DTYPES = {"rgb": np.float32, "depth": np.float32, "landmarks_2d": np.float32, "landmarks_3d": np.float32,
                "vertice": np.float32, "K": np.float32, "w2c_R": np.float32, "w2c_T": np.float32,
                "pitchyaw_cam": np.float32, "face_head_pose": np.float32, "eye_region": np.int8}


def _rasterizer(width: int, height: int):
    import os

    from render.mesh_gl import MeshRasterizer

    r = _RASTERIZERS.get(os.getpid())  # per process: GL objects do not survive fork
    if r is None:
        _RASTERIZERS.clear()
        r = _RASTERIZERS[os.getpid()] = MeshRasterizer(width, height)
    r.resize(width, height)
    return r


def render_views(subject: Subject, gaze, pose, expression, cameras: list[Camera], *, scale=1.0,
                 light_dirs=None, ambient: float = 0.45, rasterizer=None,
                 supersample: int | None = None) -> dict[str, np.ndarray]:
    """Render N images of ``subject`` with exact labels (any gaze / pose / expression / camera).

    Args:
        gaze: [N, 2] or [2] head-frame (pitch, yaw) radians. pose: [N, 6] or [6] head -> world.
        expression: [N, 4] or [4]. cameras: N ``toolkit.cameras.Camera`` (world-to-camera, all one size).
        scale: scalar or [N] head scale. light_dirs: [N, 3] or [3] world-space directions towards the
            light (default: a headlight per camera).
        rasterizer: a ``render.mesh_gl.MeshRasterizer`` to reuse (default: one per process).
        supersample: samples per pixel side (odd; default :data:`SUPERSAMPLE`): ``rgb`` is anti-aliased like a
            camera image, masks, ids, depth and landmarks are the same as without it.

    Rows with identical gaze, pose, expression, scale and light share one mesh upload.

    Returns dict of numpy arrays: ``rgb`` [N, H, W, 3] float32 in [0, 1] on white; ``head_mask``,
    ``left_eye_mask``, ``right_eye_mask`` [N, H, W] bool (head = every drawn pixel, eye = visible
    eyeball); ``eye_region`` [N, H, W] int8 (-1, 0 sclera, 1 iris, 2 pupil); ``depth`` [N, H, W];
    ``landmarks_2d`` [N, 68, 2] pixels; ``landmarks_3d`` [N, 68, 3] world; ``vertice`` [N, V, 3] world
    head vertices; ``K`` [N, 3, 3]; ``w2c_R`` [N, 3, 3]; ``w2c_T`` [N, 3]; ``pitchyaw_head``,
    ``pitchyaw_cam``, ``face_head_pose`` [N, 2]; ``pose`` [N, 6]; ``scale`` [N, 1]; ``expression`` [N, 4].
    """
    gaze, pose, expression, scale, lights = _checked_rows(len(cameras), gaze, pose, expression, scale, light_dirs)
    W, H = cameras[0].width, cameras[0].height
    if any((c.width, c.height) != (W, H) for c in cameras):
        raise ToolkitError("render_views: all cameras must have the same image size")
    rast = rasterizer or _rasterizer(W, H)
    rast.resize(W, H)
    out = {k: [] for k in VIEW_KEYS}
    key = np.concatenate([gaze, pose, expression, scale] + ([lights] if lights is not None else []), 1)
    for start, stop in _runs_of_equal_rows(key):
        posed = _posed_scene(subject, gaze[start], pose[start], expression[start], float(scale[start, 0]))
        views = np.stack([c.viewmat.numpy() for c in cameras[start:stop]])
        Ks = np.stack([c.K.numpy() for c in cameras[start:stop]])
        cam_lights = None if lights is None else np.einsum("cij,j->ci", views[:, :3, :3], lights[start])
        res = rast.render_views(posed["world"], posed["mesh"]["faces"], views, Ks, colors=posed["mesh"]["colors"],
                                light_dir=cam_lights, ambient=ambient, smooth=True,
                                supersample=SUPERSAMPLE if supersample is None else supersample)
        g_head = _pitchyaw_vec(gaze[start])
        for c, r in enumerate(res):
            _append_view(out, r, posed, views[c], Ks[c], g_head, len(subject.head_dirs))
    result = {k: np.stack(v) for k, v in out.items()}
    for k, d in _VIEW_DTYPES.items():
        result[k] = result[k].astype(d)
    result.update(pitchyaw_head=gaze.astype(np.float32), pose=pose.astype(np.float32),
                  scale=scale.astype(np.float32), expression=expression.astype(np.float32))
    return result


def _checked_rows(n: int, gaze, pose, expression, scale, light_dirs) -> tuple[np.ndarray, ...]:
    """The per-row inputs of :func:`render_views` for ``n`` cameras as float64 ``[n, k]`` arrays (one row
    broadcast to all): gaze [n, 2], pose [n, 6], expression [n, 4], scale [n, 1], lights [n, 3] or None."""
    if n == 0:
        raise ToolkitError("render_views: no cameras given")

    def rows(a, width, name):
        a = np.asarray(a, np.float64)
        if a.shape == (width,):
            a = np.broadcast_to(a, (n, width))
        if a.shape != (n, width) or not np.isfinite(a).all():
            raise ToolkitError(f"render_views: {name} must be finite [{n}, {width}] or [{width}], got {list(a.shape)}")
        return np.ascontiguousarray(a)

    gaze = rows(gaze, 2, "gaze")
    if (np.abs(gaze) > math.pi / 2 + 1e-6).any():
        raise ToolkitError("render_views: gaze pitch/yaw must lie in [-pi/2, pi/2] radians")
    pose = rows(pose, 6, "pose")
    expression = rows(check_expression(expression), len(EXPRESSION_NAMES), "expression")
    scale = rows(np.reshape(np.asarray(scale, np.float64), (-1, 1)) if np.ndim(scale) else [float(scale)], 1, "scale")
    if (scale <= 0).any():
        raise ToolkitError("render_views: scale must be > 0")
    lights = None if light_dirs is None else rows(light_dirs, 3, "light_dirs")
    return gaze, pose, expression, scale, lights


def _runs_of_equal_rows(key: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of consecutive identical rows of ``key`` [n, k] (one mesh upload each)."""
    runs, start, n = [], 0, len(key)
    while start < n:
        stop = start + 1
        while stop < n and np.array_equal(key[stop], key[start]):
            stop += 1
        runs.append((start, stop))
        start = stop
    return runs


def _posed_scene(subject: Subject, gaze: np.ndarray, pose: np.ndarray, expression: np.ndarray, s: float) -> dict:
    """One row's scene in the world: {"R" [3, 3], "t" [3] (the head pose), "mesh" (:meth:`Subject.scene_mesh`),
    "world" [V', 3] float32 mesh vertices, "landmarks" [68, 3] float64}."""
    R, t = pose_matrix(pose)
    mesh = subject.scene_mesh(expression, gaze)
    world = (s * mesh["verts"].astype(np.float64) @ R.T + t).astype(np.float32)
    lm = subject.landmarks(expression).astype(np.float64)
    return {"R": R, "t": t, "mesh": mesh, "world": world, "landmarks": s * lm @ R.T + t}


def _append_view(out: dict[str, list], r: dict, posed: dict, view: np.ndarray, K: np.ndarray, g_head: np.ndarray,
                 num_head_vertices: int) -> None:
    """Append one rendered view's images and labels to ``out``: ``r`` is the rasterizer's result, ``view``
    [4, 4] and ``K`` [3, 3] its camera, ``g_head`` [3] the head-frame gaze vector."""
    mesh, lm_w, R = posed["mesh"], posed["landmarks"], posed["R"]
    Rc, tc = view[:3, :3].astype(np.float64), view[:3, 3].astype(np.float64)
    tri = r["tri_id"]
    part = np.where(tri >= 0, mesh["face_part"][np.clip(tri, 0, None)], -1)
    out["rgb"].append(r["rgb"])
    out["head_mask"].append(r["mask"])
    out["left_eye_mask"].append(part == PART_LEFT_EYE)
    out["right_eye_mask"].append(part == PART_RIGHT_EYE)
    out["eye_region"].append(np.where(tri >= 0, mesh["face_eye_region"][np.clip(tri, 0, None)], -1))
    out["depth"].append(r["depth"])
    pc = lm_w @ Rc.T + tc
    K = K.astype(np.float64)
    out["landmarks_2d"].append(np.stack([K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 1] * pc[:, 1] / pc[:, 2] + K[0, 2],
                                         K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], -1))
    out["landmarks_3d"].append(lm_w)
    out["vertice"].append(posed["world"][:num_head_vertices])
    out["K"].append(K)
    out["w2c_R"].append(Rc)
    out["w2c_T"].append(tc)
    RcR = Rc @ R
    out["pitchyaw_cam"].append(vector_to_pitchyaw(torch.from_numpy(RcR @ g_head)).numpy())
    out["face_head_pose"].append(vector_to_pitchyaw(torch.from_numpy(RcR @ np.array([0.0, 0, -1]))).numpy())


def _pitchyaw_vec(py: np.ndarray) -> np.ndarray:
    p, y = float(py[0]), float(py[1])
    return np.array([-math.cos(p) * math.sin(y), -math.sin(p), -math.cos(p) * math.cos(y)])
