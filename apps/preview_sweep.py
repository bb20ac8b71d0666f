"""The preview's headless gaze sweep (through EGL): a grid of gazes -> an MPEG-4 video or a PNG contact sheet."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from apps.gaze_scene import NO_EYES, GazeScene, frame_camera
from toolkit.errors import ToolkitError


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
    from render.gl_context import shared_context
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
    splatter = splatter or PreviewSplatter(camera.width, camera.height, ctx=shared_context())
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

