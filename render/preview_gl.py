"""GPU side of the preview splatter (``render.preview``): the Gaussians' data texture, uploaded row by
changed row, the per-instance index lists that draw them in depth order, and the GL programs with their
draw calls. What to draw, and when, is the splatter's business.

Layouts as in ``render.preview_shaders``; packing as in ``render.preview_footprints.pack_gaussians``.
"""

from __future__ import annotations

import numpy as np

from render import preview_shaders as sh
from render.preview_footprints import camera_free_ok, pack_gaussians, tangent_limits
from toolkit.errors import ToolkitError


def max_texture_size(ctx) -> int:
    """The context's largest texture side (and viewport), in texels."""
    info = ctx.info
    return int(min(info["GL_MAX_TEXTURE_SIZE"], *info["GL_MAX_VIEWPORT_DIMS"]))


class IdList:
    """A per-instance int32 index buffer (grown on demand) and the VAO that draws one quad per entry."""

    def __init__(self, ctx, prog):
        self.ctx, self.prog, self.count = ctx, prog, 0
        self.buffer = ctx.buffer(reserve=4 * 1024, dynamic=True)
        self.vao = ctx.vertex_array(prog, [(self.buffer, "i/i", "a_id")])

    def set(self, ids: np.ndarray) -> None:
        """Draw these Gaussian ids [M] from now on, in this order."""
        data = np.ascontiguousarray(ids, dtype=np.int32)
        if data.nbytes > self.buffer.size:
            self.vao.release()
            self.buffer.release()
            self.buffer = self.ctx.buffer(reserve=max(2 * data.nbytes, 4096), dynamic=True)
            self.vao = self.ctx.vertex_array(self.prog, [(self.buffer, "i/i", "a_id")])
        if data.nbytes:
            self.buffer.write(data.tobytes())
        self.count = int(data.shape[0])

    def draw(self) -> None:
        import moderngl

        if self.count:
            self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=self.count)

    def release(self) -> None:
        self.vao.release()
        self.buffer.release()


class GaussianTexture:
    """The Gaussians in the float data texture, with a CPU copy of its packed rows and of the inputs.

    ``rows`` [N, 16] float32 is what the texture holds (``pack_gaussians`` layout: mean 0:3, opacity 3,
    covariance 4:10, r_cut 10, colour 12:15); the kept inputs let :meth:`upload` find what changed.
    """

    def __init__(self, ctx):
        self.ctx = ctx
        self.texture = None
        self.rows = np.zeros((0, 16), np.float32)
        self.ok = np.zeros(0, bool)  # [N] the camera-free tests of the cull rule (render.cull.param_tests)
        self.inputs: tuple | None = None

    @property
    def count(self) -> int | None:
        """How many Gaussians the texture holds (None: nothing to compare an upload with)."""
        return None if self.inputs is None else int(self.inputs[0].shape[0])

    def holds(self, n: int) -> bool:
        """Whether the texture holds a set of ``n`` Gaussians (so an upload of n compares, not reloads)."""
        return self.count == n

    def forget(self) -> None:
        """Compare nothing on the next upload: it reloads every row."""
        self.inputs = None

    def upload(self, means, quats, scales, opacities, colors, may_change=None) -> tuple[np.ndarray | None, np.ndarray]:
        """Upload what changed -> (changed ids or None for a full reload, old packed rows of those ids).

        ``may_change`` (ids): the caller promises every other row equals what it passed last time, so
        only these rows are compared (a gaze frame compares the eye rows, not the whole scene).
        """
        new = (means, quats, scales, opacities, colors)
        n = means.shape[0]
        if not self.holds(n):
            self._reload(new)
            return None, self.rows[:0]
        cand = None if may_change is None else np.asarray(may_change, np.int64).reshape(-1)
        if cand is not None and cand.size > 1 and not bool(np.all(cand[1:] > cand[:-1])):
            cand = np.unique(cand)  # sorted and unique (the app's eye ids already are)
        if cand is not None and cand.size and (cand[0] < 0 or cand[-1] >= n):
            raise ToolkitError(f"render_preview: may_change holds ids outside [0, {n})")
        diff = np.zeros(n if cand is None else cand.size, bool)
        for old, cur in zip(self.inputs, new, strict=True):
            d = (old != cur) if cand is None else (old[cand] != cur[cand])
            diff |= d.any(1) if d.ndim == 2 else d
        ids = np.flatnonzero(diff) if cand is None else cand[diff]
        old_rows = self.rows[ids].copy()
        if ids.size:
            self.ok[ids] = camera_free_ok(*(a[ids] for a in new[:3]))
            self.rows[ids] = pack_gaussians(*(a[ids] for a in new), ok=self.ok[ids])
            for old, cur in zip(self.inputs, new, strict=True):
                old[ids] = cur[ids]
            # Rewrite only the texture rows holding a changed Gaussian, one write per run of rows.
            trows = np.unique(ids // sh.GAUSSIANS_PER_ROW)
            breaks = np.flatnonzero(np.diff(trows) > 1)
            for s, e in zip(np.r_[0, breaks + 1], np.r_[breaks, trows.size - 1], strict=True):
                self._write_rows(int(trows[s]), int(trows[e] - trows[s] + 1))
        return ids, old_rows

    def _reload(self, new: tuple) -> None:
        """A new texture sized for these Gaussians, every row written."""
        n = new[0].shape[0]
        rows_tex = max(1, -(-n // sh.GAUSSIANS_PER_ROW))
        limit = max_texture_size(self.ctx)
        if rows_tex > limit:  # a GL error (and a traceback) otherwise
            raise ToolkitError(f"render_preview: {n} Gaussians need a data texture of {rows_tex} rows, more than "
                               f"this OpenGL's limit of {limit} ({limit * sh.GAUSSIANS_PER_ROW} Gaussians)")
        self.ok = camera_free_ok(*new[:3])
        self.rows = pack_gaussians(*new, ok=self.ok)
        self.inputs = tuple(a.copy() for a in new)
        if self.texture is not None:
            self.texture.release()
        self.texture = self.ctx.texture((sh.TEXTURE_WIDTH, rows_tex), 4, dtype="f4")
        self._write_rows(0, rows_tex)

    def _write_rows(self, row0: int, nrows: int) -> None:
        g = sh.GAUSSIANS_PER_ROW
        block = np.zeros((nrows * g, 16), np.float32)
        src = self.rows[row0 * g:(row0 + nrows) * g]
        block[:src.shape[0]] = src
        self.texture.write(block.tobytes(), viewport=(0, row0, sh.TEXTURE_WIDTH, nrows))

    def release(self) -> None:
        if self.texture is not None:
            self.texture.release()
        self.texture = None


class SplatPrograms:
    """The preview's three GL programs (splat, layer copy, present) and the draw calls that use them, for
    ``width`` x ``height`` float targets."""

    def __init__(self, ctx, width: int, height: int):
        limit = max_texture_size(ctx)
        if width > limit or height > limit:
            raise ToolkitError(f"PreviewSplatter: {width}x{height} pixels exceed this OpenGL's limit of {limit} "
                               "pixels per side")
        self.ctx, self.width, self.height = ctx, width, height
        self.splat = ctx.program(vertex_shader=sh.SPLAT_VERTEX, fragment_shader=sh.SPLAT_FRAGMENT)
        self._layer = ctx.program(vertex_shader=sh.FULLSCREEN_VERTEX, fragment_shader=sh.LAYER_FRAGMENT)
        self._present = ctx.program(vertex_shader=sh.FULLSCREEN_VERTEX, fragment_shader=sh.PRESENT_FRAGMENT)
        self._layer_vao = ctx.vertex_array(self._layer, [])
        self._present_vao = ctx.vertex_array(self._present, [])

    def float_target(self):
        """(RGBA32F texture, framebuffer drawing into it) of the image size."""
        tex = self.ctx.texture((self.width, self.height), 4, dtype="f4")
        return tex, self.ctx.framebuffer(color_attachments=[tex])

    def set_camera(self, viewmat: np.ndarray, K: np.ndarray, near: float, far: float, eps2d: float) -> None:
        """The splat program's camera: viewmat [4, 4] world-to-camera, K [3, 3] pixels, clip range, dilation."""
        p = self.splat
        for i in range(3):
            p[f"u_rot{i}"].value = tuple(float(v) for v in viewmat[i, :3])
        p["u_trans"].value = tuple(float(v) for v in viewmat[:3, 3])
        p["u_intr"].value = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        p["u_skew"].value = float(K[0, 1])
        p["u_size"].value = (float(self.width), float(self.height))
        p["u_clip"].value = (near, far)
        p["u_lim"].value = tuple(float(v) for v in tangent_limits(K, self.width, self.height))
        p["u_eps2d"].value = eps2d

    def splat_into(self, fbo, lst: IdList, data_texture, rect=None, clear=True) -> None:
        """Blend the Gaussians of ``lst`` (back to front) into ``fbo``, inside ``rect`` (x, y, w, h) if given."""
        import moderngl

        fbo.use()
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)  # the shared context may hold a mesh pass's state
        self.ctx.viewport = (0, 0, self.width, self.height)
        self.ctx.scissor = rect
        if clear:
            fbo.clear(0.0, 0.0, 0.0, 0.0, viewport=rect)
        data_texture.use(0)
        self.splat["u_data"].value = 0
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        lst.draw()

    def composite(self, fbo, tex, rect, blend: bool) -> None:
        """Copy (``blend`` False) or blend "over" (True) the layer texture into ``fbo`` inside ``rect``."""
        import moderngl

        fbo.use()
        self.ctx.scissor = rect
        (self.ctx.enable if blend else self.ctx.disable)(moderngl.BLEND)
        tex.use(1)
        self._layer["u_layer"].value = 1
        self._layer_vao.render(moderngl.TRIANGLES, vertices=3)

    def present(self, frame, viewport: tuple[int, int, int, int], background, overlay) -> None:
        """Show the premultiplied ``frame`` texture in the bound window framebuffer (see PreviewSplatter.present)."""
        import moderngl

        self.ctx.screen.use()
        self.ctx.viewport = viewport
        self.ctx.scissor = None
        self.ctx.disable(moderngl.BLEND)
        frame.use(2)
        p = self._present
        p["u_frame"].value = 2
        p["u_background"].value = tuple(float(b) for b in background)
        p["u_scale"].value = (self.width / viewport[2], self.height / viewport[3])
        p["u_win_height"].value = float(viewport[3])
        x, y, w, h = overlay if overlay is not None else (1, 1, -2, -2)
        p["u_rect"].value = (float(x), float(y), float(x + w - 1), float(y + h - 1))
        self._present_vao.render(moderngl.TRIANGLES, vertices=3)

    def release(self) -> None:
        for obj in (self._layer_vao, self._present_vao, self.splat, self._layer, self._present):
            obj.release()
