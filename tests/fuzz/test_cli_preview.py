"""The bad-input corpus of ``python -m apps.preview``: bad scene paths and specs, counts and sizes beyond their
bounds (``toolkit.limits``), sweeps too long or too large to write, and bad flags. Every case is refused with
one ``error:`` line naming the argument, exit 2, no traceback, its inputs and output folder unchanged, before
any scene is built or frame rendered (a case that started the work would run into the time cap)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.fuzz.cli import assert_refused

SWEEP = ["--headless", "--sweep", "{out}/sweep.png"]
VIDEO = ["--headless", "--sweep", "{out}/sweep.mp4"]

# (case, argv with {scene} {bad} {bad_ply} {tmp} {out} placeholders, regex the error line matches, env)
CASES = [
    ("missing scene", ["{tmp}/nope.ply", *SWEEP], r"nope\.ply: no such scene file", {}),
    ("scene extension", ["{tmp}/model.pt", *SWEEP], r"model\.pt: expected a \.safetensors or \.ply", {}),
    ("folder without config", ["{tmp}", *SWEEP], r"expected a \.safetensors or \.ply Gaussian scene", {}),
    ("corrupt safetensors", ["{bad}", *SWEEP], r"bad\.safetensors: not a valid safetensors file", {}),
    ("corrupt ply", ["{bad_ply}", *SWEEP], r"bad\.ply", {}),
    ("demo not a number", ["demo:many", *SWEEP], r"scene 'demo:many': expected demo or demo:N", {}),
    ("demo 1e10 Gaussians", ["demo:10000000000", *SWEEP],
     r"scene demo:10000000000: expected a number of demo Gaussians \(demo:N\) in \[64, 2000000\]", {}),
    ("demo too few", ["demo:10", *SWEEP], r"scene demo:10: expected .* in \[64, 2000000\], got 10", {}),
    ("demo negative", ["demo:-5", *SWEEP], r"scene demo:-5: expected .* got -5", {}),
    ("demo over the memory budget", ["demo:1000000", *SWEEP], r"scene demo:1000000 would allocate .* memory budget",
     {"DITGAZE_MEMORY_GB": "0.5"}),
    ("pitch 2000 gazes", ["{scene}", *SWEEP, "--pitch", "0:0:2000", "--yaw=0:0:2000"],
     r"--pitch: expected a number of gazes in \[1, 1000\], got 2000", {}),
    ("4 M sweep frames", ["{scene}", *SWEEP, "--pitch", "0:0:1000", "--yaw=0:0:1000"],
     r"--pitch x --yaw: expected a number of sweep frames in \[1, 10000\], got 1000000", {}),
    ("1001 yaw values", ["{scene}", *SWEEP, "--yaw=" + ",".join(["1"] * 1001)],
     r"--yaw: expected a number of gazes in \[1, 1000\], got 1001", {}),
    ("zero gazes", ["{scene}", *SWEEP, "--pitch", "0:10:0"], r"--pitch: expected a number of gazes .* got 0", {}),
    ("pitch not a range", ["{scene}", *SWEEP, "--pitch", "a:b"], r"--pitch: expected MIN:MAX:N", {}),
    ("fractional count", ["{scene}", *SWEEP, "--pitch", "0:1:2.5"], r"--pitch: expected MIN:MAX:N", {}),
    ("nan yaw", ["{scene}", *SWEEP, "--yaw", "nan,1"], r"--yaw: expected finite degrees", {}),
    ("pitch beyond the head", ["{scene}", *SWEEP, "--pitch", "720"], r"--pitch: expected degrees in \[-90, 90\]", {}),
    ("yaw range beyond the head", ["{scene}", *SWEEP, "--yaw=-1e30:0:3"], r"--yaw: expected degrees in \[-90, 90\]",
     {}),
    ("overflowing range", ["{scene}", *SWEEP, "--pitch=-1e308:1e308:3"], r"--pitch: expected finite degrees", {}),
    ("size zero", ["{scene}", *SWEEP, "--size", "0", "10"], r"--size W: expected pixels per side in \[1, 8192\]", {}),
    ("size too tall", ["{scene}", *SWEEP, "--size", "8", "8193"], r"--size H: expected .* \[1, 8192\], got 8193", {}),
    ("size over the memory budget", ["{scene}", *SWEEP, "--size", "8192", "8192"],
     r"--size 8192 8192 \(the preview's float frames\) would allocate", {"DITGAZE_MEMORY_GB": "0.5"}),
    ("sweep frames over the memory budget", ["{scene}", *SWEEP, "--size", "2048", "2048", "--pitch", "0:0:50",
                                             "--yaw=0:0:50"], r"a sweep of 2500 frames of 2048x2048 would allocate",
     {"DITGAZE_MEMORY_GB": "4"}),
    ("contact sheet too wide", ["{scene}", *SWEEP, "--size", "8000", "8", "--pitch", "0", "--yaw=0:0:200"],
     r"a contact sheet of 1600398x8 pixels", {}),
    ("video frame too small", ["{scene}", *VIDEO, "--size", "1", "1"],
     r"--size W \(of an \.mp4 sweep\): expected pixels in \[2, 8191\], got 1", {}),
    ("video frame too wide", ["{scene}", *VIDEO, "--size", "8192", "64"],
     r"--size W \(of an \.mp4 sweep\): expected pixels in \[2, 8191\], got 8192", {}),
    ("sweep type", ["{scene}", "--headless", "--sweep", "{out}/sweep.gif"], r"sweep\.gif: sweep output must end in", {}),
    ("sweep is a folder", ["{scene}", "--headless", "--sweep", "{tmp}/folder.png"], r"folder\.png: is a directory", {}),
    ("sweep under a file", ["{scene}", "--headless", "--sweep", "{tmp}/file.txt/sweep.png"],
     r"file\.txt is a file, not a folder", {}),
    ("headless without sweep", ["{scene}", "--headless"], r"--headless needs --sweep", {}),
    ("sweep without headless", ["{scene}", "--sweep", "{out}/sweep.png"], r"--sweep is the headless output", {}),
    ("fps zero", ["{scene}", *VIDEO, "--fps", "0"], r"--fps: expected a video frame rate in \[0\.1, 240\]", {}),
    ("fps nan", ["{scene}", *VIDEO, "--fps", "nan"], r"--fps: expected a video frame rate", {}),
    ("fps not a number", ["{scene}", *VIDEO, "--fps", "fast"], r"argument --fps: invalid float value", {}),
    ("background out of range", ["{scene}", *SWEEP, "--background", "2,0,0"], r"--background: expected R,G,B", {}),
    ("background two channels", ["{scene}", *SWEEP, "--background", "1,1"], r"--background: expected R,G,B", {}),
    ("max frames zero", ["{scene}", "--max-frames", "0"], r"--max-frames: expected a number of window frames in", {}),
    ("max frames huge", ["{scene}", "--max-frames", "99999999999"], r"--max-frames: expected .* got 99999999999", {}),
    ("max frames not an int", ["{scene}", "--max-frames", "1e3"], r"argument --max-frames: invalid int value", {}),
    ("screenshot folder is a file", ["{scene}", "--screenshot-dir", "{tmp}/file.txt"],
     r"--screenshot-dir .*file\.txt: .*file\.txt is a file, not a folder", {}),
    ("screenshot folder under a file", ["{scene}", "--screenshot-dir", "{tmp}/file.txt/shots"],
     r"--screenshot-dir .*shots: .*file\.txt is a file, not a folder", {}),
    ("one size value", ["{scene}", *SWEEP, "--size", "64"], r"argument --size: expected 2 arguments", {}),
    ("unknown flag", ["{scene}", *SWEEP, "--frames", "3"], r"unrecognized arguments: --frames 3", {}),
]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from tests.conftest import random_scene

    tmp = tmp_path_factory.mktemp("preview_inputs")
    random_scene(20, d=3).save(tmp / "scene.safetensors")
    (tmp / "bad.safetensors").write_bytes(b"\x00\x01not a safetensors file")
    (tmp / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    (tmp / "folder.png").mkdir()
    (tmp / "file.txt").write_text("a file, not a folder\n")
    return tmp


@pytest.mark.parametrize("case, argv, match, env", CASES, ids=[c[0] for c in CASES])
def test_preview_refuses_bad_input(files: Path, tmp_path, monkeypatch, case, argv, match, env):
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    out = tmp_path / "out"
    out.mkdir()
    names = {"scene": files / "scene.safetensors", "bad": files / "bad.safetensors", "bad_ply": files / "bad.ply",
             "tmp": files, "out": out}
    args = [a.format(**names) for a in argv]
    inputs = [files / n for n in ("scene.safetensors", "bad.safetensors", "bad.ply", "file.txt")]
    assert_refused("apps.preview", args, match, inputs=inputs, out_dir=out, seconds=20)
    assert not any((files / "folder.png").iterdir())


@pytest.mark.parametrize("key", ["1", "~", "yes"])
def test_a_run_directory_whose_config_has_a_non_string_key(tmp_path, key):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(f"{key}: x\n")
    out = tmp_path / "out"
    out.mkdir()
    assert_refused("apps.preview", [run, "--headless", "--sweep", out / "s.png"],
                   r"config.yaml: a mapping key must be a string", inputs=[run], out_dir=out, seconds=20)
