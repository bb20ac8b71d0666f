"""The preview's headless gaze sweep (through EGL): a grid of gazes -> an MPEG-4 video or a PNG contact sheet."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from apps.gaze_scene import GazeScene, frame_camera, visibility_warning
from toolkit.errors import ToolkitError
from toolkit.io import check_output_folder
from toolkit.limits import check_allocation, check_count

MAX_GAZES = 1000
"""Most gazes along one axis of a sweep (--pitch or --yaw)."""
MAX_FRAMES = 10000
"""Most frames of a sweep (pitches x yaws): at a few tens of ms per frame and read-back, minutes of work."""
SHEET_MAX_SIDE = 1_000_000
"""libpng refuses wider or taller PNGs."""
SHEET_MAX_PIXELS = 1 << 30
"""OpenCV reads no larger image back (its CV_IO_MAX_IMAGE_PIXELS)."""
VIDEO_SIDES = (2, 8191)
"""Frame sides the mp4v (MPEG-4 part 2) encoder accepts."""


def parse_range(text: str, what: str) -> list[float]:
    """'MIN:MAX:N' (degrees) or a comma list 'a,b,c' -> angles in degrees (at most ``MAX_GAZES``)."""
    try:
        if ":" in text:
            lo, hi, n = text.split(":")
            n = int(n)
            lo, hi = float(lo), float(hi)
        else:
            angles = [float(v) for v in text.split(",") if v.strip()]
            n = len(angles)
    except ValueError:
        raise ToolkitError(f"--{what}: expected MIN:MAX:N or a comma list of degrees, got {text!r}") from None
    check_count(n, f"--{what}", 1, MAX_GAZES, "a number of gazes")
    if ":" in text:
        with np.errstate(all="ignore"):  # -1e308:1e308 overflows: refused as not finite just below
            angles = [lo] if n == 1 else list(np.linspace(lo, hi, n))
    if not all(math.isfinite(a) for a in angles):
        raise ToolkitError(f"--{what}: expected finite degrees, got {text!r}")
    if not all(-90 <= a <= 90 for a in angles):  # an eye turned further would look into the head
        raise ToolkitError(f"--{what}: expected degrees in [-90, 90], got {text!r}")
    return angles


def check_sweep(out_path, n_pitch: int, n_yaw: int, width: int, height: int) -> None:
    """Refuse, before any work, a sweep whose output could not be written or would cost too much: the output
    type, the frame count, the memory its frames take and the size limits of the PNG / MPEG-4 encoders."""
    path = Path(out_path)
    ext = path.suffix.lower()
    if ext not in (".mp4", ".png"):
        raise ToolkitError(f"{path}: sweep output must end in .mp4 (video) or .png (contact sheet)")
    if path.is_dir():
        raise ToolkitError(f"--sweep {path}: is a directory, expected a .png or .mp4 file path")
    check_output_folder(path.parent, f"--sweep {path}")
    frames = check_count(n_pitch * n_yaw, "--pitch x --yaw", 1, MAX_FRAMES, "a number of sweep frames")
    hint = "lower --size or the number of --pitch / --yaw gazes"
    # The frames as uint8 RGB, then stacked, then reordered into the video or laid out on the sheet.
    check_allocation(3.0 * frames * width * height * 3, f"a sweep of {frames} frames of {width}x{height}", hint)
    if ext == ".mp4":
        lo, hi = VIDEO_SIDES
        check_count(width, "--size W (of an .mp4 sweep)", lo, hi, "pixels")
        check_count(height, "--size H (of an .mp4 sweep)", lo, hi, "pixels")
        return
    sheet_w, sheet_h = n_yaw * (width + 2) - 2, n_pitch * (height + 2) - 2
    if max(sheet_w, sheet_h) > SHEET_MAX_SIDE or sheet_w * sheet_h > SHEET_MAX_PIXELS:
        raise ToolkitError(f"--sweep {path}: a contact sheet of {sheet_w}x{sheet_h} pixels, more than PNG readers "
                           f"take (at most {SHEET_MAX_SIDE} per side and {SHEET_MAX_PIXELS} in all); {hint}")


def render_gaze_sweep(scene, out_path, pitches: Sequence[float], yaws: Sequence[float], width: int = 512,
                      height: int = 512, *, camera=None, background=(1.0, 1.0, 1.0), fps: float = 8.0,
                      splatter=None, degrees: bool = True) -> dict:
    """Render ``scene`` at every (pitch, yaw) of the grid and write ``out_path`` (.mp4 video or .png sheet).

    The grid is pitch-major (a row per pitch); the video runs it as a serpentine so consecutive frames
    differ by one step. Returns {"path", "frames" [F, H, W, 3] uint8, "gazes" [F, 2] radians, "rects",
    "scrubbing"}; frames are in grid order (rows of the contact sheet).
    """
    from render.gl_context import shared_context
    from render.preview import PreviewSplatter

    out_path = Path(out_path)
    ext = out_path.suffix.lower()
    if not pitches or not yaws:
        raise ToolkitError("render_gaze_sweep: need at least one pitch and one yaw")
    camera = camera or frame_camera(scene, width, height)
    check_sweep(out_path, len(pitches), len(yaws), camera.width, camera.height)
    scale = math.pi / 180 if degrees else 1.0
    gs = GazeScene.prepare(scene)
    if not gs.can_scrub:
        print(f"warning: {gs.no_scrub}; the sweep shows the unchanged scene", file=sys.stderr)
    own = splatter is None
    splatter = splatter or PreviewSplatter(camera.width, camera.height, ctx=shared_context())
    bg = np.asarray(background, np.float32)
    frames, gazes, rects = [], [], []
    try:
        for p in pitches:
            row = []
            for y in yaws:
                g = (float(p) * scale, float(y) * scale)
                gs.draw(splatter, camera, *g, fresh=not frames and not row)  # the first frame compares all rows
                if not frames and not row and (why := visibility_warning(camera, splatter)):
                    print(f"warning: {why}", file=sys.stderr)
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

