"""The moderngl preview splatter: the fast picture a person looks at, equal to ``render.splat.rasterize``.

Conventions are the torch splatter's (``render.splat``; docs/preview.md lists them): the same projection,
tangent clamp, dilation, alpha cut and ``render.cull`` rule, composited back to front (premultiplied "over")
into an RGBA32F target. The only difference: GL blends every Gaussian, while the torch splatter stops a pixel
once T <= 1e-4 (below 1e-2 at a few pixels). GL 3.3 core: per-Gaussian data in a float texture, one
instanced quad per visible Gaussian in sorted order, cut where alpha reaches 1/255 (``render.preview_shaders``).

What a frame skips (``PreviewSplatter.stats`` records what happened):
- the depth sort, when the previous order is still exactly sorted for the new view and Gaussians
  (an O(N) check), or when no Gaussian changed and the view moved less than ``resort_tolerance``
  (approximate, for orbiting);
- uploads of Gaussians that did not change (rows of the data texture that hold a changed Gaussian);
- when only ``dynamic`` Gaussians (the eyes) changed under the same camera: everything outside the
  screen rectangle covering their footprints before and after the change. Inside it, a per-camera
  depth-layer cache is composited: the Gaussians behind the dynamic depth range (back layer), the
  Gaussians in that range (sorted each frame), and those in front (front layer). "Over" is associative,
  so this equals a full redraw to float rounding (tests/render/test_preview_frames.py checks it).

This module decides what a frame draws; ``render.preview_gl`` holds the GPU buffers and draw calls,
``render.preview_layers`` plans the depth layers, ``render.preview_footprints`` checks inputs and mirrors the
vertex shader on the CPU, ``render.preview_scene`` turns a scene into colours and its eyes into the dynamic set.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from render.cull import cull_counts, finite_scales
from render.gl_context import shared_context
from render.preview_footprints import (
    as_float32,
    back_to_front,
    check_frame_inputs,
    drawable,
    dynamic_mask,
    float32_tensor,
    is_back_to_front,
    merge_rects,
    project_footprints,
    sort_back_to_front,
    union_rect,
)
from render.preview_gl import GaussianTexture, IdList, SplatPrograms
from render.preview_layers import boxes_touching, dynamic_depth_range, rect_within, sphere_zone, split_layers
from render.preview_scene import eye_dynamics, scene_colors
from toolkit.errors import ToolkitError


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
        if not (0 <= self.near < self.far and 0 <= self.eps2d < math.inf):  # NaN fails too
            raise ToolkitError(f"PreviewSplatter: need 0 <= near_plane < far_plane and a finite eps2d >= 0, got "
                               f"{near_plane}, {far_plane}, {eps2d}")
        self.resort_tolerance = float(resort_tolerance)
        # Headless splatters share the process's one standalone context with render.mesh_gl: with two
        # standalone EGL contexts in a process, one's GL calls could land in the other's objects.
        self.ctx = ctx if ctx is not None else shared_context()
        self._gl = SplatPrograms(self.ctx, self.width, self.height)
        self._target, self._fbo = self._gl.float_target()
        self._lists = {k: IdList(self.ctx, self._gl.splat) for k in ("all", "back", "mid", "front")}
        self._gaussians = GaussianTexture(self.ctx)
        self._order: np.ndarray | None = None       # visible ids, back to front, for _order_view
        self._order_view: np.ndarray | None = None
        self._camera: tuple | None = None            # (viewmat, K) of the frame in the target
        self._layers: dict | None = None
        self._frame: np.ndarray | None = None        # premultiplied RGBA [H, W, 4] read back
        self._dirty: tuple[int, int, int, int] | None = None  # drawn since the last read-back
        self.last_rect: tuple[int, int, int, int] | None = None
        self._fp_cache = None
        self._keep: np.ndarray | None = None         # the cull rule's keep [N] for _keep_camera
        self._keep_camera: tuple | None = None
        self.stats: dict[str, Any] = {}

    @property
    def drawn(self) -> np.ndarray:
        """Ids [M] the last full frame drew, back to front: those ``render.cull`` keeps for its camera whose
        opacity reaches 1/255 (off-image ones included: GL clips them)."""
        return np.zeros(0, np.int64) if self._order is None else self._order.copy()

    @property
    def _rows(self) -> np.ndarray:
        """[N, 16] packed rows of the Gaussians the data texture holds."""
        return self._gaussians.rows

    # ------------------------------------------------------------------ resources
    def release(self) -> None:
        """Free the GL objects (a shared or caller's context stays)."""
        for lst in self._lists.values():
            lst.release()
        self._gaussians.release()
        for obj in (self._fbo, self._target):
            obj.release()
        self._gl.release()
        self._release_layers()

    def _release_layers(self) -> None:
        if self._layers is not None:
            for k in ("back_fbo", "back_tex", "front_fbo", "front_tex"):
                self._layers[k].release()
            self._layers = None

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
        visible = self._keep & (self._rows[:, 10] > 0)
        if self._order is not None and not structure_changed:
            # An old order is reused only while it holds exactly the visible set: the shader does not cull
            # what the rule drops (near / far, overflowing footprints), so a stale member would be drawn.
            if self._order.size == int(visible.sum()) and bool(visible[self._order].all()):
                if not moved and self._view_close(viewmat):  # the tolerance is for the view alone
                    return self._order, depth, False
                if is_back_to_front(self._order, depth[self._order]):  # still exact
                    return self._order, depth, False
        order = sort_back_to_front(np.flatnonzero(visible), depth)
        self._order, self._order_view = order, viewmat.copy()
        self._lists["all"].set(order)
        return order, depth, True

    # ------------------------------------------------------------------ drawing
    def _set_camera(self, viewmat: np.ndarray, K: np.ndarray) -> None:
        # The id lists hold only what the cull rule keeps, near / far included; the shader's own clip only
        # guards its division by z (its z, rounded another way, must not drop a Gaussian the rule kept).
        self._gl.set_camera(viewmat, K, 0.0, 3.0e38, self.eps2d)

    def _update_keep(self, viewmat: np.ndarray, K: np.ndarray, cam: tuple, changed: np.ndarray | None) -> np.ndarray:
        """The cull rule (``render.cull``) for this camera -> keep [N] bool; under the same camera only the
        ``changed`` rows are decided again."""
        means, quats, scales = self._gaussians.inputs[:3]
        ok = self._gaussians.ok
        args = (K, self.width, self.height, self.near, self.far, self.eps2d)
        if self._keep_camera == cam and changed is not None and self._keep is not None:
            if changed.size:
                self._keep[changed] = drawable(means[changed], quats[changed], scales[changed], viewmat, *args,
                                               ok=ok[changed])
        else:
            self._keep = drawable(means, quats, scales, viewmat, *args, ok=ok)
            self._keep_camera = cam
        return self._keep

    def _splat_into(self, fbo, lst: IdList, rect=None, clear=True) -> None:
        self._gl.splat_into(fbo, lst, self._gaussians.texture, rect=rect, clear=clear)

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
            vis = self._keep[L["dyn_ids"]]
            if not vis.any() or (dz[vis].min() >= L["zlo"] and dz[vis].max() <= L["zhi"]):
                return L
        t0 = time.perf_counter()
        depth = self._depth(viewmat)
        visible = self._keep & (self._rows[:, 10] > 0)
        lo, hi = dynamic_depth_range(depth[dynamic & visible], spheres, viewmat)
        zone = None
        if spheres and not need_full_zone:  # every gaze keeps the eyes' footprints in this zone
            zone = sphere_zone(self._rows[dynamic], spheres, viewmat, K, self.width, self.height, self.near,
                               self.eps2d)
        back, front, mid_static = split_layers(depth, visible, dynamic, lo, hi)
        mid_bbox = project_footprints(self._rows[mid_static], viewmat, K, self.width, self.height,
                                      self.near, self.far, self.eps2d)["bbox"]
        if zone is not None:
            hit = boxes_touching(mid_bbox, zone)
            mid_static, mid_bbox = mid_static[hit], mid_bbox[hit]
        if L is None:
            L = {}
            L["back_tex"], L["back_fbo"] = self._gl.float_target()
            L["front_tex"], L["front_fbo"] = self._gl.float_target()
        L.update(camera=cam, dynamic=dynamic.copy(), dyn_ids=np.flatnonzero(dynamic), zlo=lo, zhi=hi, zone=zone,
                 mid_static=mid_static, mid_bbox=mid_bbox, n_back=int(back.size), n_front=int(front.size))
        self._lists["back"].set(back)
        self._lists["front"].set(front)
        self._set_camera(viewmat, K)
        self._splat_into(L["back_fbo"], self._lists["back"], rect=zone)  # only ever read inside the zone
        self._splat_into(L["front_fbo"], self._lists["front"], rect=zone)
        self._layers = L
        self.stats["layers_built"] = True
        self.stats["layers_s"] = time.perf_counter() - t0
        return L

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
        means, quats, scales, opacities, colors, viewmat, K = check_frame_inputs(
            means, quats, scales, opacities, colors, viewmat, K, may_change, held=self._gaussians.count)
        n = means.shape[0]
        dyn = dynamic_mask(dynamic, n)
        self.stats = st = {"n": n, "sort_s": 0.0, "upload_s": 0.0, "draw_s": 0.0, "read_s": 0.0,
                           "resorted": False, "layers_built": False, "layers_s": 0.0}
        if n == 0:
            self._release_layers()  # their textures too: a preview may sit on an empty scene for long
            self._gaussians.forget()
            self._order = None
            self._keep = self._keep_camera = None
            self._fbo.clear(0.0, 0.0, 0.0, 0.0)
            self._camera = None
            st["path"] = "empty"
            return self._mark((0, 0, self.width, self.height))
        changed, old_rows = self._gaussians.upload(means, quats, scales, opacities, colors, may_change)
        st["uploaded"] = n if changed is None else int(changed.size)
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
        keep_old = self._keep[changed].copy() if changed is not None and self._keep is not None else None
        keep = self._update_keep(viewmat, K, cam, changed)
        st["culled"] = int(n - np.count_nonzero(keep))  # by the cull rule (render.cull), on or off the image
        if same_cam and changed is not None and dyn is not None and dyn[changed].all():
            st["path"] = "incremental"
            rect = self._draw_incremental(changed, old_rows, keep_old, dyn, dynamic_spheres, viewmat, K, cam)
        else:
            st["path"] = "full"
            order, _, st["resorted"] = self._sorted_ids(viewmat, structure_changed=changed is None,
                                                        moved=changed is not None and changed.size > 0)
            st["drawn"] = int(order.size)  # kept by the cull rule and opacity above 1/255
            t2 = time.perf_counter()
            st["sort_s"] = t2 - t1
            self._set_camera(viewmat, K)
            self._splat_into(self._fbo, self._lists["all"], rect=None)
            self.ctx.finish()
            st["draw_s"] = time.perf_counter() - t2
            rect = (0, 0, self.width, self.height)
        self._camera = cam
        self.last_rect = rect
        return self._mark(rect)

    def culled_by_test(self, viewmat, K) -> dict[str, int]:
        """How many of the Gaussians last drawn the cull rule drops for this camera (viewmat [4, 4], K [3, 3]),
        by the first test each fails (``render.cull.REASONS``); {} when it drops none."""
        if self._gaussians.inputs is None:
            return {}
        viewmat, K = as_float32(viewmat, "viewmat", (4, 4)), as_float32(K, "K", (3, 3))
        t = float32_tensor
        return cull_counts(*(t(a) for a in self._gaussians.inputs[:3]), t(viewmat)[None], t(K)[None], self.width,
                           self.height, near_plane=self.near, far_plane=self.far, eps2d=self.eps2d)

    def _footprint_rect(self, ids, rows, keep, viewmat, K):
        """Pixel rectangle of the footprints of ``rows`` (of Gaussians ``ids``, ``keep`` [M] what the cull rule
        draws of them), reusing the last frame's."""
        c = self._fp_cache
        if c is not None and c[0] == (viewmat.tobytes(), K.tobytes()) and np.array_equal(c[1], ids) \
                and np.array_equal(c[2], rows):
            return c[3]
        fp = project_footprints(rows[keep], viewmat, K, self.width, self.height, self.near, self.far, self.eps2d)
        return union_rect(fp["bbox"][fp["valid"]], self.width, self.height)

    def _draw_incremental(self, changed, old_rows, keep_old, dyn, spheres, viewmat, K, cam):
        st = self.stats
        t1 = time.perf_counter()
        rect_old = self._footprint_rect(changed, old_rows, keep_old, viewmat, K)
        new_rows = self._rows[changed]
        rect_new = self._footprint_rect(changed, new_rows, self._keep[changed], viewmat, K)
        self._fp_cache = (cam, changed, new_rows, rect_new)
        rect = merge_rects(rect_old, rect_new)
        L = self._ensure_layers(dyn, spheres, viewmat, K, cam)
        if rect is not None and L["zone"] is not None and not rect_within(rect, L["zone"]):
            L = self._ensure_layers(dyn, spheres, viewmat, K, cam, need_full_zone=True)
        t2 = time.perf_counter()
        mids = np.zeros(0, np.int64)
        if rect is not None:
            # Static mid-range Gaussians touching this frame's rectangle, plus every visible dynamic one.
            hit = boxes_touching(L["mid_bbox"], rect)
            dyn_ids = L["dyn_ids"]
            dyn_vis = dyn_ids[self._keep[dyn_ids] & (self._rows[dyn_ids, 10] > 0)]
            mids = np.sort(np.concatenate([L["mid_static"][hit], dyn_vis]))
            self._lists["mid"].set(back_to_front(mids, self._depth(viewmat, mids)))
        t3 = time.perf_counter()
        st["sort_s"] = (t3 - t2) + (t2 - t1 - st["layers_s"])
        st["n_mid"] = int(mids.size)
        if rect is not None:
            self._set_camera(viewmat, K)
            self._gl.composite(self._fbo, L["back_tex"], rect, blend=False)
            self._splat_into(self._fbo, self._lists["mid"], rect=rect, clear=False)
            self._gl.composite(self._fbo, L["front_tex"], rect, blend=True)
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
        if not np.isfinite(bg).all():  # it is blended into every pixel
            raise ToolkitError(f"render_preview: background must be finite, got {bg.tolist()}")
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
        # finite_scales: a log-scale that overflows float32 is culled as huge (render.cull), not refused as inf.
        return self.render(scene.means, scene.quats, finite_scales(scene.scales.float()), scene.opacities, colors,
                           camera.viewmat, camera.K, background, return_alpha=return_alpha, dynamic=dynamic,
                           dynamic_spheres=spheres)

    def present(self, viewport: tuple[int, int, int, int], background=(0.0, 0.0, 0.0), overlay=None) -> None:
        """Show the current frame in the bound window framebuffer (``ctx.screen``), optionally outlining
        the image rectangle ``overlay`` (x, y, w, h)."""
        self._gl.present(self._target, viewport, background, overlay)


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
