"""The bad-input corpus of ``python -m train.data`` (synth, inspect) and of ``python -m geometry fit``'s subject
file: every case exits 2 with one ``error:`` line naming the flag or the file and key, no traceback, no
output written, inputs unchanged, within the time cap.

``apps.redirect RUN DATA OUT`` reads subject files through the same reader (GazeDataset) but only after
opening a trained run, so its HDF5 cases are covered here through ``train.data inspect``."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from tests.fuzz.cli import assert_refused
from tests.train.data.tiny_subject import (
    edited_copy,
    huge_rows,
    link_key,
    replace_key,
    tiny_rows,
    write_tiny_subject,
)


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _virtual(base):
    def edit(f):
        layout = h5py.VirtualLayout(shape=(4, 6), dtype=np.float32)
        layout[:] = h5py.VirtualSource(str(base), "pose", shape=(4, 6))
        del f["pose"]
        f.create_virtual_dataset("pose", layout)
    return edit


def _attr(name, value):
    def edit(f):
        f.attrs[name] = value
    return edit


def _nan_pose():
    pose = tiny_rows()["pose"]
    pose[1, 2] = np.nan
    return replace_key("pose", data=pose)


def _secret(folder):
    secret = folder / "secret.bin"
    secret.write_bytes(np.zeros(96, np.uint8).tobytes())
    return replace_key("pose", shape=(4, 6), dtype=np.float32, external=[(str(secret), 0, 96)])


BAD_FILES = {
    # name: (edit of the valid base file, the error line's key and reason)
    "dangling": (lambda base, d: link_key("w2c_Rmat", h5py.SoftLink("/gone")),
                 r"bad\.h5: key 'w2c_Rmat' is a soft link to '/gone', which does not resolve"),
    "loop": (lambda base, d: link_key("pose", h5py.SoftLink("/pose")), r"bad\.h5: key 'pose' is a soft link"),
    "extlink": (lambda base, d: link_key("head_mask", h5py.ExternalLink(str(base), "/head_mask")),
                r"bad\.h5: key 'head_mask' is an external link to .*base\.h5"),
    "extstorage": (lambda base, d: _secret(d), r"bad\.h5: key 'pose' keeps its data in another file"),
    "virtual": (lambda base, d: _virtual(base), r"bad\.h5: key 'pose' is a virtual dataset"),
    "huge_rows": (lambda base, d: huge_rows(20_000_000),
                  r"bad\.h5: .*20000000 rows would allocate .* more than the memory budget"),
    "short_contiguous": (lambda base, d: replace_key("latent_codes", shape=(4, 144), dtype=np.float32),
                         r"bad\.h5: key 'latent_codes' declares 2304 bytes .* but stores 0"),
    "string_pose": (lambda base, d: replace_key("pose", data=np.array([b"pose"] * 4)),
                    r"bad\.h5: key 'pose' has dtype fixed-length string"),
    "compound_pose": (lambda base, d: replace_key("pose", data=np.zeros(4, [("a", "f4"), ("b", "i4")])),
                      r"bad\.h5: key 'pose' has dtype compound"),
    "vlen_pose": (lambda base, d: replace_key("pose", shape=(4,), dtype=h5py.vlen_dtype(np.float32)),
                  r"bad\.h5: key 'pose' has dtype variable-length"),
    "nan_pose": (lambda base, d: _nan_pose(), r"bad\.h5: key 'pose' contains NaN"),
    "rank_inmat": (lambda base, d: replace_key("inmat", data=np.ones((4, 9), np.float32)),
                   r"bad\.h5: key 'inmat' has shape \[4, 9\], expected \[N, 3, 3\]"),
    "zero_rows": (lambda base, d: _every_key_empty, r"bad\.h5: empty subject"),
    "short_pose": (lambda base, d: replace_key("pose", data=np.zeros((2, 6), np.float32)),
                   r"bad\.h5: key 'pose' has 2 rows, face_patch has 4"),
    "attr_type": (lambda base, d: _attr("subject_params", 7), r"bad\.h5: attribute 'subject_params' is 7"),
    "attr_compound": (lambda base, d: _attr("x", np.zeros(1, [("a", "f4")])), r"bad\.h5: attribute 'x' has type compound"),
    "truncated": (None, r"bad\.h5: not a readable HDF5 file \(truncated or corrupt\?\)"),
}


def _every_key_empty(f):
    for k, v in tiny_rows(1).items():
        del f[k]
        f.create_dataset(k, data=v[:0])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """name -> a bad subject file ``bad.h5``, alone in its own folder (where inspect would write its sheet)."""
    root = tmp_path_factory.mktemp("corpus")
    (root / "base").mkdir()
    base = write_tiny_subject(root / "base" / "base.h5")
    out = {"base": base}
    for name, (make, _) in BAD_FILES.items():
        folder = root / name
        folder.mkdir()
        if make is None:
            out[name] = edited_copy(base, folder / "bad.h5", lambda f: None)
            _truncate(out[name])
        else:
            out[name] = edited_copy(base, folder / "bad.h5", make(base, folder))
    return out


@pytest.fixture(autouse=True)
def _small_memory_budget(monkeypatch):
    # The allocation cases must not depend on the machine's memory.
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "2")


FLAG_CASES = [
    # (id, argv, error line); "{out}" is a folder that must stay as it is, "{base}" the valid subject file
    ("seed_negative", ["synth", "--seed", "-1", "--out", "{out}"], r"--seed: expected a seed in \[0, 4294967295\]"),
    ("seed_2_32", ["synth", "--seed", "4294967296", "--out", "{out}"], r"--seed: expected a seed"),
    ("frames_1e12_text", ["synth", "--frames", "1e12", "--out", "{out}"], r"argument --frames: invalid int value"),
    ("frames_1e12", ["synth", "--frames", "1000000000000", "--out", "{out}"], r"--frames: expected frames per subject"),
    ("frames_zero", ["synth", "--frames", "0", "--out", "{out}"], r"--frames: expected frames per subject in \[1, "),
    ("subjects_1e12", ["synth", "--subjects", "1000000000000", "--out", "{out}"],
     r"--subjects: expected a number of subject files in \[1, 10000\]"),
    ("subjects_zero", ["synth", "--subjects", "0", "--out", "{out}"], r"--subjects: expected"),
    ("test_frames_huge", ["synth", "--test-frames", "99999999999", "--out", "{out}"], r"--test-frames: expected"),
    ("res_huge", ["synth", "--res", "100000", "--out", "{out}"], r"--res: expected an image size in pixels in \[16, 2048\]"),
    ("res_small", ["synth", "--res", "7", "--out", "{out}"], r"--res: expected"),
    ("frames_times_res", ["synth", "--frames", "5000", "--res", "2048", "--out", "{out}"],
     r"one subject .*--frames 5000 .*--res 2048.* would allocate .* lower --frames or --res"),
    ("test_frames_times_res", ["synth", "--frames", "1", "--test-frames", "9000", "--res", "1024", "--out", "{out}"],
     r"one subject .*--test-frames 9000 .* would allocate .* lower --frames or --res"),
    ("light_nan", ["synth", "--light-jitter", "nan", "--out", "{out}"], r"--light-jitter: expected a spread in \[0, 2\]"),
    ("light_inf", ["synth", "--light-jitter", "inf", "--out", "{out}"], r"--light-jitter: expected"),
    ("tile_huge", ["inspect", "{base}", "--tile", "100000"], r"--tile: expected a tile side in pixels in \[16, 4096\]"),
    ("tile_small", ["inspect", "{base}", "--tile", "4"], r"--tile: expected"),
    ("n_huge", ["inspect", "{base}", "--n", "100000000000"], r"--n: expected a number of images in \[1, 10000\]"),
    ("n_negative", ["inspect", "{base}", "--n", "-3"], r"--n: expected"),
    ("sheet_not_png", ["inspect", "{base}", "--sheet", "{out}/sheet.jpg"], r"--sheet .*expected a file name ending in \.png"),
    ("sheet_is_input", ["inspect", "{base}", "--sheet", "{base}"], r"--sheet .*(png|input)"),
    ("inspect_missing", ["inspect", "{out}/missing.h5"], r"missing\.h5: no such file"),
    ("inspect_empty_folder", ["inspect", "{out}"], r"no \*\.h5 subject files"),
]


@pytest.mark.parametrize("argv,match", [c[1:] for c in FLAG_CASES], ids=[c[0] for c in FLAG_CASES])
def test_train_data_flags(files, tmp_path, argv, match):
    out = tmp_path / "out"
    out.mkdir()
    argv = [a.format(out=out, base=files["base"]) for a in argv]
    assert_refused(cli="train.data", argv=argv, match=match, inputs=[files["base"]], out_dir=tmp_path)


@pytest.mark.parametrize("name", list(BAD_FILES))
def test_train_data_inspect_bad_files(files, name):
    p = files[name]
    assert_refused(cli="train.data", argv=["inspect", p], match=BAD_FILES[name][1], inputs=[p], out_dir=p.parent)


GEOMETRY_FILES = ["dangling", "loop", "extlink", "extstorage", "virtual", "huge_rows", "string_pose", "vlen_pose", "nan_pose", "truncated"]


@pytest.mark.parametrize("name", GEOMETRY_FILES)
def test_geometry_fit_bad_files(files, tmp_path, name):
    p = files[name]
    match = BAD_FILES[name][1].replace("bad\\.h5: key 'pose' contains NaN", "bad\\.h5: pose contains NaN")
    assert_refused(cli="geometry", argv=["fit", p, tmp_path / "fit", "--steps", "1"], match=match, inputs=[p],
                   out_dir=tmp_path)
