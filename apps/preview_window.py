"""The preview's live window (glfw): drag or use the arrow keys to move the gaze, shift to orbit the camera."""

from __future__ import annotations

import collections
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apps.gaze_scene import NO_EYES, GazeScene, frame_camera, orbit_camera, visibility_warning
from toolkit.errors import ToolkitError

IDLE_WAIT_S = 0.1
"""Longest sleep of the window loop after a frame that changed nothing; any input event ends it at once."""


@dataclass
class ScrubState:
    """What the person controls: gaze and camera orbit (radians), the overlay, pending actions."""

    pitch: float = 0.0
    yaw: float = 0.0
    orbit_yaw: float = 0.0
    orbit_pitch: float = 0.0
    overlay: bool = False
    screenshot: bool = False
    quit: bool = False
    dragging: str | None = None  # "gaze" or "orbit"
    cursor: tuple[float, float] | None = None
    gaze_limit: float = math.radians(45)

    def move_gaze(self, d_pitch: float, d_yaw: float) -> None:
        self.pitch = max(-self.gaze_limit, min(self.gaze_limit, self.pitch + d_pitch))
        self.yaw = max(-self.gaze_limit, min(self.gaze_limit, self.yaw + d_yaw))

    def move_orbit(self, d_pitch: float, d_yaw: float) -> None:
        self.orbit_pitch = max(-1.2, min(1.2, self.orbit_pitch + d_pitch))
        self.orbit_yaw = max(-math.pi, min(math.pi, self.orbit_yaw + d_yaw))


class WindowControls:
    """glfw callbacks -> ScrubState (kept apart from the loop so tests can feed synthetic events)."""

    STEP = math.radians(2.0)
    DRAG = math.radians(0.25)  # radians per window pixel

    def __init__(self, state: ScrubState):
        self.state = state

    def on_key(self, window, key, scancode, action, mods) -> None:
        import glfw

        if action not in (glfw.PRESS, glfw.REPEAT):
            return
        s, orbit = self.state, bool(mods & glfw.MOD_SHIFT)
        arrows = {glfw.KEY_UP: (1, 0), glfw.KEY_DOWN: (-1, 0), glfw.KEY_LEFT: (0, 1), glfw.KEY_RIGHT: (0, -1)}
        if key in arrows:
            dp, dy = arrows[key]
            # Gaze: right arrow looks towards the image right (yaw decreases, ETH-XGaze convention).
            (s.move_orbit(dp * self.STEP, -dy * self.STEP) if orbit else s.move_gaze(dp * self.STEP, dy * self.STEP))
        elif key == glfw.KEY_R:
            s.pitch = s.yaw = s.orbit_yaw = s.orbit_pitch = 0.0
        elif key == glfw.KEY_O:
            s.overlay = not s.overlay
        elif key == glfw.KEY_S:
            s.screenshot = True
        elif key in (glfw.KEY_Q, glfw.KEY_ESCAPE):
            s.quit = True

    def on_mouse_button(self, window, button, action, mods) -> None:
        import glfw

        s = self.state
        if action == glfw.PRESS:
            orbit = button == glfw.MOUSE_BUTTON_RIGHT or bool(mods & glfw.MOD_SHIFT)
            s.dragging = "orbit" if orbit else "gaze"
            s.cursor = None
        elif action == glfw.RELEASE:
            s.dragging, s.cursor = None, None

    def on_cursor(self, window, x: float, y: float) -> None:
        s = self.state
        if s.dragging and s.cursor is not None:
            dx, dy = x - s.cursor[0], y - s.cursor[1]
            if s.dragging == "gaze":
                s.move_gaze(-dy * self.DRAG, -dx * self.DRAG)  # drag up: look up; drag right: look right
            else:
                s.move_orbit(-dy * self.DRAG, dx * self.DRAG)
        s.cursor = (x, y)


def run_window(scene, width: int = 512, height: int = 512, *, background=(1.0, 1.0, 1.0), max_frames=None,
               events=None, screenshot_dir="out/preview", visible: bool = True) -> dict:
    """Open a glfw window and scrub gaze live until closed (or for ``max_frames`` frames).

    ``events`` (for tests): {frame index: [(callback name, args...), ...]} fed to :class:`WindowControls`
    before that frame, exactly as glfw would call them. Returns the final state and frame statistics
    (``idle_waits``: frames that slept waiting for input because the one before changed nothing).
    """
    import glfw
    import moderngl

    from render.preview import PreviewSplatter

    gs = GazeScene.prepare(scene)
    if not gs.can_scrub:
        print(f"warning: {gs.no_scrub}; orbiting still works", file=sys.stderr)
    glfw.ERROR_REPORTING = "ignore"  # failures become one ToolkitError below, not Python warnings
    if not glfw.init():
        raise ToolkitError(f"could not open a window: glfw found no display ({_glfw_error() or 'is DISPLAY set?'}); "
                           "use --headless --sweep OUT for a headless gaze sweep")
    try:
        win = _open_window(width, height, visible)
        splatter = PreviewSplatter(width, height, ctx=moderngl.create_context(require=330))
        state = ScrubState()
        controls = WindowControls(state)
        glfw.set_key_callback(win, controls.on_key)
        glfw.set_mouse_button_callback(win, controls.on_mouse_button)
        glfw.set_cursor_pos_callback(win, controls.on_cursor)
        try:
            stats = _scrub(win, gs, splatter, controls, frame_camera(scene, width, height),
                           tuple(float(b) for b in background), max_frames, events, screenshot_dir)
        finally:
            splatter.release()
            glfw.destroy_window(win)
        return {"state": state, **stats, "scrubbing": gs.can_scrub}
    finally:
        glfw.terminate()


def _glfw_error() -> str:
    """glfw's last error description, as text."""
    import glfw

    _, why = glfw.get_error()
    return why.decode(errors="replace") if isinstance(why, bytes) else str(why or "")


def _open_window(width: int, height: int, visible: bool):
    """A glfw window with a current OpenGL 3.3 core context, vsync off (glfw initialized)."""
    import glfw

    glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
    glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
    glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
    glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
    glfw.window_hint(glfw.VISIBLE, visible)
    win = glfw.create_window(width, height, "DiT-Gaze preview", None, None)
    if not win:
        raise ToolkitError(f"could not open a window with an OpenGL 3.3 core context ({_glfw_error()}); "
                           "use --headless --sweep OUT instead")
    glfw.make_context_current(win)
    glfw.swap_interval(0)
    return win


def _scrub(win, gs: GazeScene, splatter, controls: WindowControls, base, bg: tuple, max_frames, events,
           screenshot_dir) -> dict:
    """The window's frame loop: draw the scene at the state's gaze and the camera ``base`` orbited as the state
    says, present it, save screenshots and keep the title's numbers current, until the window closes, Q, or
    ``max_frames``. Returns the frame statistics."""
    import glfw

    scene, state = gs.scene, controls.state
    target = scene.means.detach().cpu().double().quantile(0.5, 0)
    # Frame times: the last 30 for the title, running totals for the mean (a window left open for hours keeps no list).
    frames, paths, shots, last_title, eye_rect = 0, {}, [], 0.0, None
    recent, total_s, timed = collections.deque(maxlen=30), 0.0, 0
    idle, idle_waits = False, 0
    while not glfw.window_should_close(win) and not state.quit:
        if max_frames is not None and frames >= max_frames:
            break
        if idle:  # the last frame changed nothing: sleep until an event arrives instead of spinning a core
            glfw.wait_events_timeout(IDLE_WAIT_S)
            idle_waits += 1
        else:
            glfw.poll_events()
        for name, *args in (events or {}).get(frames, []):
            getattr(controls, name)(win, *args)
        t0 = time.perf_counter()
        camera = orbit_camera(base, target, state.orbit_yaw, state.orbit_pitch)
        gs.draw(splatter, camera, state.pitch, state.yaw)
        if frames == 0 and (why := visibility_warning(camera, splatter)):
            print(f"warning: {why}", file=sys.stderr)
        path = splatter.stats.get("path", "full")
        paths[path] = paths.get(path, 0) + 1
        idle = path == "unchanged"
        if path == "incremental":
            eye_rect = splatter.last_rect
        fbw, fbh = glfw.get_framebuffer_size(win)
        splatter.present((0, 0, fbw, fbh), bg, eye_rect if state.overlay else None)
        glfw.swap_buffers(win)
        recent.append(time.perf_counter() - t0)
        total_s, timed = total_s + recent[-1], timed + 1
        if state.screenshot:
            state.screenshot = False
            shots.append(_save_screenshot(splatter, bg, screenshot_dir))
            print(f"saved {shots[-1]}")
        now = time.perf_counter()
        if now - last_title > 0.25:
            glfw.set_window_title(win, _title(gs, state, len(recent) / max(sum(recent), 1e-9)))
            last_title = now
        frames += 1
    return {"frames": frames, "paths": paths, "screenshots": shots, "fps": timed / max(total_s, 1e-9),
            "idle_waits": idle_waits}


def _title(gs: GazeScene, state: ScrubState, fps: float) -> str:
    why = "no eye Gaussians" if gs.no_scrub == NO_EYES else "eyeballs unusable (see the terminal)"
    note = "" if gs.can_scrub else f" | {why}: scrubbing disabled"
    return (f"DiT-Gaze preview | gaze pitch {math.degrees(state.pitch):+.1f}° yaw {math.degrees(state.yaw):+.1f}° | "
            f"{gs.scene.num_gaussians} Gaussians | {fps:.1f} FPS{note}")


def _save_screenshot(splatter, background, folder) -> Path:
    import cv2

    from toolkit.io import atomic_write_bytes

    rgba = splatter.read()
    rgb = rgba[..., :3] + (1 - rgba[..., 3:]) * np.asarray(background, np.float32)
    img = ((np.clip(rgb, 0, 1) * 255) + 0.5).astype(np.uint8)
    folder = Path(folder)
    k = 0
    while (folder / f"preview_{k:04d}.png").exists():
        k += 1
    path = folder / f"preview_{k:04d}.png"
    ok, buf = cv2.imencode(".png", img[..., ::-1])
    if not ok:
        raise ToolkitError(f"{path}: OpenCV could not encode the PNG")
    atomic_write_bytes(path, buf.tobytes())
    return path
