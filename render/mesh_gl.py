"""Headless OpenGL triangle-mesh rasterizer (moderngl, EGL, GL 3.3 core).

Renders a mesh with per-vertex colours or a UV texture, Lambert + ambient shading, and reads back
RGB, coverage mask, camera depth, camera-space normals and triangle ids in one pass (multiple render
targets, float32, no MSAA so coverage is exact per pixel centre).

Camera convention as ``toolkit.cameras``: OpenCV axes, ``viewmat`` world-to-camera [4, 4], ``K`` [3, 3]
in pixels, pixel (i, j) sampled at (j + 0.5, i + 0.5). The GL pair comes from
:func:`toolkit.cameras.opengl_projection`, which maps image row r to framebuffer row r, so the
read-back needs no flip; it mirrors the winding, which does not matter because nothing is culled.

Vertices are de-indexed (three corners per face) so face normals stay exact for flat shading and
``gl_PrimitiveID`` is the face index.
"""

from __future__ import annotations

import numpy as np
import torch

from render.gl_context import make_current, shared_context
from toolkit.cameras import opengl_projection
from toolkit.errors import ToolkitError

DEFAULT_COLOR = (0.8, 0.8, 0.8)
MAX_FACES = 1 << 24  # triangle ids travel through a float32 channel: exact below 2^24

_VERTEX_SHADER = """
#version 330 core
uniform mat4 u_view;   // OpenCV world-to-camera
uniform mat4 u_proj;   // OpenGL clip-from-eye (toolkit.cameras.opengl_projection)
in vec3 in_pos;
in vec3 in_nrm;
in vec3 in_col;
in vec2 in_uv;
out vec3 v_cam;
out vec3 v_nrm;
out vec3 v_col;
out vec2 v_uv;
void main() {
    vec4 cam = u_view * vec4(in_pos, 1.0);
    v_cam = cam.xyz;
    v_nrm = mat3(u_view) * in_nrm;
    v_col = in_col;
    v_uv = in_uv;
    // OpenGL eye space is the OpenCV camera with y and z negated.
    gl_Position = u_proj * vec4(cam.x, -cam.y, -cam.z, 1.0);
}
"""

_FRAGMENT_SHADER = """
#version 330 core
uniform vec3 u_light;      // camera-space unit direction from the surface towards the light
uniform float u_ambient;
uniform bool u_use_tex;
uniform sampler2D u_tex;
in vec3 v_cam;
in vec3 v_nrm;
in vec3 v_col;
in vec2 v_uv;
layout(location = 0) out vec4 f_rgb;
layout(location = 1) out vec4 f_nrm_depth;
layout(location = 2) out vec4 f_id;
void main() {
    vec3 n = v_nrm / max(length(v_nrm), 1e-20);
    vec3 albedo = u_use_tex ? texture(u_tex, v_uv).rgb : v_col;
    float lambert = max(dot(n, u_light), 0.0);
    f_rgb = vec4(albedo * (u_ambient + (1.0 - u_ambient) * lambert), 1.0);
    f_nrm_depth = vec4(n, v_cam.z);
    f_id = vec4(float(gl_PrimitiveID + 1), 0.0, 0.0, 1.0);
}
"""

def _as_array(x, name: str, dtype) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        return np.ascontiguousarray(np.asarray(x), dtype=dtype)
    except (TypeError, ValueError) as e:
        raise ToolkitError(f"{name}: expected a numeric array, got {type(x).__name__} ({e})") from e


def _check_shape(a: np.ndarray, name: str, shape: tuple) -> None:
    ok = a.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, a.shape, strict=False))
    if not ok:
        want = "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"
        raise ToolkitError(f"{name}: expected shape {want}, got {list(a.shape)}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ToolkitError(f"{name}: contains NaN or inf")


def face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3], [F, 3] -> [F, 3] unit normals (right-hand rule over the face's vertex order)."""
    v = verts.astype(np.float64)
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3], [F, 3] -> [V, 3] area-weighted unit vertex normals (zero for unused vertices)."""
    v = verts.astype(np.float64)
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])  # length = 2 * area
    out = np.zeros_like(v)
    for k in range(3):
        np.add.at(out, faces[:, k], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-30)


class MeshRasterizer:
    """Rasterize triangle meshes headlessly into a ``width`` × ``height`` float framebuffer.

    ``ctx`` shares an existing moderngl context (e.g. a window's, or one context for many sizes);
    by default the process-wide EGL context of :func:`render.gl_context.shared_context` is used. The framebuffer is
    recreated by :meth:`resize`; programs and the context are reused.
    """

    def __init__(self, width: int, height: int, *, ctx=None):
        self.ctx = ctx if ctx is not None else shared_context()
        make_current(self.ctx)
        self.prog = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self._fbo, self._fbo_objects = None, []
        self._ss_fbo, self._ss_objects = None, []  # framebuffer (and its GL objects) of the last supersampled size
        self.width = self.height = 0
        self.resize(width, height)

    def resize(self, width: int, height: int) -> None:
        """Use a ``width`` × ``height`` framebuffer from now on (a no-op when the size is unchanged)."""
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise ToolkitError(f"MeshRasterizer: width and height must be >= 1, got {width}x{height}")
        if (width, height) == (self.width, self.height):
            return
        self.release_framebuffer()
        # Colour, normal + depth and triangle-id targets (the fragment shader's three outputs).
        self._fbo, self._fbo_objects = self._float_framebuffer((width, height), 3)
        self.width, self.height = width, height

    def _float_framebuffer(self, size: tuple[int, int], n_colour: int):
        """(framebuffer, [its GL objects]) with ``n_colour`` float RGBA targets and a depth buffer."""
        colour = [self.ctx.texture(size, 4, dtype="f4") for _ in range(n_colour)]
        depth = self.ctx.depth_renderbuffer(size)
        fbo = self.ctx.framebuffer(color_attachments=colour, depth_attachment=depth)
        return fbo, [fbo, depth, *colour]

    def release_framebuffer(self) -> None:
        self._release_supersample()
        if self._fbo is not None:
            for obj in self._fbo_objects:
                obj.release()
            self._fbo, self._fbo_objects = None, []
            self.width = self.height = 0

    def release(self) -> None:
        """Free the GL objects of this rasterizer (not the context)."""
        self.release_framebuffer()
        self.prog.release()

    def render(self, verts, faces, viewmat, K, **kw) -> dict[str, np.ndarray]:
        """Render one mesh from one camera.

        Args:
            verts: [V, 3] world positions. faces: [F, 3] vertex indices (any winding; nothing is culled).
            viewmat: [4, 4] world-to-camera (OpenCV). K: [3, 3] intrinsics in pixels of this image size.
            colors: [V, 3] albedo in [0, 1] (default light grey), or
            uvs: [V, 2] with texture [h, w, 3] (uint8 or float in [0, 1]); uv (0, 0) is the texture's
                top-left corner, v grows downwards (row i has its centre at v = (i + 0.5) / h).
            light_dir: [3] camera-space direction from the surface towards the light; default (0, 0, -1),
                a headlight at the camera.
            ambient: shade = ambient + (1 - ambient) · max(0, n·l), n the (unflipped) outward normal.
            background: RGB where nothing is drawn.
            near, far: clip distances along the camera z.
            smooth: interpolate area-weighted vertex normals (for curved meshes) instead of face normals.
            supersample: odd s >= 1. s > 1 rasterizes s x s samples per pixel and box-filters ``rgb`` (composited
                on ``background`` first), i.e. anti-aliases edges the way a camera's pixel integrates light;
                sub-pixel detail such as an iris edge then moves the pixel values continuously. The discrete
                outputs (``mask``, ``depth``, ``normals``, ``tri_id``) come from a second, plain pass: exactly
                those of an s = 1 render.

        Returns:
            dict of numpy arrays: ``rgb`` [H, W, 3] float32, ``mask`` [H, W] bool, ``depth`` [H, W] float32
            camera z (0 where empty), ``normals`` [H, W, 3] float32 camera-space unit normals (0 where
            empty), ``tri_id`` [H, W] int32 face index (-1 where empty).
        """
        view = _as_array(viewmat, "viewmat", np.float32)
        _check_shape(view, "viewmat", (4, 4))
        Kn = _as_array(K, "K", np.float32)
        _check_shape(Kn, "K", (3, 3))
        light = kw.pop("light_dir", None)
        if light is not None:
            light = _as_array(light, "light_dir", np.float32).reshape(1, -1)
        return self.render_views(verts, faces, view[None], Kn[None], light_dir=light, **kw)[0]

    def render_views(
        self,
        verts,
        faces,
        viewmats,
        Ks,
        *,
        colors=None,
        uvs=None,
        texture=None,
        light_dir=None,
        ambient: float = 0.3,
        background=(1.0, 1.0, 1.0),
        near: float = 0.01,
        far: float = 100.0,
        smooth: bool = False,
        supersample: int = 1,
    ) -> list[dict[str, np.ndarray]]:
        """Render one mesh from C cameras, uploading it once: viewmats [C, 4, 4], Ks [C, 3, 3].

        ``light_dir`` is None (headlight), [3] (the same camera-space direction for every view) or
        [C, 3] (one per view, e.g. a world-fixed light turned into each camera). Other arguments and the
        per-view result dicts as in :meth:`render`.
        """
        v = _as_array(verts, "verts", np.float32)
        f_raw = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
        if f_raw.size and f_raw.dtype.kind not in "iu":
            raise ToolkitError(f"faces: expected integer vertex indices, got dtype {f_raw.dtype}")
        f = np.ascontiguousarray(f_raw, dtype=np.int64)
        _check_shape(v, "verts", (None, 3))
        _check_shape(f, "faces", (None, 3))
        if v.shape[0] == 0 or f.shape[0] == 0:
            raise ToolkitError(f"mesh is empty ({v.shape[0]} vertices, {f.shape[0]} faces); nothing to render")
        if f.shape[0] >= MAX_FACES:
            raise ToolkitError(f"faces: at most {MAX_FACES - 1} faces supported, got {f.shape[0]}")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise ToolkitError(f"faces: indices must be in [0, {v.shape[0] - 1}], got [{f.min()}, {f.max()}]")
        views = _as_array(viewmats, "viewmats", np.float32)
        _check_shape(views, "viewmats", (None, 4, 4))
        C = views.shape[0]
        Kn = _as_array(Ks, "Ks", np.float32)
        _check_shape(Kn, "Ks", (C, 3, 3))
        if not (0 < near < far) or not np.isfinite(far):
            raise ToolkitError(f"near/far: expected 0 < near < far < inf, got near={near}, far={far}")
        if not 0.0 <= float(ambient) <= 1.0:
            raise ToolkitError(f"ambient: expected a value in [0, 1], got {ambient}")
        bg = _as_array(background, "background", np.float32).reshape(-1)
        if bg.shape != (3,) or not np.isfinite(bg).all():
            raise ToolkitError(f"background: expected 3 finite RGB values, got {list(bg.shape)}")
        if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) \
                or supersample < 1 or supersample % 2 == 0:
            raise ToolkitError(f"supersample: expected an odd integer >= 1 (samples per pixel side), got {supersample!r}")
        ss = int(supersample)

        V = v.shape[0]
        if colors is not None:
            col = _as_array(colors, "colors", np.float32)
            _check_shape(col, "colors", (V, 3))
        else:
            col = np.broadcast_to(np.asarray(DEFAULT_COLOR, np.float32), (V, 3))
        use_tex = texture is not None
        if use_tex:
            if uvs is None:
                raise ToolkitError("texture given without uvs: pass uvs [V, 2]")
            uv = _as_array(uvs, "uvs", np.float32)
            _check_shape(uv, "uvs", (V, 2))
            tex = texture.detach().cpu().numpy() if isinstance(texture, torch.Tensor) else np.asarray(texture)
            if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
                raise ToolkitError(f"texture: expected shape [h, w, 3], got {list(tex.shape)}")
            tex = tex.astype(np.float32) / 255.0 if tex.dtype == np.uint8 else tex.astype(np.float32)
            if not np.isfinite(tex).all():
                raise ToolkitError("texture: contains NaN or inf")
        else:
            uv = np.zeros((V, 2), np.float32)

        if light_dir is None:
            lights = np.tile(np.array([[0.0, 0.0, -1.0]], np.float32), (C, 1))
        else:
            lights = _as_array(light_dir, "light_dir", np.float32)
            lights = np.tile(lights.reshape(1, -1), (C, 1)) if lights.size == 3 else lights
            norms = np.linalg.norm(lights, axis=-1) if lights.ndim == 2 and lights.shape[-1] == 3 else None
            if lights.shape != (C, 3) or not np.isfinite(lights).all() or (norms < 1e-12).any():
                raise ToolkitError(f"light_dir: expected finite non-zero 3-vectors, [3] or [{C}, 3]")
            lights = lights / norms[:, None]

        ctx = self.ctx
        make_current(ctx)
        ibo = None
        if smooth:
            # Shared vertices + an index buffer: the vertex shader runs once per vertex, not per corner.
            attrs = np.concatenate([v, vertex_normals(v, f).astype(np.float32), col, uv], axis=-1)
            vbo = ctx.buffer(np.ascontiguousarray(attrs, dtype=np.float32).tobytes())
            ibo = ctx.buffer(f.astype(np.int32).tobytes())
        else:
            # De-indexed corners keep face normals exact (flat shading).
            nrm = np.repeat(face_normals(v, f)[:, None], 3, 1).astype(np.float32)
            corners = np.concatenate([v[f], nrm, col[f], uv[f]], axis=-1).astype(np.float32).reshape(-1, 11)
            vbo = ctx.buffer(corners.tobytes())
        vao = ctx.vertex_array(self.prog, [(vbo, "3f 3f 3f 2f", "in_pos", "in_nrm", "in_col", "in_uv")],
                               index_buffer=ibo, index_element_size=4)
        gl_tex = None
        results = []
        try:
            self.prog["u_ambient"].value = float(ambient)
            self.prog["u_use_tex"].value = use_tex
            if use_tex:
                gl_tex = ctx.texture((tex.shape[1], tex.shape[0]), 3, np.ascontiguousarray(tex).tobytes(), dtype="f4")
                gl_tex.filter = (ctx.LINEAR, ctx.LINEAR)
                gl_tex.repeat_x = gl_tex.repeat_y = False
                gl_tex.use(location=0)
                self.prog["u_tex"].value = 0
            ctx.scissor = None  # the shared context may hold a preview pass's scissor box
            ctx.disable(ctx.CULL_FACE | ctx.BLEND)
            ctx.enable(ctx.DEPTH_TEST)

            def draw(fbo, K: np.ndarray, w: int, h: int, clear=(0.0, 0.0, 0.0, 0.0)) -> None:
                fbo.use()
                ctx.viewport = (0, 0, w, h)
                P = opengl_projection(torch.from_numpy(K), w, h, near, far).numpy()
                self.prog["u_proj"].write(np.ascontiguousarray(P.T, dtype=np.float32).tobytes())
                fbo.clear(*clear, depth=1.0)
                vao.render(ctx.TRIANGLES)

            for c in range(C):
                self.prog["u_view"].write(np.ascontiguousarray(views[c].T).tobytes())  # GL is column-major
                self.prog["u_light"].value = tuple(float(x) for x in lights[c])
                rgb_aa = None
                if ss > 1:
                    # Pixel-edge convention (x = 0 is the left edge): s x s samples per pixel is K scaled by s.
                    fbo = self._supersample_fbo(ss)
                    # Cleared to the background, so every sample is already composited on it.
                    draw(fbo, Kn[c] * np.array([[ss], [ss], [1]], np.float32), self.width * ss, self.height * ss,
                         clear=(*(float(x) for x in bg), 0.0))
                    rgb_aa = self._read_supersampled(fbo, ss)
                # The discrete buffers come from a plain pass: the exact samples of an s = 1 render.
                draw(self._fbo, Kn[c], self.width, self.height)
                out = self._read_back(bg)
                if rgb_aa is not None:
                    out["rgb"] = rgb_aa
                results.append(out)
        finally:
            vao.release()
            vbo.release()
            if ibo is not None:
                ibo.release()
            if gl_tex is not None:
                gl_tex.release()
        return results

    def _supersample_fbo(self, ss: int):
        """An RGBA + depth framebuffer ``ss`` times this rasterizer's size, kept until the size changes."""
        size = (self.width * ss, self.height * ss)
        if self._ss_fbo is None or self._ss_fbo.size != size:
            limit = int(self.ctx.info.get("GL_MAX_TEXTURE_SIZE", 8192))
            if max(size) > limit:
                raise ToolkitError(f"supersample: {self.width}x{self.height} at {ss}x{ss} samples needs a {size[0]}x{size[1]} "
                                   f"target, above this GL's limit of {limit}; use a smaller supersample")
            self._release_supersample()
            # One colour attachment: the shader's normal/id outputs have no buffer there and are dropped.
            self._ss_fbo, self._ss_objects = self._float_framebuffer(size, 1)
        return self._ss_fbo

    def _release_supersample(self) -> None:
        for obj in self._ss_objects:
            obj.release()
        self._ss_fbo, self._ss_objects = None, []

    def _read_supersampled(self, fbo, ss: int) -> np.ndarray:
        """[H, W, 3] box filter of the s x s samples of each pixel (drawn on a background-cleared target)."""
        H, W = self.height, self.width
        fine = np.frombuffer(fbo.read(components=3, dtype="f4"), np.float32).reshape(H, ss, W, ss, 3)
        return fine.sum(axis=(1, 3), dtype=np.float32) / np.float32(ss * ss)

    def _read_back(self, bg: np.ndarray) -> dict[str, np.ndarray]:
        H, W = self.height, self.width

        def read(i):
            return np.frombuffer(self._fbo.read(components=4, attachment=i, dtype="f4"), np.float32).reshape(H, W, 4)

        rgba, nd, ids = read(0), read(1), read(2)
        mask = rgba[..., 3] > 0.5
        rgb = np.where(mask[..., None], rgba[..., :3], bg[None, None, :]).astype(np.float32)
        normals = np.where(mask[..., None], nd[..., :3], 0.0).astype(np.float32)
        depth = np.where(mask, nd[..., 3], 0.0).astype(np.float32)
        tri_id = np.where(mask, np.rint(ids[..., 0]).astype(np.int64) - 1, -1).astype(np.int32)
        return {"rgb": rgb, "mask": mask, "depth": depth, "normals": normals, "tri_id": tri_id}


def render_mesh(verts, faces, viewmat, K, width: int, height: int, **kw) -> dict[str, np.ndarray]:
    """One-shot :meth:`MeshRasterizer.render` on the shared context (keyword arguments as there)."""
    r = MeshRasterizer(width, height)
    try:
        return r.render(verts, faces, viewmat, K, **kw)
    finally:
        r.release()
