"""Live gaze scrubbing of a Gaussian head: a glfw window, or a headless gaze sweep through EGL.

    python apps/preview.py SCENE                                  # window: drag to move the gaze
    python apps/preview.py SCENE --headless --sweep out/sweep.mp4  # or .png for a contact sheet
    python apps/preview.py demo:20000 --headless --sweep out/sweep.png --pitch -20:20:3 --yaw -30:30:5

Without a trained model, the eye Gaussians (part 1 and 2) rotate rigidly about each eyeball's centre
(from ``scene.metadata["eyes"]``, else a sphere fitted per eye): exact for the procedural demo head.
The picture comes from ``render.preview.PreviewSplatter`` and equals ``render.splat.rasterize``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

if __package__ in (None, ""):  # run as a script (python apps/preview.py): make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from toolkit.errors import ToolkitError, run_cli

WINDOW_HELP = """window controls:
  left drag / arrow keys        change gaze pitch and yaw
  shift + left drag / arrows    orbit the camera (right drag works too)
  R  reset gaze and camera      O  toggle the eye-region overlay
  S  save a screenshot (PNG)    Q / Esc  quit
"""


# ---------------------------------------------------------------------------------------------- scenes
def load_trained_scene(run_dir: str):
    """A trained run directory (train/run.py) -> the model's Gaussians as an RGB scene.

    The two-stream model is posed with a training subject's code, the identity head pose and a frontal
    gaze; its feature channels 0..2 (supervised as the low-resolution RGB image) become the colours.
    The eyes are then scrubbed rigidly about their fitted eyeball centres, like any scene.
    """
    from train.data.dataset import GazeDataset
    from train.run import _split, load_trained, open_run

    ctx = open_run(run_dir)
    model, _ = load_trained(ctx, "cpu")
    item = GazeDataset(_split(ctx, "train"), res=ctx.config.data.res)[0]
    code = torch.as_tensor(item["latent_code"]).float()[None]
    scene = model.export_scene(code, torch.zeros(1, 6), torch.zeros(1, 2))
    scene.features = scene.features[:, :3].clamp(0, 1)
    scene.metadata["feature_kind"] = "rgb"
    return scene.validate()


def load_scene(spec: str):
    """A ``.safetensors`` / ``.ply`` scene path, a trained run directory, or ``demo[:N]`` (the procedural head)."""
    from toolkit.io import check_readable_file
    from toolkit.procedural import demo_head_scene
    from toolkit.scene import GaussianScene

    if spec == "demo" or spec.startswith("demo:"):
        try:
            n = int(spec.split(":", 1)[1]) if ":" in spec else 20000
        except ValueError:
            raise ToolkitError(f"scene {spec!r}: expected demo or demo:N with an integer N") from None
        return demo_head_scene(n)
    if os.path.isdir(spec) and os.path.isfile(os.path.join(spec, "config.yaml")):
        return load_trained_scene(spec)
    ext = os.path.splitext(spec)[1].lower()
    if ext not in (".ply", ".safetensors"):
        raise ToolkitError(f"{spec}: expected a .safetensors or .ply Gaussian scene, a trained run directory "
                           "(with config.yaml), or demo[:N]")
    check_readable_file(spec, "scene file")
    return GaussianScene.read(spec)


def frame_camera(scene, width: int, height: int, fov_y_deg: float = 25.0, fill: float = 0.95):
    """A frontal camera (the face looks towards -z) whose view the scene's bulk fills."""
    from toolkit.cameras import Camera, intrinsics_from_fov, look_at

    m = scene.means.detach().cpu().double()
    if m.shape[0] == 0:
        raise ToolkitError("scene has no Gaussians: nothing to preview")
    lo, hi = torch.quantile(m, 0.005, 0), torch.quantile(m, 0.995, 0)
    centre, half = (lo + hi) / 2, ((hi - lo) / 2).clamp_min(1e-6)
    K = intrinsics_from_fov(fov_y_deg, width, height)
    tan_y = math.tan(math.radians(fov_y_deg) / 2)
    tan_x = tan_y * width / height
    dist = float(max(half[0] / tan_x, half[1] / tan_y) / fill + half[2])
    eye = centre + torch.tensor([0.0, 0.0, -dist], dtype=torch.float64)
    return Camera(K, look_at(eye.float(), centre.float()), width, height)


def orbit_camera(base, target, yaw: float, pitch: float):
    """``base`` camera moved on a sphere about ``target`` [3] by ``yaw`` (about the vertical) and ``pitch``
    (positive = from above) radians, still looking at ``target`` with the head's up (-y) up."""
    from toolkit.cameras import Camera, look_at

    target = torch.as_tensor(target, dtype=torch.float64)
    d = base.center.double() - target
    pitch = max(-1.4, min(1.4, pitch))  # stay clear of the poles, where look_at has no up direction
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    Ry = torch.tensor([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]], dtype=torch.float64)
    Rx = torch.tensor([[1, 0, 0], [0, cp, sp], [0, -sp, cp]], dtype=torch.float64)
    eye = target + Ry @ Rx @ d
    return Camera(base.K, look_at(eye.float(), target.float()), base.width, base.height)


@dataclass
class GazeScene:
    """A scene prepared for live gaze changes: activated numpy arrays, display colours, the eye set and
    each eye's rotation sphere. A gaze frame rotates only the eye rows (rigidly about each eyeball's
    centre, as ``toolkit.eyes.redirect_eyes`` does) and hands the splatter arrays that differ there only."""

    scene: object
    colors: np.ndarray
    dynamic: np.ndarray | None
    spheres: list | None
    eye_info: dict = field(default_factory=dict)
    arrays: tuple = ()
    eye_index: dict = field(default_factory=dict)

    @classmethod
    def prepare(cls, scene) -> "GazeScene":
        from render.preview import FeatureColors, eye_dynamics
        from toolkit.eyes import EYE_PARTS, eyeball_info

        scene.validate()
        colors = FeatureColors(scene.features)(scene.features)
        try:
            info = eyeball_info(scene)
        except ToolkitError:
            info = {}
        dynamic, spheres = eye_dynamics(scene) if info else (None, None)
        arrays = tuple(t.detach().cpu().float().numpy().copy() for t in
                       (scene.means, scene.quats, scene.scales, scene.opacities))
        part = scene.part.cpu().numpy()
        index = {name: np.flatnonzero(part == EYE_PARTS[name]) for name in info}
        return cls(scene, colors, dynamic, spheres, info, arrays, index)

    @property
    def can_scrub(self) -> bool:
        return bool(self.eye_info)

    def arrays_at(self, pitch: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """(means [N, 3], quats [N, 4]) with both eyes turned to head-frame gaze (pitch, yaw) radians."""
        from render.preview_footprints import affine_rows
        from toolkit.eyes import gaze_rotation
        from toolkit.rotations import matrix_to_quat

        means, quats = self.arrays[0], self.arrays[1]
        if not self.can_scrub:
            return means, quats
        means, quats = means.copy(), quats.copy()
        R = gaze_rotation(torch.tensor([pitch, yaw], dtype=torch.float32))
        # toolkit.eyes.rotate_about in numpy (elementwise; no threaded kernels for a few thousand rows).
        aw, ax, ay, az = matrix_to_quat(R).numpy().astype(np.float32)
        R = R.numpy().astype(np.float32)
        for name, eye in self.eye_info.items():
            idx = self.eye_index[name]
            c = eye["center"].detach().cpu().numpy().astype(np.float32)
            means[idx] = affine_rows(means[idx] - c, R, c)
            b = quats[idx]
            b[(b == 0).all(1)] = (1, 0, 0, 0)  # an all-zero quaternion is the identity, and turns like one
            bw, bx, by, bz = b.T
            quats[idx] = np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                                   aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], 1)
        return means, quats

    def scene_at(self, pitch: float, yaw: float):
        """The scene itself with the eyes turned (``toolkit.eyes.redirect_eyes``), e.g. for the torch splatter."""
        from toolkit.eyes import redirect_eyes

        return redirect_eyes(self.scene, (pitch, yaw), info=self.eye_info) if self.can_scrub else self.scene

    def draw(self, splatter, camera, pitch: float = 0.0, yaw: float = 0.0, *, fresh: bool = False):
        """Draw the scene at this gaze. Only the eye rows are compared with the splatter's last inputs, unless
        ``fresh``: the splatter may last have drawn something else (a splatter the caller passed in)."""
        means, quats = self.arrays_at(pitch, yaw)
        return splatter.draw(means, quats, self.arrays[2], self.arrays[3], self.colors, camera.viewmat,
                             camera.K, dynamic=self.dynamic, dynamic_spheres=self.spheres,
                             may_change=None if fresh else self.eye_ids)

    @property
    def eye_ids(self) -> np.ndarray:
        """Rows a gaze change can touch (all other arrays are passed unchanged, frame after frame)."""
        return np.concatenate([*self.eye_index.values(), np.zeros(0, np.int64)])


NO_EYES = "scene has no eye Gaussians (part 1 or 2): gaze scrubbing is disabled"
IDLE_WAIT_S = 0.1
"""Longest sleep of the window loop after a frame that changed nothing; any input event ends it at once."""


# ---------------------------------------------------------------------------------------------- headless
def parse_range(text: str, what: str) -> list[float]:
    """'MIN:MAX:N' (degrees) or a comma list 'a,b,c' -> angles in degrees."""
    try:
        if ":" in text:
            lo, hi, n = text.split(":")
            n = int(n)
            if n < 1:
                raise ValueError
            angles = [float(lo)] if n == 1 else list(np.linspace(float(lo), float(hi), n))
        else:
            angles = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ToolkitError(f"--{what}: expected MIN:MAX:N or a comma list of degrees, got {text!r}") from None
    if not all(math.isfinite(a) for a in angles):
        raise ToolkitError(f"--{what}: expected finite degrees, got {text!r}")
    return angles


def render_gaze_sweep(scene, out_path, pitches: Sequence[float], yaws: Sequence[float], width: int = 512,
                      height: int = 512, *, camera=None, background=(1.0, 1.0, 1.0), fps: float = 8.0,
                      splatter=None, degrees: bool = True) -> dict:
    """Render ``scene`` at every (pitch, yaw) of the grid and write ``out_path`` (.mp4 video or .png sheet).

    The grid is pitch-major (a row per pitch); the video runs it as a serpentine so consecutive frames
    differ by one step. Returns {"path", "frames" [F, H, W, 3] uint8, "gazes" [F, 2] radians, "rects",
    "scrubbing"}; frames are in grid order (rows of the contact sheet).
    """
    from render.gl_context import shared_context as _shared_context
    from render.preview import PreviewSplatter

    out_path = Path(out_path)
    ext = out_path.suffix.lower()
    if ext not in (".mp4", ".png"):
        raise ToolkitError(f"{out_path}: sweep output must end in .mp4 (video) or .png (contact sheet)")
    if not pitches or not yaws:
        raise ToolkitError("render_gaze_sweep: need at least one pitch and one yaw")
    scale = math.pi / 180 if degrees else 1.0
    gs = GazeScene.prepare(scene)
    if not gs.can_scrub:
        print(f"warning: {NO_EYES}; the sweep shows the unchanged scene", file=sys.stderr)
    camera = camera or frame_camera(scene, width, height)
    own = splatter is None
    splatter = splatter or PreviewSplatter(camera.width, camera.height, ctx=_shared_context())
    bg = np.asarray(background, np.float32)
    frames, gazes, rects = [], [], []
    try:
        for p in pitches:
            row = []
            for y in yaws:
                g = (float(p) * scale, float(y) * scale)
                gs.draw(splatter, camera, *g, fresh=not frames and not row)  # the first frame compares all rows
                rgba = splatter.read()
                rgb = rgba[..., :3] + (1 - rgba[..., 3:]) * bg
                row.append(((np.clip(rgb, 0, 1) * 255) + 0.5).astype(np.uint8))
                gazes.append(g)
                rects.append(splatter.last_rect)
            frames.extend(row)
    finally:
        if own:
            splatter.release()
    frames_arr = np.stack(frames)
    if ext == ".png":
        write_contact_sheet(out_path, frames_arr, len(pitches), len(yaws))
    else:
        order = [i * len(yaws) + (j if i % 2 == 0 else len(yaws) - 1 - j)
                 for i in range(len(pitches)) for j in range(len(yaws))]
        write_video(out_path, frames_arr[order], fps)
    return {"path": out_path, "frames": frames_arr, "gazes": np.array(gazes), "rects": rects,
            "scrubbing": gs.can_scrub}


def write_contact_sheet(path, frames: np.ndarray, rows: int, cols: int, gap: int = 2) -> None:
    """[rows * cols, H, W, 3] uint8 -> one PNG grid with ``gap`` white pixels between frames (atomic)."""
    import cv2

    from toolkit.io import atomic_write_bytes

    n, h, w, _ = frames.shape
    sheet = np.full((rows * h + (rows - 1) * gap, cols * w + (cols - 1) * gap, 3), 255, np.uint8)
    for k in range(n):
        r, c = divmod(k, cols)
        sheet[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = frames[k]
    ok, buf = cv2.imencode(".png", sheet[..., ::-1])
    if not ok:
        raise ToolkitError(f"{path}: OpenCV could not encode the PNG")
    atomic_write_bytes(path, buf.tobytes())


def write_video(path, frames: np.ndarray, fps: float) -> None:
    """[F, H, W, 3] uint8 -> an MPEG-4 (mp4v) video through OpenCV: encoded to a temp file beside ``path``, its
    frames counted, then renamed onto ``path`` (``toolkit.io.atomic_path``)."""
    import cv2

    from toolkit.io import atomic_path

    path = Path(path)
    with atomic_path(path, suffix=".mp4") as tmp_path:  # OpenCV writes by file name
        tmp = str(tmp_path)
        h, w = frames.shape[1:3]
        writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
        if not writer.isOpened():
            raise ToolkitError(f"{path}: this OpenCV build cannot write MPEG-4 video (no mp4v encoder); "
                               "write a .png contact sheet instead")
        for f in frames:
            writer.write(np.ascontiguousarray(f[..., ::-1]))
        writer.release()
        cap = cv2.VideoCapture(tmp)
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        if count != len(frames):
            raise ToolkitError(f"{path}: the video writer produced {count} of {len(frames)} frames")


# ---------------------------------------------------------------------------------------------- window
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
        print(f"warning: {NO_EYES}; orbiting still works", file=sys.stderr)
    glfw.ERROR_REPORTING = "ignore"  # failures become one ToolkitError below, not Python warnings
    if not glfw.init():
        _, why = glfw.get_error()
        why = why.decode(errors="replace") if isinstance(why, bytes) else str(why or "")
        raise ToolkitError(f"could not open a window: glfw found no display ({why or 'is DISPLAY set?'}); "
                           "use --headless --sweep OUT for a headless gaze sweep")
    try:
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        glfw.window_hint(glfw.VISIBLE, visible)
        win = glfw.create_window(width, height, "DiT-Gaze preview", None, None)
        if not win:
            _, why = glfw.get_error()
            why = why.decode(errors="replace") if isinstance(why, bytes) else str(why or "")
            raise ToolkitError(f"could not open a window with an OpenGL 3.3 core context ({why}); "
                               "use --headless --sweep OUT instead")
        glfw.make_context_current(win)
        glfw.swap_interval(0)
        ctx = moderngl.create_context(require=330)
        splatter = PreviewSplatter(width, height, ctx=ctx)
        state = ScrubState()
        controls = WindowControls(state)
        glfw.set_key_callback(win, controls.on_key)
        glfw.set_mouse_button_callback(win, controls.on_mouse_button)
        glfw.set_cursor_pos_callback(win, controls.on_cursor)
        base = frame_camera(scene, width, height)
        target = scene.means.detach().cpu().double().quantile(0.5, 0)
        bg = tuple(float(b) for b in background)
        frames, paths, shots, last_title, times, eye_rect = 0, {}, [], 0.0, [], None
        idle, idle_waits = False, 0
        try:
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
                cam = orbit_camera(base, target, state.orbit_yaw, state.orbit_pitch)
                gs.draw(splatter, cam, state.pitch, state.yaw)
                path = splatter.stats.get("path", "full")
                paths[path] = paths.get(path, 0) + 1
                idle = path == "unchanged"
                if path == "incremental":
                    eye_rect = splatter.last_rect
                fbw, fbh = glfw.get_framebuffer_size(win)
                splatter.present((0, 0, fbw, fbh), bg, eye_rect if state.overlay else None)
                glfw.swap_buffers(win)
                times.append(time.perf_counter() - t0)
                if state.screenshot:
                    state.screenshot = False
                    shots.append(_save_screenshot(splatter, bg, screenshot_dir))
                    print(f"saved {shots[-1]}")
                now = time.perf_counter()
                if now - last_title > 0.25:
                    fps = len(times[-30:]) / max(sum(times[-30:]), 1e-9)
                    note = "" if gs.can_scrub else " | no eye Gaussians: scrubbing disabled"
                    glfw.set_window_title(win, f"DiT-Gaze preview | gaze pitch {math.degrees(state.pitch):+.1f}° "
                                               f"yaw {math.degrees(state.yaw):+.1f}° | {scene.num_gaussians} "
                                               f"Gaussians | {fps:.1f} FPS{note}")
                    last_title = now
                frames += 1
        finally:
            splatter.release()
            glfw.destroy_window(win)
        return {"state": state, "frames": frames, "paths": paths, "screenshots": shots,
                "fps": len(times) / max(sum(times), 1e-9), "scrubbing": gs.can_scrub, "idle_waits": idle_waits}
    finally:
        glfw.terminate()


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


# ---------------------------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python apps/preview.py", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Preview a Gaussian head and scrub its gaze live (OpenGL; headless through EGL).",
        epilog=WINDOW_HELP + "\nSCENE is a .safetensors or .ply Gaussian scene, a trained run directory "
        "(train/run.py: its Gaussians' RGB channels, posed with a training subject's code), or demo[:N] for the "
        "procedural head. The eye Gaussians are rotated rigidly about their eyeball centres.")
    ap.add_argument("scene", help="scene file (.safetensors / .ply), a trained run directory, or demo[:N]")
    ap.add_argument("--headless", action="store_true", help="no window: render --sweep through EGL")
    ap.add_argument("--sweep", help="headless output: .mp4 video or .png contact sheet of the gaze grid")
    ap.add_argument("--pitch", default="20:-20:3", help="pitch grid in degrees, MIN:MAX:N or a,b,c; the first is the top row (default 20:-20:3)")
    ap.add_argument("--yaw", default="-30:30:5", help="yaw grid in degrees, MIN:MAX:N or a,b,c; write --yaw=-30:30:5 for a leading minus (default -30:30:5)")
    ap.add_argument("--size", type=int, nargs=2, default=(512, 512), metavar=("W", "H"), help="image size")
    ap.add_argument("--background", default="1,1,1", help="background colour R,G,B in [0, 1]")
    ap.add_argument("--fps", type=float, default=8.0, help="video frame rate")
    ap.add_argument("--max-frames", type=int, default=None, help="window: quit after this many frames")
    ap.add_argument("--screenshot-dir", default="out/preview", help="window: where S saves screenshots")
    args = ap.parse_args(argv)
    w, h = args.size
    if w < 1 or h < 1 or w > 8192 or h > 8192:
        raise ToolkitError(f"--size: expected 1..8192 pixels per side, got {w} {h}")
    try:
        bg = [float(v) for v in args.background.split(",")]
        if len(bg) != 3:
            raise ValueError
    except ValueError:
        raise ToolkitError(f"--background: expected R,G,B, got {args.background!r}") from None
    if args.headless and not args.sweep:
        raise ToolkitError("--headless needs --sweep OUT.mp4 or OUT.png")
    scene = load_scene(args.scene)
    if args.headless:
        t0 = time.perf_counter()
        res = render_gaze_sweep(scene, args.sweep, parse_range(args.pitch, "pitch"), parse_range(args.yaw, "yaw"),
                                w, h, background=bg, fps=args.fps)
        print(f"wrote {res['path']} ({len(res['frames'])} gazes, {w}x{h}, {scene.num_gaussians} Gaussians) "
              f"in {time.perf_counter() - t0:.1f} s")
        return 0
    res = run_window(scene, w, h, background=bg, max_frames=args.max_frames, screenshot_dir=args.screenshot_dir)
    print(f"{res['frames']} frames, {res['fps']:.1f} FPS")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
