"""The moderngl preview splatter: the fast picture a person looks at, equal to ``render.splat.rasterize``.

Conventions (identical to the torch splatter, see ``render.splat``): OpenCV camera axes, ``viewmat``
world-to-camera [4, 4], ``K`` [3, 3] in pixels, pixel (i, j) sampled at (j + 0.5, i + 0.5); quaternions
wxyz normalized here (zero -> identity); Sigma = R S S^T R^T; EWA Jacobian with gsplat's tangent clamp
(x/z in [-(cx/fx + 0.3 tan_x), (W - cx)/fx + 0.3 tan_x], tan_x = W / (2 fx), same for y); cov2d + 0.3 I;
conic from the dilated covariance; cull z <= near or z >= far; alpha = min(0.99, o exp(-sigma)), skipped
below 1/255; premultiplied back-to-front "over" blending (sorted by camera depth of the means) into an
RGBA32F target; C = sum c_i a_i T_i + T bg, alpha = 1 - T. The only difference is that GL blends every
Gaussian, while the torch splatter stops a pixel once T <= 1e-4 (a difference below 1e-2 at a few pixels).

GL 3.3 core (no SSBOs): per-Gaussian data in a float texture, one instanced quad per visible Gaussian
in sorted order through a per-instance index buffer (``render.preview_shaders``). Each quad is oriented
along the screen-space ellipse's axes and cut where alpha reaches 1/255 for that Gaussian's opacity
(sqrt(2 ln(255 o)) standard deviations, <= 3.33 as in the torch splatter's boxes).

What a frame skips (``PreviewSplatter.stats`` records what happened):
- the depth sort, when the previous order is still exactly sorted for the new view and Gaussians
  (an O(N) check), or when no Gaussian changed and the view moved less than ``resort_tolerance``
  (approximate, for orbiting);
- uploads of Gaussians that did not change (rows of the data texture that hold a changed Gaussian);
- when only ``dynamic`` Gaussians (the eyes) changed under the same camera: everything outside the
  screen rectangle covering their footprints before and after the change. Inside it, a per-camera
  depth-layer cache is composited: the Gaussians behind the dynamic depth range (back layer), the
  Gaussians in that range (sorted each frame), and those in front (front layer). "Over" is associative,
  so this equals a full redraw to float rounding (tests/render/test_preview.py checks it).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from render import preview_shaders as sh
from render.gl_context import shared_context
from render.preview_footprints import (  # noqa: F401 (re-exported: part of the preview API)
    as_float32,
    back_to_front,
    covariances,
    is_back_to_front,
    merge_rects,
    pack_gaussians,
    project_footprints,
    sort_back_to_front,
    tangent_limits,
    union_rect,
)
from render.preview_scene import FeatureColors, eye_dynamics, scene_colors  # noqa: F401
from toolkit.errors import ToolkitError

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_ALPHA = 0.99


# ---------------------------------------------------------------------------------------------- GL side
class _IdList:
    """A per-instance int32 index buffer (grown on demand) and the VAO that draws one quad per entry."""

    def __init__(self, ctx, prog):
        self.ctx, self.prog, self.count = ctx, prog, 0
        self.buffer = ctx.buffer(reserve=4 * 1024, dynamic=True)
        self.vao = ctx.vertex_array(prog, [(self.buffer, "i/i", "a_id")])

    def set(self, ids: np.ndarray) -> None:
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


class PreviewSplatter:
    """Headless (EGL) or windowed OpenGL splatter with the conventions of ``render.splat.rasterize``.

    Args:
        width, height: image size in pixels.
        ctx: an existing moderngl context (e.g. a glfw window's); default: a standalone EGL context.
        near_plane, far_plane, eps2d: as in ``render.splat.rasterize``.
        resort_tolerance: keep the last depth order while the view direction turned less than this many
            radians and the camera centre moved less than this fraction of its distance to the scene
            centre (approximate, for smooth orbiting), and no Gaussian changed. 0 (default) re-sorts whenever
            the order changed.
    """

    def __init__(self, width: int, height: int, *, ctx=None, near_plane: float = 0.01, far_plane: float = 1e10,
                 eps2d: float = 0.3, resort_tolerance: float = 0.0):
        if int(width) < 1 or int(height) < 1:
            raise ToolkitError(f"PreviewSplatter: width and height must be >= 1, got {width}x{height}")
        self.width, self.height = int(width), int(height)
        self.near, self.far, self.eps2d = float(near_plane), float(far_plane), float(eps2d)
        self.resort_tolerance = float(resort_tolerance)
        # Headless splatters share the process's one standalone context with render.mesh_gl: with two
        # standalone EGL contexts in a process, one's GL calls could land in the other's objects.
        self.ctx = ctx if ctx is not None else shared_context()
        c = self.ctx
        self._splat = c.program(vertex_shader=sh.SPLAT_VERTEX, fragment_shader=sh.SPLAT_FRAGMENT)
        self._layer = c.program(vertex_shader=sh.FULLSCREEN_VERTEX, fragment_shader=sh.LAYER_FRAGMENT)
        self._present = c.program(vertex_shader=sh.FULLSCREEN_VERTEX, fragment_shader=sh.PRESENT_FRAGMENT)
        self._layer_vao = c.vertex_array(self._layer, [])
        self._present_vao = c.vertex_array(self._present, [])
        self._target, self._fbo = self._float_target()
        self._lists = {k: _IdList(c, self._splat) for k in ("all", "back", "mid", "front")}
        self._data_tex = None
        self._rows = np.zeros((0, 16), np.float32)  # packed copy of what the texture holds
        self._inputs: tuple | None = None
        self._order: np.ndarray | None = None       # visible ids, back to front, for _order_view
        self._order_view: np.ndarray | None = None
        self._camera: tuple | None = None            # (viewmat, K) of the frame in the target
        self._layers: dict | None = None
        self._frame: np.ndarray | None = None        # premultiplied RGBA [H, W, 4] read back
        self._dirty: tuple[int, int, int, int] | None = None  # drawn since the last read-back
        self.last_rect: tuple[int, int, int, int] | None = None
        self._fp_cache = None
        self.stats: dict[str, Any] = {}

    # ------------------------------------------------------------------ resources
    def _float_target(self):
        tex = self.ctx.texture((self.width, self.height), 4, dtype="f4")
        return tex, self.ctx.framebuffer(color_attachments=[tex])

    def release(self) -> None:
        """Free the GL objects (a shared or caller's context stays)."""
        for lst in self._lists.values():
            lst.release()
        for obj in (self._data_tex, self._fbo, self._target, self._layer_vao, self._present_vao, self._splat,
                    self._layer, self._present):
            if obj is not None:
                obj.release()
        self._data_tex = None
        self._release_layers()

    def _release_layers(self) -> None:
        if self._layers is not None:
            for k in ("back_fbo", "back_tex", "front_fbo", "front_tex"):
                self._layers[k].release()
            self._layers = None

    # ------------------------------------------------------------------ uploads
    def _upload(self, means, quats, scales, opacities, colors, may_change=None) -> tuple[np.ndarray | None, np.ndarray]:
        """Upload what changed -> (changed ids or None for a full reload, old packed rows of those ids).

        ``may_change`` (ids): the caller promises every other row equals what it passed last time, so
        only these rows are compared (a gaze frame compares the eye rows, not the whole scene).
        """
        new = (means, quats, scales, opacities, colors)
        n = means.shape[0]
        if self._inputs is None or self._inputs[0].shape[0] != n:
            self._rows = pack_gaussians(*new)
            self._inputs = tuple(a.copy() for a in new)
            rows_tex = max(1, -(-n // sh.GAUSSIANS_PER_ROW))
            if self._data_tex is not None:
                self._data_tex.release()
            self._data_tex = self.ctx.texture((sh.TEXTURE_WIDTH, rows_tex), 4, dtype="f4")
            self._write_rows(0, rows_tex)
            self.stats["uploaded"] = n
            return None, self._rows[:0]
        cand = None if may_change is None else np.asarray(may_change, np.int64).reshape(-1)
        if cand is not None and cand.size > 1 and not bool(np.all(cand[1:] > cand[:-1])):
            cand = np.unique(cand)  # sorted and unique (the app's eye ids already are)
        if cand is not None and cand.size and (cand[0] < 0 or cand[-1] >= n):
            raise ToolkitError(f"render_preview: may_change holds ids outside [0, {n})")
        diff = np.zeros(n if cand is None else cand.size, bool)
        for old, cur in zip(self._inputs, new, strict=True):
            d = (old != cur) if cand is None else (old[cand] != cur[cand])
            diff |= d.any(1) if d.ndim == 2 else d
        ids = np.flatnonzero(diff) if cand is None else cand[diff]
        old_rows = self._rows[ids].copy()
        if ids.size:
            self._rows[ids] = pack_gaussians(*(a[ids] for a in new))
            for old, cur in zip(self._inputs, new, strict=True):
                old[ids] = cur[ids]
            # Rewrite only the texture rows holding a changed Gaussian, one write per run of rows.
            trows = np.unique(ids // sh.GAUSSIANS_PER_ROW)
            breaks = np.flatnonzero(np.diff(trows) > 1)
            for s, e in zip(np.r_[0, breaks + 1], np.r_[breaks, trows.size - 1], strict=True):
                self._write_rows(int(trows[s]), int(trows[e] - trows[s] + 1))
        self.stats["uploaded"] = int(ids.size)
        return ids, old_rows

    def _write_rows(self, row0: int, nrows: int) -> None:
        g = sh.GAUSSIANS_PER_ROW
        block = np.zeros((nrows * g, 16), np.float32)
        src = self._rows[row0 * g:(row0 + nrows) * g]
        block[:src.shape[0]] = src
        self._data_tex.write(block.tobytes(), viewport=(0, row0, sh.TEXTURE_WIDTH, nrows))

    # ------------------------------------------------------------------ sorting
    def _view_close(self, viewmat: np.ndarray) -> bool:
        if self._order_view is None or self.resort_tolerance <= 0:
            return False
        R0, R1 = self._order_view[:3, :3], viewmat[:3, :3]
        cos = np.clip((np.trace(R0.T @ R1) - 1) / 2, -1, 1)
        c0, c1 = -R0.T @ self._order_view[:3, 3], -R1.T @ viewmat[:3, 3]
        centre = self._rows[:, :3].mean(0)
        dist = max(float(np.linalg.norm(c0 - centre)), 1e-9)
        return math.acos(cos) < self.resort_tolerance and float(np.linalg.norm(c1 - c0)) < self.resort_tolerance * dist

    def _sorted_ids(self, viewmat: np.ndarray, structure_changed: bool, moved: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """-> (visible ids back to front, depth [N], whether a new order was uploaded). ``moved``: some
        Gaussians changed since the last order, so ``resort_tolerance`` (a view's) does not apply."""
        depth = self._depth(viewmat)
        visible = (depth > self.near) & (depth < self.far) & (self._rows[:, 10] > 0)
        if self._order is not None and not structure_changed:
            if not moved and self._view_close(viewmat):  # the tolerance is for the view alone
                return self._order, depth, False
            # The old order is still exact when it is sorted and holds exactly the visible set.
            if is_back_to_front(self._order, depth[self._order]) and self._order.size == int(visible.sum()) \
                    and bool(visible[self._order].all()):
                return self._order, depth, False
        order = sort_back_to_front(np.flatnonzero(visible), depth)
        self._order, self._order_view = order, viewmat.copy()
        self._lists["all"].set(order)
        return order, depth, True

    # ------------------------------------------------------------------ drawing
    def _set_camera_uniforms(self, viewmat: np.ndarray, K: np.ndarray) -> None:
        p = self._splat
        for i in range(3):
            p[f"u_rot{i}"].value = tuple(float(v) for v in viewmat[i, :3])
        p["u_trans"].value = tuple(float(v) for v in viewmat[:3, 3])
        p["u_intr"].value = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        p["u_skew"].value = float(K[0, 1])
        p["u_size"].value = (float(self.width), float(self.height))
        p["u_clip"].value = (self.near, self.far)
        p["u_lim"].value = tuple(float(v) for v in tangent_limits(K, self.width, self.height))
        p["u_eps2d"].value = self.eps2d

    def _splat_into(self, fbo, lst: _IdList, rect=None, clear=True) -> None:
        import moderngl

        fbo.use()
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)  # the shared context may hold a mesh pass's state
        self.ctx.viewport = (0, 0, self.width, self.height)
        self.ctx.scissor = rect
        if clear:
            fbo.clear(0.0, 0.0, 0.0, 0.0, viewport=rect)
        self._data_tex.use(0)
        self._splat["u_data"].value = 0
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        lst.draw()

    def _composite_layer(self, tex, rect, blend: bool) -> None:
        import moderngl

        self._fbo.use()
        self.ctx.scissor = rect
        (self.ctx.enable if blend else self.ctx.disable)(moderngl.BLEND)
        tex.use(1)
        self._layer["u_layer"].value = 1
        self._layer_vao.render(moderngl.TRIANGLES, vertices=3)

    # ------------------------------------------------------------------ depth layers (gaze-only frames)
    def _depth(self, viewmat: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        rows = self._rows if ids is None else self._rows[ids]
        r = viewmat[2]  # elementwise rather than a BLAS matvec (see preview_footprints.affine_rows)
        return rows[:, 0] * r[0] + rows[:, 1] * r[1] + rows[:, 2] * r[2] + r[3]

    def _ensure_layers(self, dynamic: np.ndarray, spheres, viewmat, K, cam, need_full_zone=False):
        """The per-camera depth layers for a dynamic set: valid while the camera, the static Gaussians and
        the dynamic set stay, and every visible dynamic mean stays inside the cached depth range."""
        L = self._layers
        if L is not None and L["camera"] == cam and np.array_equal(L["dynamic"], dynamic) \
                and not (need_full_zone and L["zone"] is not None):
            dz = self._depth(viewmat, L["dyn_ids"])
            vis = (dz > self.near) & (dz < self.far)
            if not vis.any() or (dz[vis].min() >= L["zlo"] and dz[vis].max() <= L["zhi"]):
                return L
        t0 = time.perf_counter()
        depth = self._depth(viewmat)
        visible = (depth > self.near) & (depth < self.far) & (self._rows[:, 10] > 0)
        dz = depth[dynamic & visible]
        lo, hi = (float(dz.min()), float(dz.max())) if dz.size else (0.0, 0.0)
        zone = None
        if spheres:
            # Every gaze keeps each eye Gaussian's mean on its sphere: the range and zone hold for all gazes.
            R, t = viewmat[:3, :3], viewmat[:3, 3]
            cz = [float(R[2] @ c + t[2]) for c, _ in spheres]
            s_lo = min(z - r for z, (_, r) in zip(cz, spheres, strict=True))
            s_hi = max(z + r for z, (_, r) in zip(cz, spheres, strict=True))
            lo, hi = (min(lo, s_lo), max(hi, s_hi)) if dz.size else (s_lo, s_hi)
            if not need_full_zone:
                zone = self._sphere_zone(spheres, dynamic, viewmat, K)
        else:
            pad = 0.25 * (hi - lo) + 1e-6 * max(abs(lo), abs(hi)) + 1e-9
            lo, hi = lo - pad, hi + pad
        static = visible & ~dynamic
        back = sort_back_to_front(np.flatnonzero(static & (depth > hi)), depth)
        front = sort_back_to_front(np.flatnonzero(static & (depth < lo)), depth)
        mid_static = np.flatnonzero(static & (depth >= lo) & (depth <= hi))
        mid_bbox = project_footprints(self._rows[mid_static], viewmat, K, self.width, self.height,
                                      self.near, self.far, self.eps2d)["bbox"]
        if zone is not None:
            x0, y0, w, h = zone
            hit = (mid_bbox[:, 2] >= x0) & (mid_bbox[:, 0] <= x0 + w) & (mid_bbox[:, 3] >= y0) & (mid_bbox[:, 1] <= y0 + h)
            mid_static, mid_bbox = mid_static[hit], mid_bbox[hit]
        if L is None:
            L = {}
            L["back_tex"], L["back_fbo"] = self._float_target()
            L["front_tex"], L["front_fbo"] = self._float_target()
        L.update(camera=cam, dynamic=dynamic.copy(), dyn_ids=np.flatnonzero(dynamic), zlo=lo, zhi=hi, zone=zone,
                 mid_static=mid_static, mid_bbox=mid_bbox, n_back=int(back.size), n_front=int(front.size))
        self._lists["back"].set(back)
        self._lists["front"].set(front)
        self._set_camera_uniforms(viewmat, K)
        self._splat_into(L["back_fbo"], self._lists["back"], rect=zone)  # only ever read inside the zone
        self._splat_into(L["front_fbo"], self._lists["front"], rect=zone)
        self._layers = L
        self.stats["layers_built"] = True
        self.stats["layers_s"] = time.perf_counter() - t0
        return L

    def _sphere_zone(self, spheres, dynamic, viewmat, K):
        """Pixel rectangle that holds every footprint of the dynamic Gaussians for any rotation, or None."""
        rows = self._rows[dynamic]
        cov = rows[:, 4:10]
        # r_cut * sqrt(trace) bounds the alpha ellipse of any 3D covariance along any direction.
        margin3d = float((rows[:, 10] * np.sqrt(np.maximum(cov[:, 0] + cov[:, 3] + cov[:, 5], 0))).max())
        R, t = viewmat[:3, :3].astype(np.float64), viewmat[:3, 3].astype(np.float64)
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        xs, ys = [], []
        for c, r in spheres:
            p = R @ np.asarray(c, np.float64) + t
            rr = r + margin3d
            if p[2] - rr <= self.near:
                return None
            skew = float(K[0, 1])
            for zz in (p[2] - rr, p[2] + rr):  # x/z and y/z over the sphere's box peak at its corners
                for sx in (-rr, rr):
                    for sy in (-rr, rr):
                        xs.append(fx * (p[0] + sx) / zz + skew * (p[1] + sy) / zz + cx)
                        ys.append(fy * (p[1] + sy) / zz + cy)
        pad = 3.33 * math.sqrt(self.eps2d) + 3.0  # the 2D dilation and rounding
        x0, x1 = max(0, int(min(xs) - pad)), min(self.width, int(max(xs) + pad) + 1)
        y0, y1 = max(0, int(min(ys) - pad)), min(self.height, int(max(ys) + pad) + 1)
        return (x0, y0, max(x1 - x0, 1), max(y1 - y0, 1))

    # ------------------------------------------------------------------ frames
    def draw(self, means, quats, scales, opacities, colors, viewmat, K, *, dynamic=None,
             dynamic_spheres=None, may_change=None) -> tuple[int, int, int, int] | None:
        """Draw a frame into the GL target (no read-back) -> the pixel rectangle (x, y, w, h) redrawn.

        ``dynamic`` [N] bool marks the Gaussians that may change between frames of one camera (the eyes);
        ``dynamic_spheres`` [(centre [3], radius)] optionally bounds where their means can ever be (each
        eye's sphere), so the depth-layer cache holds for every gaze. ``may_change`` (ids): only these
        rows can differ from the previous call's inputs (skips comparing the rest). Shapes as in :meth:`render`.
        """
        t0 = time.perf_counter()
        means = as_float32(means, "means", (None, 3))
        n = means.shape[0]
        quats = as_float32(quats, "quats", (n, 4))
        scales = as_float32(scales, "scales", (n, 3))
        opacities = as_float32(opacities, "opacities", (n,))
        colors = as_float32(colors, "colors", (n, 3))
        viewmat = as_float32(viewmat, "viewmat", (4, 4))
        K = as_float32(K, "K", (3, 3))
        # Rows promised unchanged were checked when they came in; only the candidates need a look.
        rows = None if may_change is None or self._inputs is None or self._inputs[0].shape[0] != n \
            else np.asarray(may_change, np.int64).reshape(-1)
        if rows is not None and rows.size and (rows.min() < 0 or rows.max() >= n):
            raise ToolkitError(f"render_preview: may_change holds ids outside [0, {n})")
        for name, a in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                        ("colors", colors), ("viewmat", viewmat), ("K", K)):
            part = a if rows is None or a.shape[0] != n or name in ("viewmat", "K") else a[rows]
            if not np.isfinite(part).all():
                raise ToolkitError(f"render_preview: {name} contains NaN or inf")
        dyn = None
        if dynamic is not None:
            dyn = np.asarray(dynamic.detach().cpu() if hasattr(dynamic, "detach") else dynamic).astype(bool)
            if dyn.shape != (n,):
                raise ToolkitError(f"render_preview: dynamic must be a bool mask of shape [{n}], got {list(dyn.shape)}")
            if not dyn.any():
                dyn = None
        self.stats = st = {"n": n, "sort_s": 0.0, "upload_s": 0.0, "draw_s": 0.0, "read_s": 0.0,
                           "resorted": False, "layers_built": False, "layers_s": 0.0}
        if n == 0:
            self._release_layers()  # their textures too: a preview may sit on an empty scene for long
            self._inputs, self._order = None, None
            self._fbo.clear(0.0, 0.0, 0.0, 0.0)
            self._camera = None
            st["path"] = "empty"
            return self._mark((0, 0, self.width, self.height))
        changed, old_rows = self._upload(means, quats, scales, opacities, colors, may_change)
        t1 = time.perf_counter()
        st["upload_s"] = t1 - t0
        cam = (viewmat.tobytes(), K.tobytes())
        same_cam = self._camera == cam
        if self._layers is not None and (changed is None or (changed.size and (dyn is None or not dyn[changed].all()))):
            self._layers["camera"] = None  # static Gaussians moved: the cached layers are stale
        if changed is None:
            self._order = None
        if same_cam and changed is not None and changed.size == 0:
            st["path"] = "unchanged"
            return None
        if same_cam and changed is not None and dyn is not None and dyn[changed].all():
            st["path"] = "incremental"
            rect = self._draw_incremental(changed, old_rows, dyn, dynamic_spheres, viewmat, K, cam)
        else:
            st["path"] = "full"
            _, _, st["resorted"] = self._sorted_ids(viewmat, structure_changed=changed is None,
                                                    moved=changed is not None and changed.size > 0)
            t2 = time.perf_counter()
            st["sort_s"] = t2 - t1
            self._set_camera_uniforms(viewmat, K)
            self._splat_into(self._fbo, self._lists["all"], rect=None)
            self.ctx.finish()
            st["draw_s"] = time.perf_counter() - t2
            rect = (0, 0, self.width, self.height)
        self._camera = cam
        self.last_rect = rect
        return self._mark(rect)

    def _footprint_rect(self, ids, rows, viewmat, K):
        """Pixel rectangle of the footprints of ``rows`` (of Gaussians ``ids``), reusing the last frame's."""
        c = self._fp_cache
        if c is not None and c[0] == (viewmat.tobytes(), K.tobytes()) and np.array_equal(c[1], ids) \
                and np.array_equal(c[2], rows):
            return c[3]
        fp = project_footprints(rows, viewmat, K, self.width, self.height, self.near, self.far, self.eps2d)
        return union_rect(fp["bbox"][fp["valid"]], self.width, self.height)

    def _draw_incremental(self, changed, old_rows, dyn, spheres, viewmat, K, cam):
        st = self.stats
        t1 = time.perf_counter()
        rect_old = self._footprint_rect(changed, old_rows, viewmat, K)
        new_rows = self._rows[changed]
        rect_new = self._footprint_rect(changed, new_rows, viewmat, K)
        self._fp_cache = (cam, changed, new_rows, rect_new)
        rect = merge_rects(rect_old, rect_new)
        L = self._ensure_layers(dyn, spheres, viewmat, K, cam)
        if rect is not None and L["zone"] is not None:
            x0, y0, w, h = L["zone"]
            if rect[0] < x0 or rect[1] < y0 or rect[0] + rect[2] > x0 + w or rect[1] + rect[3] > y0 + h:
                L = self._ensure_layers(dyn, spheres, viewmat, K, cam, need_full_zone=True)
        t2 = time.perf_counter()
        mids = np.zeros(0, np.int64)
        if rect is not None:
            # Static mid-range Gaussians touching this frame's rectangle, plus every visible dynamic one.
            x, y, w, h = rect
            b = L["mid_bbox"]
            hit = (b[:, 2] >= x) & (b[:, 0] <= x + w) & (b[:, 3] >= y) & (b[:, 1] <= y + h)
            dyn_ids = L["dyn_ids"]
            dz = self._depth(viewmat, dyn_ids)
            dyn_vis = dyn_ids[(dz > self.near) & (dz < self.far) & (self._rows[dyn_ids, 10] > 0)]
            mids = np.sort(np.concatenate([L["mid_static"][hit], dyn_vis]))
            self._lists["mid"].set(back_to_front(mids, self._depth(viewmat, mids)))
        t3 = time.perf_counter()
        st["sort_s"] = (t3 - t2) + (t2 - t1 - st["layers_s"])
        st["n_mid"] = int(mids.size)
        if rect is not None:
            self._set_camera_uniforms(viewmat, K)
            self._composite_layer(L["back_tex"], rect, blend=False)
            self._splat_into(self._fbo, self._lists["mid"], rect=rect, clear=False)
            self._composite_layer(L["front_tex"], rect, blend=True)
            self.ctx.scissor = None
            self.ctx.finish()
        st["draw_s"] = time.perf_counter() - t3 + st["layers_s"]
        return rect

    def _mark(self, rect):
        if rect is not None:
            self._dirty = merge_rects(self._dirty, rect)
        return rect

    def read(self) -> np.ndarray:
        """The premultiplied RGBA frame [H, W, 4] float32, reading back only what changed since the last read.

        The array is the splatter's own buffer, updated in place by later reads: copy it to keep it."""
        t0 = time.perf_counter()
        rect = self._dirty
        if self._frame is None:
            self._frame = np.zeros((self.height, self.width, 4), np.float32)
            rect = (0, 0, self.width, self.height)
        if rect is not None:
            x, y, w, h = rect
            raw = self._fbo.read(viewport=rect, components=4, dtype="f4")
            # GL window row r is image row r (see toolkit.cameras.opengl_projection): no flip.
            self._frame[y:y + h, x:x + w] = np.frombuffer(raw, np.float32).reshape(h, w, 4)
            self._dirty = None
        self.stats["read_s"] = time.perf_counter() - t0
        return self._frame

    def render(self, means, quats, scales, opacities, colors, viewmat, K, background=None, *,
               return_alpha: bool = False, dynamic=None, dynamic_spheres=None, may_change=None):
        """Splat N Gaussians -> image [H, W, 3] float32 (and alpha [H, W, 1] with ``return_alpha``).

        Args: means [N, 3], quats [N, 4] wxyz, scales [N, 3] (activated), opacities [N] in (0, 1),
        colors [N, 3], viewmat [4, 4] world-to-camera, K [3, 3] pixels, background [3] (default black);
        numpy arrays or CPU/CUDA tensors. ``dynamic``, ``dynamic_spheres``, ``may_change``: see :meth:`draw`.
        """
        self.draw(means, quats, scales, opacities, colors, viewmat, K, dynamic=dynamic, dynamic_spheres=dynamic_spheres,
                  may_change=may_change)
        rgba = self.read()
        bg = np.zeros(3, np.float32) if background is None else as_float32(background, "background", (3,))
        rgb = rgba[..., :3] + (1.0 - rgba[..., 3:4]) * bg
        return (rgb, rgba[..., 3:4].copy()) if return_alpha else rgb

    def render_scene(self, scene, camera, background=None, *, feature_map=None, return_alpha: bool = False):
        """Render a ``GaussianScene`` through a ``Camera`` of this splatter's size.

        Features with D != 3 go through ``feature_map`` (default: a :class:`FeatureColors` of this scene).
        The eye Gaussians (part 1, 2) are the dynamic set, bounded by their eyeball spheres.
        """
        if (camera.width, camera.height) != (self.width, self.height):
            raise ToolkitError(f"render_scene: camera is {camera.width}x{camera.height}, the splatter "
                               f"{self.width}x{self.height}")
        colors = scene_colors(scene, feature_map)
        dynamic, spheres = eye_dynamics(scene)
        return self.render(scene.means, scene.quats, scene.scales, scene.opacities, colors, camera.viewmat,
                           camera.K, background, return_alpha=return_alpha, dynamic=dynamic,
                           dynamic_spheres=spheres)

    def present(self, viewport: tuple[int, int, int, int], background=(0.0, 0.0, 0.0), overlay=None) -> None:
        """Show the current frame in the bound window framebuffer (``ctx.screen``), optionally outlining
        the image rectangle ``overlay`` (x, y, w, h)."""
        import moderngl

        self.ctx.screen.use()
        self.ctx.viewport = viewport
        self.ctx.scissor = None
        self.ctx.disable(moderngl.BLEND)
        self._target.use(2)
        p = self._present
        p["u_frame"].value = 2
        p["u_background"].value = tuple(float(b) for b in background)
        p["u_scale"].value = (self.width / viewport[2], self.height / viewport[3])
        p["u_win_height"].value = float(viewport[3])
        x, y, w, h = overlay if overlay is not None else (1, 1, -2, -2)
        p["u_rect"].value = (float(x), float(y), float(x + w - 1), float(y + h - 1))
        self._present_vao.render(moderngl.TRIANGLES, vertices=3)


# ---------------------------------------------------------------------------------------------- scenes


def render_preview(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int,
                   background=None) -> np.ndarray:
    """One-shot headless preview render -> [H, W, 3] float32 (shapes as :meth:`PreviewSplatter.render`)."""
    s = PreviewSplatter(width, height, ctx=shared_context())
    try:
        return s.render(means, quats, scales, opacities, colors, viewmat, K, background).copy()
    finally:
        s.release()


def render_scene(scene, camera, background=None, *, feature_map=None) -> np.ndarray:
    """One-shot headless render of a ``GaussianScene`` through a ``Camera`` -> [H, W, 3] float32."""
    s = PreviewSplatter(camera.width, camera.height, ctx=shared_context())
    try:
        return s.render_scene(scene, camera, background, feature_map=feature_map).copy()
    finally:
        s.release()
