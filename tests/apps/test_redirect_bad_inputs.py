"""Bad input to ``python -m apps.redirect`` (flags, gaze specs, labels CSVs, image bombs, a full disk): one line,
exit 2, inputs unchanged, nothing new beside the output. Part of the fuzz suite (marker ``fuzz``)."""

from __future__ import annotations

import os
import re
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from PIL import Image

from apps import redirect
from tests.apps.helpers import interrupt_redirect_before_assembly
from tests.apps.test_redirect_csv import HEADER, write_crops
from tests.fuzz.cli import assert_refused
from toolkit.errors import ToolkitError

pytestmark = pytest.mark.fuzz
ROOT = Path(__file__).resolve().parents[2]


def _h5(run: Path) -> Path:
    return sorted((run / "data").glob("*.h5"))[-1]


# (id, extra flags, error regex): refused by the flags' own checks or the sizes they imply, before any render.
FLAGS = [
    ("fit-steps-1e8", ["--fit-steps", "100000000"], r"--fit-steps: expected test-time fitting steps per row in \[0, 20000\]"),
    ("batch-0", ["--batch", "0"], r"--batch: expected input rows per chunk in \[1, 4096\]"),
    ("batch-huge", ["--batch", "1000000"], r"--batch: expected input rows per chunk"),
    ("rows-negative", ["--rows", "-3"], r"--rows: expected a row count"),
    ("steps-negative", ["--steps", "-1"], r"--steps: expected DDIM steps"),
    ("steps-huge", ["--steps", "10000000"], r"--steps: expected DDIM steps"),
    ("seed-2^32", ["--seed", "4294967296"], r"--seed must be in \[0, 2\^32\)"),
    ("fit-lr-nan", ["--fit-lr", "nan"], r"--fit-lr must be in \(0, 1\]"),
    ("grid-zero", ["--gazes", "grid:0x3:20"], r"at least 1 row and 1 column"),
    ("grid-cap", ["--gazes", "grid:1000x1000:20"], r"at most 100000 per input row"),
    ("grid-noise", ["--gazes", "grid:316x316:30"], r"99856 gazes.*would allocate"),
    ("random-cap", ["--gazes", "random:1000000:30"], r"expected 1..100000 random gazes"),
    ("range-90", ["--gazes", "grid:3x3:90"], r"expected a range in \[0, 90\) degrees"),
    ("range-nan", ["--gazes", "random:3:nan"], r"expected a range in \[0, 90\) degrees"),
    ("bad-kind", ["--gazes", "spiral:3"], r"expected grid:"),
    ("no-file", ["--gazes", "file:/nonexistent/g.csv"], r"--gazes file /nonexistent/g.csv: no such file"),
    ("natural-eyes-alone", ["--natural-eyes"], r"--natural-eyes sets how --fit-weights fits"),
    ("fit-weights-0-steps", ["--fit-weights", "--fit-steps", "0"], r"--fit-weights needs --fit-steps >= 1"),
    ("fit-steps-alone", ["--fit-steps", "3"], r"--fit-steps sets how long --fit-weights fits each row .* give "
     r"--fit-weights too"),
]


@pytest.mark.parametrize("flags, match", [pytest.param(f, m, id=i) for i, f, m in FLAGS])
def test_bad_flags(tiny_trained_run, tmp_path, flags, match):
    data = _h5(tiny_trained_run)
    assert_refused("apps.redirect", [tiny_trained_run, data, tmp_path / "out.h5", *flags], match,
                   inputs=[data], out_dir=tmp_path)


def test_outputs_that_are_inputs_or_not_hdf5(tiny_trained_run, tmp_path):
    data = _h5(tiny_trained_run)
    assert_refused("apps.redirect", [tiny_trained_run, data, data], r"out", inputs=[data], out_dir=tmp_path)
    assert_refused("apps.redirect", [tiny_trained_run, data, tmp_path / "out.png"], r"ending in .h5",
                   inputs=[data], out_dir=tmp_path)
    picture = tmp_path / "face.h5"  # a photo under a dataset's name: the name, not the output, is the mistake
    Image.new("RGB", (8, 8)).save(picture, format="PNG")
    assert_refused("apps.redirect", [tiny_trained_run, picture, tmp_path / "out"],
                   rf"^error: dataset {re.escape(str(picture))}: a picture by its content, named as an HDF5 dataset",
                   inputs=[picture], out_dir=tmp_path)


def test_an_output_inside_the_run_neither_replaces_its_files_nor_joins_its_data(tiny_trained_run, tmp_path):
    """An output in the run's data folder (its training subjects, or a new file a retraining would take as a
    subject) is refused before any work, under any
    spelling of its path; every file of the run is left as it was and nothing is added to it."""
    run_files = sorted(p for p in tiny_trained_run.rglob("*") if p.is_file())
    subject = tiny_trained_run / "data" / "subject0000.h5"
    assert subject in run_files
    other = _h5(tiny_trained_run)
    for out, match in ((subject, "inside the run's data folder"),
                       (tiny_trained_run / "data" / ".." / "data" / "subject0000.h5", "inside the run's data folder"),
                       (tiny_trained_run / "data" / "new.h5", "inside the run's data folder")):
        assert_refused("apps.redirect", [tiny_trained_run, other, out, "--rows", "1", "--gazes", "grid:1x1:10"],
                       rf"^error: out .*: {match}", inputs=run_files, out_dir=tiny_trained_run)


def test_an_earlier_output_inside_the_run_may_be_written_again(tiny_trained_run, tmp_path):
    from apps import redirect
    from apps.redirect_parts import check_out_of_run

    run = tmp_path / "run"
    shutil.copytree(tiny_trained_run, run)
    argv = [run, _h5(run), run / "redirected.h5", "--rows", "1", "--gazes", "grid:1x1:10"]
    assert redirect.main([str(a) for a in argv]) == 0
    check_out_of_run(run / "redirected.h5", run)  # its own earlier output: not refused
    with h5py.File(run / "mine.h5", "w") as f:  # any other HDF5 file of the run's folder is
        f.attrs["generator"] = "a notebook"
    with pytest.raises(ToolkitError, match=r"mine.h5: already exists inside the run .* not an earlier output of "
                                           r"apps.redirect; writing it would replace it"):
        check_out_of_run(run / "mine.h5", run)
    assert redirect.main([str(a) for a in argv[:3]] + ["--rows", "1", "--gazes", "grid:1x1:20"]) == 0


def test_gaze_files(tiny_trained_run, tmp_path):
    data, gz = _h5(tiny_trained_run), tmp_path / "in" / "g.csv"
    gz.parent.mkdir()
    cases = [("pitch,yaw\n", r"expected lines of 'pitch,yaw'"), ("", r"no gazes in the file"),
             ("1,2,3\n", r"expected two columns"), ("95,0\n", r"within ±90°"), ("nan,0\n", r"finite"),
             ("0,0\n" * 100_001, r"at most 100000")]
    for text, match in cases:
        gz.write_text(text)
        assert_refused("apps.redirect", [tiny_trained_run, data, tmp_path / "out.h5", "--gazes", f"file:{gz}"],
                       match, inputs=[data, gz], out_dir=tmp_path)
    gz.write_bytes(b"0,0\n" * 2_000_000)  # 8 MB: refused from its size, before it is parsed
    assert_refused("apps.redirect", [tiny_trained_run, data, tmp_path / "out.h5", "--gazes", f"file:{gz}"],
                   r"bytes; expected at most 100000 lines", inputs=[data, gz], out_dir=tmp_path)


def _bomb(path: Path, side: int = 20_000) -> None:
    """A PNG declaring side x side pixels of one colour: a few hundred KB that decode to side² x 3 bytes."""
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    row = b"\0" * (side + 1)  # a filter byte, then one grey byte a pixel
    comp = zlib.compressobj(9)
    body = b"".join(comp.compress(row) for _ in range(side)) + comp.flush()
    ihdr = side.to_bytes(4, "big") * 2 + bytes([8, 0, 0, 0, 0])
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", body) + chunk(b"IEND", b""))


def test_labels_csv_bad_rows(tiny_trained_run, tmp_path):
    crops = tmp_path / "crops"
    write_crops(tiny_trained_run, crops, n=1)
    labels = crops / "labels.csv"
    good = labels.read_text().splitlines()[1]
    cells = good.split(",")
    cases = [
        (",".join(cells[:3] + ["1e300", cells[4]] + cells[5:]), r"column 'gaze_pitch': expected degrees"),
        (",".join(["img0.png"] + cells[1:]) + ",extra", r"cells, the header has"),
        (",".join(["missing.png"] + cells[1:]), r"column 'image': missing.png|no such file"),
    ]
    for row, match in cases:
        labels.write_text(HEADER + "\n" + row + "\n")
        assert_refused("apps.redirect", [tiny_trained_run, labels, tmp_path / "out.h5"], match,
                       inputs=[crops], out_dir=tmp_path)
    rows = [",".join(cells[:3] + ["1e300", cells[4]] + cells[5:]), good, ",".join(["missing.png"] + cells[1:]),
            ",".join(cells[:3] + ["nan", cells[4]] + cells[5:])]
    labels.write_text(HEADER + "\n" + "\n".join(rows) + "\n")  # every bad line named in one run
    assert_refused("apps.redirect", [tiny_trained_run, labels, tmp_path / "out.h5"],
                   r"line 2, column 'gaze_pitch': expected degrees .* \(and 2 more line\(s\) with problems: 4, 5\)$",
                   inputs=[crops], out_dir=tmp_path)
    labels.write_text(HEADER + ",focal\n" + good + ",1e300\n")
    assert_refused("apps.redirect", [tiny_trained_run, labels, tmp_path / "out.h5"],
                   r"line 2, column 'focal': expected pixels in \[0, ", inputs=[crops], out_dir=tmp_path)
    _bomb(crops / "bomb.png")
    assert (crops / "bomb.png").stat().st_size < 1_000_000
    labels.write_text(HEADER + "\n" + ",".join(["bomb.png"] + cells[1:]) + "\n")
    assert_refused("apps.redirect", [tiny_trained_run, labels, tmp_path / "out.h5"],
                   r"bomb.png: 20000x20000 pixels .* expected at most", inputs=[crops], out_dir=tmp_path)
    labels.write_text(HEADER + "\n" + good + "\n")
    assert_refused("apps.redirect", [tiny_trained_run, labels, tmp_path / "out.h5", "--focal", "1e300"],
                   r"--focal 1e\+300: expected at most 1000 image widths", inputs=[crops], out_dir=tmp_path)


def _limited() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, 40_000))


def test_redirect_on_a_full_disk(tiny_trained_run, tmp_path):
    """The chunk being written is removed; the chunks finished before are kept for a resume (by design)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-m", "apps.redirect", str(tiny_trained_run), str(_h5(tiny_trained_run)),
                        str(tmp_path / "out.h5"), "--gazes", "grid:3x3:20", "--rows", "4"], env=env,
                       preexec_fn=_limited, capture_output=True, text=True, timeout=300)
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert len(errors) == 1 and "file too large" in errors[0], r.stderr[-2000:]
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    assert not (tmp_path / "out.h5").exists()


def _truncate(chunk: Path) -> None:
    chunk.write_bytes(chunk.read_bytes()[:1000])


def _empty(chunk: Path) -> None:
    chunk.write_bytes(b"")


def _rewrite(chunk: Path, change) -> None:
    with np.load(chunk) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    np.savez(chunk, **arrays)


def _nan(arrays: dict) -> None:
    arrays["pose"][0, 0] = np.nan
    arrays["pitchyaw_cam"][-1] = np.nan


def _without_pose(arrays: dict) -> None:
    del arrays["pose"]


DAMAGED_CHUNKS = [
    ("truncated", _truncate, r"unreadable \(BadZipFile"),
    ("zero-bytes", _empty, r"unreadable \(EOFError"),
    ("nan", lambda c: _rewrite(c, _nan), r"array 'pitchyaw_cam' holds 2 non-finite values"),
    ("missing-key", lambda c: _rewrite(c, _without_pose), r"missing the arrays pose"),
    ("short-key", lambda c: _rewrite(c, lambda a: a.update(pose=a["pose"][:1])), r"'pose' has shape \(1, 6\), expected 2 rows"),
    ("wrong-rows", lambda c: _rewrite(c, lambda a: a.update(source_row=a["source_row"] + 5)), r"'source_row' column is not"),
]


@pytest.fixture(scope="module")
def leftover_chunks(tiny_trained_run, tmp_path_factory):
    """An interrupted run's ``OUT.parts`` (settings and two chunks of 2 images each) and the arguments that made
    it (the output path aside)."""
    d = tmp_path_factory.mktemp("leftover")
    flags = ["--gazes", "grid:1x2:10", "--rows", "2", "--batch", "1"]
    args = [str(tiny_trained_run), str(_h5(tiny_trained_run)), str(d / "o.h5"), *flags]
    with pytest.MonkeyPatch.context() as mp:
        interrupt_redirect_before_assembly(args, mp)
    parts = d / "o.h5.parts"
    assert (parts / "settings.json").is_file() and len(list(parts.glob("part_*.npz"))) == 2
    return parts, args


@pytest.mark.parametrize("damage, match", [pytest.param(f, m, id=i) for i, f, m in DAMAGED_CHUNKS])
def test_resume_refuses_a_damaged_chunk(leftover_chunks, tmp_path, damage, match):
    """A leftover chunk is checked as it is read: a damaged one is one line naming it and saying how to redo it,
    no output is written, and the chunks stay for the rerun."""
    parts, args = leftover_chunks
    out = tmp_path / "o.h5"
    shutil.copytree(parts, tmp_path / "o.h5.parts")  # the settings do not name the output: they apply here too
    chunk = tmp_path / "o.h5.parts" / "part_00001.npz"
    damage(chunk)
    assert_refused("apps.redirect", [*args[:2], out, *args[3:]],
                   rf"^error: chunk {re.escape(str(chunk))}: .*{match}.*; delete it \(or the folder "
                   rf"{re.escape(str(chunk.parent))}\) and rerun",
                   inputs=[Path(args[1]), chunk], out_dir=tmp_path)
    assert not out.exists()
    chunk.unlink()  # as the error says: the chunk is rendered again and the file assembled
    assert redirect.main([*args[:2], str(out), *args[3:]]) == 0
    with h5py.File(out) as h:
        assert {h[k].shape[0] for k in h} == {4}
        assert np.isfinite(h["pose"][:]).all() and np.isfinite(h["pitchyaw_cam"][:]).all()
