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
from render.mesh_inputs import (
    as_array,
    camera_arrays,
    check_render_options,
    check_shape,
    face_normals,
    light_directions,
    mesh_arrays,
    surface_arrays,
    vertex_normals,
)
from render.mesh_shaders import MESH_FRAGMENT, MESH_VERTEX
from toolkit.cameras import opengl_projection
from toolkit.errors import ToolkitError


class MeshRasterizer:
    """Rasterize triangle meshes headlessly into a ``width`` × ``height`` float framebuffer.

    ``ctx`` shares an existing moderngl context (e.g. a window's, or one context for many sizes);
    by default the process-wide EGL context of :func:`render.gl_context.shared_context` is used. The
    framebuffer is recreated by :meth:`resize`; programs and the context are reused.
    """

    def __init__(self, width: int, height: int, *, ctx=None):
        self.ctx = ctx if ctx is not None else shared_context()
        make_current(self.ctx)
        self.prog = self.ctx.program(vertex_shader=MESH_VERTEX, fragment_shader=MESH_FRAGMENT)
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
        view = as_array(viewmat, "viewmat", np.float32)
        check_shape(view, "viewmat", (4, 4))
        Kn = as_array(K, "K", np.float32)
        check_shape(Kn, "K", (3, 3))
        light = kw.pop("light_dir", None)
        if light is not None:
            light = as_array(light, "light_dir", np.float32).reshape(1, -1)
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
        v, f = mesh_arrays(verts, faces)
        views, Kn = camera_arrays(viewmats, Ks)
        bg, ss = check_render_options(near, far, ambient, background, supersample)
        col, uv, tex = surface_arrays(v.shape[0], colors, uvs, texture)
        lights = light_directions(light_dir, views.shape[0])
        make_current(self.ctx)
        vao, owned = self._upload_mesh(v, f, col, uv, smooth)
        try:
            self._set_shading(float(ambient), tex, owned)
            return [self._render_view(vao, views[c], Kn[c], lights[c], bg, ss, near, far)
                    for c in range(views.shape[0])]
        finally:
            vao.release()
            for obj in owned:
                obj.release()

    def _upload_mesh(self, v: np.ndarray, f: np.ndarray, col: np.ndarray, uv: np.ndarray, smooth: bool):
        """The mesh as vertex (and index) buffers -> (vertex array, [the buffers, to release with it])."""
        ctx = self.ctx
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
        return vao, [vbo] + ([ibo] if ibo is not None else [])

    def _set_shading(self, ambient: float, tex: np.ndarray | None, owned: list) -> None:
        """Set the shading uniforms and the GL state of a mesh pass; a texture made is appended to ``owned``."""
        ctx = self.ctx
        self.prog["u_ambient"].value = ambient
        self.prog["u_use_tex"].value = tex is not None
        if tex is not None:
            gl_tex = ctx.texture((tex.shape[1], tex.shape[0]), 3, np.ascontiguousarray(tex).tobytes(), dtype="f4")
            owned.append(gl_tex)
            gl_tex.filter = (ctx.LINEAR, ctx.LINEAR)
            gl_tex.repeat_x = gl_tex.repeat_y = False
            gl_tex.use(location=0)
            self.prog["u_tex"].value = 0
        ctx.scissor = None  # the shared context may hold a preview pass's scissor box
        ctx.disable(ctx.CULL_FACE | ctx.BLEND)
        ctx.enable(ctx.DEPTH_TEST)

    def _draw(self, vao, fbo, K: np.ndarray, w: int, h: int, near: float, far: float,
              clear=(0.0, 0.0, 0.0, 0.0)) -> None:
        """Draw the uploaded mesh into ``fbo`` ([w, h]) through intrinsics K [3, 3], cleared to ``clear`` first."""
        fbo.use()
        self.ctx.viewport = (0, 0, w, h)
        P = opengl_projection(torch.from_numpy(K), w, h, near, far).numpy()
        self.prog["u_proj"].write(np.ascontiguousarray(P.T, dtype=np.float32).tobytes())
        fbo.clear(*clear, depth=1.0)
        vao.render(self.ctx.TRIANGLES)

    def _render_view(self, vao, view: np.ndarray, K: np.ndarray, light: np.ndarray, bg: np.ndarray, ss: int,
                     near: float, far: float) -> dict[str, np.ndarray]:
        """One camera (view [4, 4], K [3, 3], light [3]) -> the result dict of :meth:`render`."""
        self.prog["u_view"].write(np.ascontiguousarray(view.T).tobytes())  # GL is column-major
        self.prog["u_light"].value = tuple(float(x) for x in light)
        rgb_aa = None
        if ss > 1:
            # Pixel-edge convention (x = 0 is the left edge): s x s samples per pixel is K scaled by s.
            fbo = self._supersample_fbo(ss)
            # Cleared to the background, so every sample is already composited on it.
            self._draw(vao, fbo, K * np.array([[ss], [ss], [1]], np.float32), self.width * ss, self.height * ss,
                       near, far, clear=(*(float(x) for x in bg), 0.0))
            rgb_aa = self._read_supersampled(fbo, ss)
        # The discrete buffers come from a plain pass: the exact samples of an s = 1 render.
        self._draw(vao, self._fbo, K, self.width, self.height, near, far)
        out = self._read_back(bg)
        if rgb_aa is not None:
            out["rgb"] = rgb_aa
        return out

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
