"""A full disk: each writing CLI stops with one line naming the file, exit 2, and leaves no temporary file.

The disk is filled the way the kernel reports it to a writer: a child process with a file-size limit
(``RLIMIT_FSIZE``, SIGXFSZ ignored) gets ``EFBIG`` on the write that crosses it, as a full file system gives
``ENOSPC``. Both reach the same handler (``toolkit.io.atomic_path``). Before it, h5py's file-object driver
crashed the interpreter (SIGSEGV) on such a write.
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LIMIT = 150_000  # bytes: above every small file written first (config.yaml), below the first large one


def _limited() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT, LIMIT))


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, preexec_fn=_limited, capture_output=True,
                          text=True, timeout=300)


def _assert_full_disk_refusal(r: subprocess.CompletedProcess, folder: Path) -> None:
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert r.returncode == 2, r.stderr[-2000:]
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    assert len(errors) == 1 and "file too large" in errors[0] and "nothing was written" in errors[0], r.stderr
    assert not [p for p in folder.rglob("*") if p.name.endswith(".tmp")], sorted(folder.rglob("*"))


def test_synth_on_a_full_disk(tmp_path):
    from tests.gl import require_gl

    require_gl()
    r = _run(["-m", "train.data", "synth", "--out", str(tmp_path / "d"), "--subjects", "2", "--frames", "2",
              "--res", "64"], tmp_path)
    _assert_full_disk_refusal(r, tmp_path)
    assert not list((tmp_path / "d").glob("*.h5"))


def test_convert_on_a_full_disk(tmp_path):
    from tests.conftest import random_scene

    src = tmp_path / "scene.safetensors"
    random_scene(n=400, d=32).save(src)  # ~70 KB as safetensors, more as an ASCII-free PLY with 32 features
    big = tmp_path / "big.safetensors"
    random_scene(n=3000, d=32).save(big)
    r = _run(["-m", "toolkit", "convert", str(big), str(tmp_path / "out" / "big.ply")], tmp_path)
    _assert_full_disk_refusal(r, tmp_path)
    assert not (tmp_path / "out" / "big.ply").exists()


def test_preview_sheet_on_a_full_disk(tmp_path):
    from tests.gl import require_gl

    require_gl()
    r = _run(["-m", "apps.preview", "demo:3000", "--headless", "--sweep", str(tmp_path / "sheet.png"),
              "--size", "256", "256"], tmp_path)
    _assert_full_disk_refusal(r, tmp_path)


@pytest.mark.slow
def test_a_run_on_a_full_disk(tmp_path):
    from tests.gl import require_gl

    require_gl()
    r = _run(["-m", "train.run", "--preset", "tiny", "--run-dir", str(tmp_path / "run")], tmp_path)
    _assert_full_disk_refusal(r, tmp_path)
