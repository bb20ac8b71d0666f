"""python -m train.data synth / inspect, and their one-line errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.train.data.conftest import needs_gl
from toolkit.errors import run_cli
from train.data.__main__ import main

ROOT = Path(__file__).resolve().parents[3]


@needs_gl
def test_synth_then_inspect(tmp_path, capsys):
    out = tmp_path / "synth"
    assert run_cli(main, ["synth", "--subjects", "2", "--frames", "1", "--test-frames", "2", "--res", "48",
                          "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["split.json", "subject0000.h5", "subject0001.h5"]
    assert "wrote 2 subjects (54 images at 48x48)" in capsys.readouterr().out  # 18 + 36: the held-out one has 2 frames
    assert run_cli(main, ["inspect", str(out), "--n", "8", "--tile", "64"]) == 0
    text = capsys.readouterr().out
    assert "subject0001.h5" in text and "| images |" in text and "contact sheet" in text
    import imageio.v3 as iio

    sheet = iio.imread(out / "contact_sheet.png")
    assert sheet.shape == (128, 384, 3)
    # Landmarks and mask outlines are drawn: cyan/yellow/green pixels exist.
    assert (np.abs(sheet.astype(int) - [0, 200, 255]).sum(-1) == 0).any()
    assert (np.abs(sheet.astype(int) - [0, 200, 0]).sum(-1) == 0).any()
    assert run_cli(main, ["inspect", str(out / "subject0000.h5"), "--n", "3", "--tile", "32"]) == 0
    assert (out / "subject0000_sheet.png").exists()


def test_cli_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"garbage")
    for args in (["inspect", str(tmp_path / "missing.h5")], ["inspect", str(bad)],
                 ["synth", "--subjects", "0", "--out", str(tmp_path / "o")],
                 ["synth", "--subjects", "1", "--frames", "1", "--light-jitter", "-1", "--out", str(tmp_path / "l")],
                 ["synth", "--subjects", "2", "--frames", "1", "--test-frames", "0", "--out", str(tmp_path / "t")]):
        assert run_cli(main, args) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1, err
    # Flags checked before any file is read or written, each error naming its flag.
    for args, flag in ((["inspect", str(bad), "--n", "0"], "--n"), (["inspect", str(bad), "--tile", "0"], "--tile"),
                       (["synth", "--frames", "0", "--out", str(tmp_path / "f")], "--frames"),
                       (["synth", "--res", "7", "--out", str(tmp_path / "r")], "--res")):
        assert run_cli(main, args) == 2
        assert capsys.readouterr().err.startswith(f"error: {flag}: expected"), args
    assert not (tmp_path / "f").exists() and not (tmp_path / "r").exists()
    # The real entry point: exit status 2, one line, no traceback.
    r = subprocess.run([sys.executable, "-m", "train.data", "inspect", str(bad)], cwd=ROOT, capture_output=True,
                       text=True)
    assert r.returncode == 2 and r.stderr.startswith(f"error: {bad}") and r.stderr.count("\n") == 1, r.stderr


def test_synth_into_a_folder_of_another_dataset_is_refused_and_a_rerun_replaces_its_own(tmp_path, capsys):
    """Two subjects written into a folder of forty would leave a dataset of both, its split.json naming two."""
    out = tmp_path / "data"
    out.mkdir()
    (out / "subject0039.h5").write_bytes(b"someone's subject")
    args = ["synth", "--subjects", "2", "--frames", "1", "--res", "32", "--out", str(out)]
    assert run_cli(main, args) == 2
    assert capsys.readouterr().err.startswith(f"error: --out {out}: holds 1 other dataset file(s) (subject0039.h5)")
    assert [p.name for p in out.iterdir()] == ["subject0039.h5"]
    (out / "subject0039.h5").unlink()
    assert run_cli(main, args) == 0 and run_cli(main, args) == 0  # its own files again: replaced
    assert sorted(p.name for p in out.iterdir()) == ["split.json", "subject0000.h5", "subject0001.h5"]


def test_inspect_of_a_read_only_dataset_prints_its_table_without_a_sheet(tmp_path, capsys, monkeypatch):
    """A shared, read-only dataset: the default sheet beside it cannot be written, which is no error; a --sheet in
    a folder that cannot be made is refused before the files are read."""
    import os

    import train.data.__main__ as cli

    out = tmp_path / "synth"
    assert run_cli(main, ["synth", "--subjects", "1", "--frames", "1", "--res", "32", "--out", str(out)]) == 0
    capsys.readouterr()
    real_access = os.access
    monkeypatch.setattr(cli.os, "access", lambda path, mode: Path(path) != out and real_access(path, mode))
    assert run_cli(main, ["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| subject0000.h5 |" in text and f"contact sheet: not written, {out} is read-only here" in text
    assert not (out / "contact_sheet.png").exists()
    (tmp_path / "file").write_text("")
    assert run_cli(main, ["inspect", str(out), "--sheet", str(tmp_path / "file" / "s.png")]) == 2
    assert capsys.readouterr().err.startswith(f"error: --sheet: {tmp_path / 'file'} is a file, not a folder")
