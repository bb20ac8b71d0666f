"""Property: any damage to a valid subject file is accepted or refused with one ToolkitError of one line by every
reader (validation, GazeDataset and its rows, ``train.data inspect``'s summary, ``geometry fit``'s reader) --
never another exception, a huge allocation or a hang.

A tiny valid file is built once per module; each example copies it, edits it with h5py (keys dropped, replaced
by links, external links, external storage, other dtypes or shapes, forged huge shapes in chunked storage, odd
values and attributes), then optionally truncates it or flips bits."""

from __future__ import annotations

import math
import signal
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from tests.train.data.tiny_subject import tiny_rows, tiny_subject_arrays, write_tiny_subject
from toolkit.errors import ToolkitError

ROWS = tiny_rows()
ARRAYS = {**ROWS, **tiny_subject_arrays()}
KEYS = sorted(ARRAYS)
SECONDS = 30  # per reader: a forged file that makes a reader run longer is a hang


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """(valid base file, the path each example writes its damaged copy to); a 1 GiB memory budget, so forged
    sizes are refused the same way on every machine."""
    root = tmp_path_factory.mktemp("h5fuzz")
    (root / "outside.bin").write_bytes(bytes(range(256)) * 64)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DITGAZE_MEMORY_GB", "1")
        yield write_tiny_subject(root / "base.h5"), root / "subject.h5"


# ---------------------------------------------------------------- edits made with h5py

DTYPES = [np.uint8, np.int64, np.uint64, np.float16, np.float64, np.bool_, np.complex64, "S4", "string", "compound",
          "vlen"]
SIZES = [0, 1, 2, 3, 4, 6, 24, 68, 144]
HUGE = [5, 1000, 2**20, 2**24, 2**31, 2**40, 2**55]
ODD_VALUES = [np.nan, np.inf, -np.inf, -1.0, 0.0, 1e30, -1e30, 7.5, 2**31, 2**63]


def _dtype(d):
    special = {"string": h5py.string_dtype(), "compound": np.dtype([("a", "f4"), ("b", "i4")]),
               "vlen": h5py.vlen_dtype(np.float32)}
    return special[d] if isinstance(d, str) and d in special else np.dtype(d)


def _remove(f, key):
    if f.get(key, getlink=True) is not None:
        del f[key]


def _put(f, key, **kw):
    _remove(f, key)
    f.create_dataset(key, **kw)


def _set(f, key, obj):
    _remove(f, key)
    f[key] = obj


@st.composite
def edits(draw):
    """One edit of an open h5py.File: (name, function)."""
    key = draw(st.sampled_from(KEYS))
    kind = draw(st.sampled_from(["drop", "soft", "external", "dtype", "values", "huge", "huge_all", "unwritten",
                                 "external_storage", "virtual", "group", "attr"]))
    if kind == "drop":
        return kind, lambda f, root: _remove(f, key)
    if kind == "soft":
        target = draw(st.sampled_from(["/nowhere", f"/{key}", "/" + draw(st.sampled_from(KEYS)), "grp", "/a/b/c"]))
        group = draw(st.booleans())

        def soft(f, root):
            if group:
                f.require_group("grp")
            _set(f, key, h5py.SoftLink(target))
        return f"soft {target}", soft
    if kind == "external":
        name = draw(st.sampled_from(["base.h5", "missing.h5"]))
        return f"external {name}", lambda f, root: _set(f, key, h5py.ExternalLink(str(root / name), f"/{key}"))
    if kind in ("dtype", "unwritten"):
        shape = draw(st.one_of(st.just(ARRAYS[key].shape), st.lists(st.sampled_from(SIZES), max_size=4).map(tuple)))
        dt = _dtype(draw(st.sampled_from(DTYPES)))
        return f"{kind} {shape} {dt}", _dataset(key, shape, dt, written=kind == "dtype")
    if kind == "values":
        value, where = draw(st.sampled_from(ODD_VALUES)), draw(st.floats(0, 1, exclude_max=True))
        return f"values {value}", _values(key, value, where)
    if kind in ("huge", "huge_all"):
        rows, auto = draw(st.sampled_from(HUGE)), draw(st.booleans())
        keys = [k for k in KEYS if k in ROWS] if kind == "huge_all" else [key]
        return f"{kind} {rows}", _huge(keys, rows, auto)
    if kind == "external_storage":
        return kind, _external_storage(key)
    if kind == "virtual":
        return kind, _virtual(key)
    if kind == "group":
        return kind, lambda f, root: (_remove(f, key), f.create_group(key))
    name = draw(st.sampled_from(["format_version", "subject_params", "ambient", "note"]))
    value = draw(st.sampled_from([7, -1, 2.5, np.nan, "text", '{"identity": [1]}', b"\xff\xfe", True,
                                  np.zeros(3), np.zeros(2, [("a", "f4")]), np.array(["a", "b"], dtype="S1")]))
    return f"attr {name}={value!r}", lambda f, root: f.attrs.__setitem__(name, value)


def _dataset(key, shape, dt, written):
    def edit(f, root):
        if written and dt.kind in "biufcS" and not dt.names and int(np.prod(shape)) <= 200_000:
            _put(f, key, data=np.zeros(shape, dt))
        else:
            _put(f, key, shape=shape, dtype=dt)
    return edit


def _values(key, value, where):
    def edit(f, root):
        a, v = np.array(ARRAYS[key]), value
        if a.dtype.kind in "iu":  # integers: the value, within int64, into an int64 copy
            if not np.isfinite(v):
                return
            a, v = a.astype(np.int64), int(max(min(v, 2**62), -(2**62)))
        a.reshape(-1)[int(where * a.size)] = v
        _put(f, key, data=a)
    return edit


def _huge(keys, rows, auto):
    def edit(f, root):
        for k in keys:
            tail = ARRAYS[k].shape[1:]
            _put(f, k, shape=(rows,) + tail, dtype=ARRAYS[k].dtype, chunks=True if auto else (1,) + tail,
                 compression="gzip")
    return edit


def _external_storage(key):
    def edit(f, root):
        a = ARRAYS[key]
        _put(f, key, shape=a.shape, dtype=a.dtype, external=[(str(root / "outside.bin"), 0, a.nbytes)])
    return edit


def _virtual(key):
    def edit(f, root):
        a = ARRAYS[key]
        layout = h5py.VirtualLayout(shape=a.shape, dtype=a.dtype)
        layout[:] = h5py.VirtualSource(str(root / "base.h5"), key, shape=a.shape)
        _remove(f, key)
        f.create_virtual_dataset(key, layout)
    return edit


# ---------------------------------------------------------------- the readers


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


def _readers(p: Path):
    from geometry.fit_dataset import read_subject
    from train.data.__main__ import summarize
    from train.data.dataset import GazeDataset
    from train.data.format import validate_subject_file

    def dataset_rows():
        ds = GazeDataset(p, with_mesh=True)
        try:
            for i in sorted({0, len(ds) // 2, len(ds) - 1}):
                ds[i]
        finally:
            ds.close()

    return {"validate": lambda: validate_subject_file(p), "dataset": dataset_rows,
            "inspect": lambda: summarize(p, validate_subject_file(p)), "geometry": lambda: read_subject(p)}


def _accepts_or_refuses(p: Path, what: str) -> None:
    previous = signal.signal(signal.SIGALRM, _alarm)
    try:
        for name, read in _readers(p).items():
            signal.alarm(SECONDS)
            try:
                read()
            except ToolkitError as e:
                assert "\n" not in str(e) and str(e), f"{name} on {what}: not one line: {e!r}"
            except _Hang:
                raise AssertionError(f"{name} on {what}: still running after {SECONDS} s") from None
            except Exception as e:  # noqa: BLE001 -- the property: nothing but ToolkitError
                raise AssertionError(f"{name} on {what}: {type(e).__name__}: {e}") from e
            finally:
                signal.alarm(0)
    finally:
        signal.signal(signal.SIGALRM, previous)


def _edited(work, chosen) -> Path:
    base, p = work
    p.write_bytes(base.read_bytes())
    with h5py.File(p, "r+") as f:
        for _, edit in chosen:
            edit(f, base.parent)
    return p


@given(st.lists(edits(), min_size=1, max_size=3))
def test_edited_subject_files_are_read_or_refused(work, chosen):
    p = _edited(work, chosen)
    _accepts_or_refuses(p, "; ".join(name for name, _ in chosen))


@given(st.lists(edits(), max_size=2), st.one_of(st.none(), st.floats(0, 1, exclude_max=True)),
       st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 7)), max_size=8))
def test_truncated_and_bit_flipped_files_are_read_or_refused(work, chosen, keep, flips):
    p = _edited(work, chosen)
    data = bytearray(p.read_bytes())
    for where, bit in flips:
        data[int(where * len(data))] ^= 1 << bit
    if keep is not None:
        data = data[: int(keep * len(data))]
    p.write_bytes(bytes(data))
    _accepts_or_refuses(p, f"{[n for n, _ in chosen]}, keep {keep}, flips {flips}")


@given(st.sampled_from([k for k in KEYS if k in ROWS]), st.lists(st.sampled_from(HUGE), min_size=1, max_size=4),
       st.booleans())
def test_huge_declared_shapes_in_chunked_storage_are_refused_quickly(work, key, dims, all_keys):
    """Shapes of up to 2^55 rows or columns in a file of a few KB: refused (or read, when small) fast."""
    tail = tuple(dims[1:]) if len(dims) > 1 else ARRAYS[key].shape[1:]
    rows = dims[0]
    assume(rows * math.prod(tail) * ARRAYS[key].dtype.itemsize < 2**62)  # HDF5 sizes are 64-bit

    def edit(f, root):
        for k in [k for k in KEYS if k in ROWS] if all_keys else [key]:
            t = tail if k == key else ARRAYS[k].shape[1:]
            chunks = tuple(min(d, 64) or 1 for d in (rows,) + t)
            _put(f, k, shape=(rows,) + t, dtype=ARRAYS[k].dtype, chunks=chunks, compression="gzip")
    p = _edited(work, [("huge", edit)])
    assert p.stat().st_size < 1 << 20
    _accepts_or_refuses(p, f"{key} {(rows,) + tail}, all keys {all_keys}")
