"""apps/preview.py: the headless gaze sweep (video and contact sheet), the window under Xvfb with
synthetic input events, and bad input (missing/corrupt scenes, no eye Gaussians, no EGL)."""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import moderngl
import numpy as np
import pytest
import torch

from tests.gl import skip_without_gl
from toolkit.errors import ToolkitError, run_cli

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def egl():
    from render.gl_context import shared_context

    try:
        return shared_context()
    except ToolkitError as e:
        skip_without_gl(f"no headless OpenGL: {e}")


@pytest.fixture(scope="module")
def head():
    from toolkit.procedural import demo_head_scene

    return demo_head_scene(3000, seed=2)


def eye_boxes(scene, camera, margin=2.0):
    """Independent image boxes around each eyeball (centre +- margin * radius, projected)."""
    from toolkit.eyes import eyeball_info

    boxes = []
    for eye in eyeball_info(scene).values():
        c, r = eye["center"], float(eye["radius"]) * margin
        corners = c + r * torch.tensor([[a, b, d] for a in (-1, 1) for b in (-1, 1) for d in (-1, 1)], dtype=c.dtype)
        uv, _ = camera.project(corners)
        boxes.append((int(uv[:, 0].min()) - 2, int(uv[:, 1].min()) - 2, int(uv[:, 0].max()) + 3, int(uv[:, 1].max()) + 3))
    return boxes


def outside_mask(shape, boxes):
    m = np.ones(shape, bool)
    for x0, y0, x1, y1 in boxes:
        m[max(y0, 0):y1, max(x0, 0):x1] = False
    return m


# ------------------------------------------------------------------ headless sweep
def test_png_contact_sheet_differs_only_in_eye_regions(egl, head, tmp_path):
    from apps.gaze_scene import frame_camera
    from apps.preview_sweep import render_gaze_sweep

    S = 96
    out = tmp_path / "sheet.png"
    res = render_gaze_sweep(head, out, [15, -15], [-25, 0, 25], S, S, background=(1, 1, 1))
    sheet = cv2.imread(str(out))[..., ::-1]
    assert sheet.shape == (2 * S + 2, 3 * S + 4, 3)
    tiles = [sheet[r * (S + 2):r * (S + 2) + S, c * (S + 2):c * (S + 2) + S] for r in range(2) for c in range(3)]
    np.testing.assert_array_equal(np.stack(tiles), res["frames"])  # lossless and in grid order
    np.testing.assert_allclose(res["gazes"][4], [math.radians(-15), 0.0], atol=1e-7)
    out_m = outside_mask((S, S), eye_boxes(head, frame_camera(head, S, S)))
    assert out_m.mean() > 0.8
    for t in tiles[1:]:
        diff = np.abs(t.astype(int) - tiles[0].astype(int)).max(-1)
        assert diff[out_m].max() == 0, "pixels outside the eyes changed with gaze"
        assert diff[~out_m].max() > 60, "the eyes did not move"
    assert res["scrubbing"]


def test_a_passed_in_splatter_that_drew_another_scene_shows_this_one(egl, head, tmp_path):
    """The sweep compares only the eye rows frame to frame; its first frame must compare them all, since a
    caller's splatter may last have drawn another scene of the same size."""
    from apps.preview_sweep import render_gaze_sweep
    from render.preview import PreviewSplatter
    from toolkit.scene import GaussianScene

    S = 64
    other = GaussianScene(**{**{k: getattr(head, k) for k in ("means", "quats", "log_scales", "opacity_logits",
                                                               "part", "metadata")},
                             "features": head.features.flip(-1)})  # another face of the same size
    splatter = PreviewSplatter(S, S)
    try:
        render_gaze_sweep(other, tmp_path / "a.png", [0], [0, 10], S, S, splatter=splatter)
        reused = render_gaze_sweep(head, tmp_path / "b.png", [0], [0, 10], S, S, splatter=splatter)["frames"]
    finally:
        splatter.release()
    fresh = render_gaze_sweep(head, tmp_path / "c.png", [0], [0, 10], S, S)["frames"]
    np.testing.assert_array_equal(reused, fresh)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_mp4_sweep_is_a_valid_video(egl, head, tmp_path):
    from apps.gaze_scene import frame_camera
    from apps.preview_sweep import render_gaze_sweep

    S = 96
    out = tmp_path / "sweep.mp4"
    res = render_gaze_sweep(head, out, [10, -10], [-20, 20], S, S, fps=5)
    # Written like every other output: the umask's mode (not mkstemp's 0600), no temporary file left beside it.
    assert out.stat().st_mode & 0o777 == 0o666 & ~_umask() and sorted(tmp_path.iterdir()) == [out]
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 4
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[..., ::-1].astype(int))
    cap.release()
    assert len(frames) == 4 and frames[0].shape == (S, S, 3)
    # Serpentine order: grid frames 0, 1, 3, 2. Lossy, so compare means.
    for dec, k in zip(frames, [0, 1, 3, 2], strict=True):
        assert np.abs(dec - res["frames"][k]).mean() < 4
    out_m = outside_mask((S, S), eye_boxes(head, frame_camera(head, S, S)))
    for f in frames[1:]:
        d = np.abs(f - frames[0]).max(-1)
        assert d[out_m].mean() < 2.0 and d[~out_m].mean() > 3 * max(d[out_m].mean(), 0.5)
    assert not list(tmp_path.glob(".*tmp*")), "a temporary file was left behind"


def test_cli_headless_sweep(egl, tmp_path, capsys):
    from apps.preview import main

    out = tmp_path / "cli.png"
    assert run_cli(main, ["demo:1500", "--headless", "--sweep", str(out), "--pitch", "0", "--yaw=-10,10",
                          "--size", "64", "48"]) == 0
    img = cv2.imread(str(out))
    assert img.shape == (48, 2 * 64 + 2, 3)
    assert "wrote" in capsys.readouterr().out


def test_scene_without_eyes_sweeps_with_a_message(egl, head, tmp_path, capsys):
    from apps.preview import main

    path = tmp_path / "face_only.safetensors"
    head.select(head.part == 0).save(path)
    out = tmp_path / "noeyes.png"
    assert run_cli(main, [str(path), "--headless", "--sweep", str(out), "--yaw=-20,20", "--pitch", "0",
                          "--size", "48", "48"]) == 0
    assert "no eye Gaussians" in capsys.readouterr().err
    sheet = cv2.imread(str(out))
    np.testing.assert_array_equal(sheet[:, :48], sheet[:, 50:])


def test_unusable_eyeballs_are_named_not_called_missing(egl, head, tmp_path, capsys):
    """Eye Gaussians that give no eyeball (three of them, no metadata["eyes"]): the sweep runs without
    scrubbing and says why, never that the scene has no eye Gaussians; malformed metadata["eyes"] is an
    error naming it."""
    from apps.preview import main
    from apps.preview_sweep import render_gaze_sweep

    left = torch.nonzero(head.part == 1).flatten()
    keep = (head.part == 0) | (head.part == 2)
    keep[left[:3]] = True
    scene = head.select(keep)
    scene.metadata = {k: v for k, v in scene.metadata.items() if k != "eyes"}
    path = tmp_path / "three_eye_gaussians.safetensors"
    scene.save(path)
    out = tmp_path / "sheet.png"
    assert run_cli(main, [str(path), "--headless", "--sweep", str(out), "--yaw=-20,20", "--pitch", "0",
                          "--size", "32", "32"]) == 0
    err = capsys.readouterr().err
    assert "no eye Gaussians" not in err and len(err.strip().splitlines()) == 1
    assert re.search(r"warning: the scene's eye Gaussians cannot be turned \(scene left eye: its 3 Gaussians give "
                     r"no eyeball sphere.*\): gaze scrubbing is disabled", err)
    sheet = cv2.imread(str(out))
    np.testing.assert_array_equal(sheet[:, :32], sheet[:, 34:])
    bad = head.select(torch.ones(head.num_gaussians, dtype=torch.bool))
    bad.metadata["eyes"] = {"left": "junk"}
    with pytest.raises(ToolkitError, match=r"metadata\.eyes\.left: expected a mapping"):
        render_gaze_sweep(bad, tmp_path / "never.png", [0.0], [0.0], 32, 32)
    assert not (tmp_path / "never.png").exists()


def test_a_scene_that_draws_nothing_says_why(egl, head, tmp_path, capsys):
    """Every Gaussian culled by render.cull (scales e^80): the sheet is the background, exit 0, and a warning
    says why; a scene with some culled ones counts them."""
    from apps.preview import main

    scene = head.select(torch.ones(head.num_gaussians, dtype=torch.bool))
    scene.log_scales = torch.full_like(scene.log_scales, 80.0)
    scene.save(tmp_path / "huge.safetensors")
    out = tmp_path / "huge.png"
    assert run_cli(main, [str(tmp_path / "huge.safetensors"), "--headless", "--sweep", str(out), "--pitch", "0",
                          "--yaw", "0", "--size", "32", "24", "--background", "0,1,0"]) == 0
    err = capsys.readouterr().err
    n = head.num_gaussians
    assert f"warning: nothing is drawn from this view: of {n} Gaussians, {n} culled ({n} with a scale above 1e+18)" \
        in err and "the frames show only the background" in err
    np.testing.assert_array_equal(cv2.imread(str(out)), np.broadcast_to(np.uint8([0, 255, 0]), (24, 32, 3)))
    some = head.select(torch.ones(n, dtype=torch.bool))
    some.log_scales = some.log_scales.clone()
    some.log_scales[:7] = 80.0
    some.save(tmp_path / "some.safetensors")
    assert run_cli(main, [str(tmp_path / "some.safetensors"), "--headless", "--sweep", str(tmp_path / "s.png"),
                          "--pitch", "0", "--yaw", "0", "--size", "32", "24"]) == 0
    assert f"warning: 7 of {n} Gaussians are not drawn (7 with a scale above 1e+18)" in capsys.readouterr().err


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("case, match", [
    ("missing", "no such scene file"),
    ("corrupt", "not a valid safetensors file"),
    ("corrupt_ply", "ply"),
    ("extension", "expected a .safetensors or .ply"),
    ("no_sweep", "--headless needs --sweep"),
    ("bad_sweep_ext", "must end in .mp4"),
    ("bad_pitch", "--pitch: expected MIN:MAX:N"),
    ("nan_yaw", "--yaw: expected finite degrees"),
    ("bad_demo", "demo:N"),
    ("fps_zero", "--fps: expected a video frame rate"),
    ("nan_background", "--background: expected R,G,B each in [0, 1]"),
])
def test_bad_input_exits_2_with_one_line(egl, tmp_path, capsys, case, match):
    from apps.preview import main

    garbage = tmp_path / "bad.safetensors"
    garbage.write_bytes(b"\x00\x01not a safetensors file")
    bad_ply = tmp_path / "bad.ply"
    bad_ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    argv = {
        "missing": [str(tmp_path / "nope.ply"), "--headless", "--sweep", str(tmp_path / "o.png")],
        "corrupt": [str(garbage), "--headless", "--sweep", str(tmp_path / "o.png")],
        "corrupt_ply": [str(bad_ply), "--headless", "--sweep", str(tmp_path / "o.png")],
        "extension": [str(tmp_path / "model.pt"), "--headless", "--sweep", str(tmp_path / "o.png")],
        "no_sweep": ["demo:200", "--headless"],
        "bad_sweep_ext": ["demo:200", "--headless", "--sweep", str(tmp_path / "o.gif")],
        "bad_pitch": ["demo:200", "--headless", "--sweep", str(tmp_path / "o.png"), "--pitch", "a:b"],
        "nan_yaw": ["demo:200", "--headless", "--sweep", str(tmp_path / "o.png"), "--yaw", "nan,1"],
        "bad_demo": ["demo:many", "--headless", "--sweep", str(tmp_path / "o.png")],
        "fps_zero": ["demo:200", "--headless", "--sweep", str(tmp_path / "o.mp4"), "--fps", "0"],
        "nan_background": ["demo:200", "--headless", "--sweep", str(tmp_path / "o.png"), "--background", "nan,nan,nan"],
    }[case]
    assert run_cli(main, argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
    assert match.lower() in err.lower()
    assert not (tmp_path / "o.png").exists()


def test_missing_egl_is_a_clear_cli_error(tmp_path, capsys, monkeypatch):
    import ctypes.util

    from apps.preview import main
    from render import gl_context

    def no_egl(*a, **k):
        raise Exception("libEGL.so.1: cannot open shared object file")

    monkeypatch.setattr(gl_context, "_SHARED_CONTEXT", None)
    monkeypatch.setattr(moderngl, "create_context", no_egl)
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None if name == "EGL" else f"lib{name}.so")
    assert run_cli(main, ["demo:200", "--headless", "--sweep", str(tmp_path / "o.png")]) == 2
    err = capsys.readouterr().err
    assert "EGL" in err and "libEGL.so" in err and "Traceback" not in err


def test_script_entry_point_prints_no_traceback(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "apps" / "preview.py"), str(tmp_path / "x.ply"), "--headless",
                        "--sweep", str(tmp_path / "o.png")], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr
    h = subprocess.run([sys.executable, str(ROOT / "apps" / "preview.py"), "--help"], capture_output=True,
                       text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert h.returncode == 0 and "a trained run directory" in " ".join(h.stdout.split())
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    w = subprocess.run([sys.executable, str(ROOT / "apps" / "preview.py"), "demo:200"], capture_output=True,
                       text=True, timeout=120, env={**env, "PYTHONPATH": str(ROOT)})
    assert w.returncode == 2 and w.stderr.startswith("error: could not open a window")
    assert "--headless" in w.stderr and len(w.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------ window under Xvfb
@pytest.fixture
def xdisplay(monkeypatch):
    """A private Xvfb server (its display number chosen by Xvfb itself); skipped where none can start."""
    if shutil.which("Xvfb") is None:
        pytest.skip("window test needs an X server: the Xvfb binary is not installed (Debian package xvfb)")
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", "320x240x24", "-nolisten", "tcp"],
                            pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(w)
    try:
        import select

        ready, _, _ = select.select([r], [], [], 20)
        num = os.read(r, 32).decode().strip() if ready else ""
        if not num:
            proc.kill()
            pytest.skip(f"window test needs an X server: Xvfb did not start ({proc.stderr.read(300)!r})")
        monkeypatch.setenv("DISPLAY", f":{num}")
        yield f":{num}"
    finally:
        os.close(r)
        proc.terminate()
        proc.wait(10)


WINDOW_SCRIPT = r"""
import json, math, sys
import glfw
from apps.preview_window import run_window
from toolkit.errors import ToolkitError
from toolkit.procedural import demo_head_scene

L, P, R = glfw.MOUSE_BUTTON_LEFT, glfw.PRESS, glfw.RELEASE
events = {
    1: [("on_mouse_button", L, P, 0), ("on_cursor", 50.0, 50.0)],
    2: [("on_cursor", 70.0, 40.0)],                                  # drag: right 20 px, up 10 px
    3: [("on_mouse_button", L, R, 0), ("on_key", glfw.KEY_RIGHT, 0, P, 0),
        ("on_key", glfw.KEY_O, 0, P, 0), ("on_key", glfw.KEY_S, 0, P, 0)],
    4: [("on_key", glfw.KEY_LEFT, 0, P, glfw.MOD_SHIFT)],             # orbit: the camera moves
    6: [("on_key", glfw.KEY_Q, 0, P, 0)],
}
try:
    res = run_window(demo_head_scene(3000, seed=2), 96, 80, max_frames=50, events=events,
                     screenshot_dir=sys.argv[1], visible=False)
except ToolkitError as e:
    print(json.dumps({"skip": str(e)}))
    sys.exit(0)
s = res["state"]
print(json.dumps({"frames": res["frames"], "quit": s.quit, "overlay": s.overlay, "pitch": s.pitch, "yaw": s.yaw,
                  "orbit_yaw": s.orbit_yaw, "paths": res["paths"], "shots": [str(p) for p in res["screenshots"]],
                  "idle_waits": res["idle_waits"]}))
"""


def test_window_scrubs_gaze_with_synthetic_events(xdisplay, tmp_path):
    """Runs in its own process: an EGL context and a GLX window in one process upset Mesa's GLX."""
    import json

    r = subprocess.run([sys.executable, "-c", WINDOW_SCRIPT, str(tmp_path)], capture_output=True, text=True,
                       timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT), "DISPLAY": xdisplay}, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    if "skip" in res:
        pytest.skip(f"window test: Xvfb started but gave no OpenGL 3.3 window: {res['skip']}")
    assert res["frames"] == 7 and res["quit"] and res["overlay"]
    assert res["pitch"] == pytest.approx(math.radians(2.5)) and res["yaw"] == pytest.approx(math.radians(-5 - 2))
    assert res["orbit_yaw"] == pytest.approx(math.radians(-2))
    assert res["paths"].get("incremental", 0) >= 2 and res["paths"].get("full", 0) >= 2
    # Frame 5 gets no input and changes nothing: the loop then sleeps for input instead of spinning.
    assert res["paths"].get("unchanged", 0) >= 1 and res["idle_waits"] >= 1
    (shot,) = res["shots"]
    img = cv2.imread(shot)
    assert img.shape == (80, 96, 3) and img.std() > 10


def test_gaze_scene_matches_redirect_eyes(head):
    from apps.gaze_scene import GazeScene
    from toolkit.eyes import redirect_eyes

    head = head.clone()
    eye = int(torch.nonzero(head.part == 1)[0])
    head.quats[eye] = 0  # an all-zero quaternion is the identity orientation: it must turn with the eye too
    gs = GazeScene.prepare(head)
    for g in [(0.3, -0.2), (-0.5, 0.6)]:
        means, quats = gs.arrays_at(*g)
        ref = redirect_eyes(head, g)
        np.testing.assert_allclose(means, ref.means.numpy(), atol=1e-6)
        np.testing.assert_allclose(quats, ref.quats.numpy(), atol=1e-6)
        assert not np.array_equal(means, head.means.numpy())
        assert abs(quats[eye, 0]) < 0.999 and np.linalg.norm(quats[eye]) == pytest.approx(1, abs=1e-6)
