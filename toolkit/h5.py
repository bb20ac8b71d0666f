"""Bounded reading of HDF5 files: every reader of the project's subject files (validation, ``GazeDataset``,
``train.data inspect``, ``geometry fit``) opens files with :func:`open_h5` and datasets with :func:`h5_dataset`,
and reads through :func:`read_array` / :func:`read_selection`, so a forged or damaged file is one
``ToolkitError`` naming the file and key.

Refused: links that leave the file (external links) or do not resolve, loops and chains longer than
:data:`MAX_LINK_HOPS`; external and virtual storage (a "dataset" that reads another file); non-numeric dtypes;
contiguous datasets that declare more bytes than they store. What a read allocates is checked against the
memory budget (``toolkit.limits``) and the HDF5 chunks it visits against :data:`MAX_CHUNK_READS`, before it reads.
"""

from __future__ import annotations

import contextlib
import math
import os
import posixpath

import numpy as np

from toolkit.errors import ToolkitError, one_line

MAX_LINK_HOPS = 8
"""Soft links followed from one key (HDF5's own limit is 16; a longer chain is a loop or a forgery)."""

MAX_ATTR_BYTES = 1 << 16
"""Bytes of one file attribute: attributes hold short text and numbers (the generator's are < 2 KiB)."""

MAX_CHUNK_READS = 1 << 20
"""HDF5 chunks one whole-dataset read may visit (~10 µs each, written or not: ~10 s). Chunked storage of a few
KB can declare millions of one-row chunks, whose reading would take hours while the memory bound allows it."""

MAX_ROW_CHUNKS = 1 << 12
"""HDF5 chunks one row may span (the writer stores one chunk a row; h5py's automatic chunks span tens)."""

NUMERIC_KINDS = "biufc"
READ_ERRORS = (OSError, RuntimeError, ValueError, TypeError, KeyError)
"""What h5py raises on a damaged file: HDF5 errors come as OSError or RuntimeError, a few as the others."""


@contextlib.contextmanager
def open_h5(path: str | os.PathLike):
    """Open an HDF5 file read-only, turning unreadable / truncated files into a ToolkitError."""
    import h5py

    from toolkit.io import check_readable_file

    path = check_readable_file(path, "HDF5 file")
    try:
        f = h5py.File(path, "r")
    except READ_ERRORS as e:
        raise ToolkitError(f"{path}: not a readable HDF5 file (truncated or corrupt?): {one_line(e, 300)}") from e
    try:
        yield f
    except (OSError, RuntimeError) as e:  # HDF5's own errors from a damaged file, wherever the block met them
        raise ToolkitError(f"{path}: cannot read (truncated or corrupt?): {one_line(e, 300)}") from e
    finally:
        f.close()


def has_key(path, f, key: str) -> bool:
    """Whether the file has a link named ``key`` (resolving or not: :func:`h5_dataset` says which)."""
    try:
        return f.get(key, getlink=True) is not None
    except READ_ERRORS as e:
        raise ToolkitError(f"{path}: cannot look up key '{key}' (truncated or corrupt?): {one_line(e, 300)}") from e


class _Unresolved(Exception):
    pass


class _External(Exception):
    pass


def _walk(f, name: str, hops: int):
    """The object at absolute HDF5 path ``name``, one link at a time: h5py would follow external links (which
    open any file on the machine) and report a dangling soft link as a bare KeyError."""
    import h5py

    obj, parts = f, [p for p in name.split("/") if p not in ("", ".")]
    for i, part in enumerate(parts):
        here = "/" + "/".join(parts[: i + 1])
        if not isinstance(obj, h5py.Group):
            raise _Unresolved(f"'{posixpath.dirname(here)}' is not a group")
        link = obj.get(part, getlink=True)
        if link is None:
            raise _Unresolved(f"'{here}' does not exist")
        if isinstance(link, h5py.ExternalLink):
            raise _External(f"'{link.path}' in {link.filename}")
        if isinstance(link, h5py.SoftLink):
            if hops >= MAX_LINK_HOPS:
                raise _Unresolved(f"soft links nest deeper than {MAX_LINK_HOPS}: a loop?")
            target = link.path if link.path.startswith("/") else posixpath.join(posixpath.dirname(here), link.path)
            obj = _walk(f, target, hops + 1)
        elif isinstance(link, h5py.HardLink):
            obj = obj[part]
        else:
            raise _Unresolved(f"'{here}' is a user-defined link")
    return obj


def dtype_name(dt: np.dtype) -> str:
    """A dtype as a user reads it: strings, compounds and variable-length sequences by name."""
    import h5py

    if dt.names:
        return "compound (" + ", ".join(dt.names)[:80] + ")"
    if h5py.check_string_dtype(dt) is not None:
        info = h5py.check_string_dtype(dt)
        return "variable-length string" if info.length is None else f"fixed-length string ({dt})"
    if h5py.check_vlen_dtype(dt) is not None:
        return f"variable-length sequences of {h5py.check_vlen_dtype(dt)}"
    if dt.subdtype is not None:
        return f"array type {dt.subdtype[0]}{list(dt.subdtype[1])}"
    if dt.kind == "O":
        return "object reference"
    return str(dt)


def h5_dataset(path, f, key: str, kinds: str = NUMERIC_KINDS, expected: str = "numbers"):
    """The dataset at ``key``, refused (one ToolkitError naming file and key) when it is missing, a link that
    does not resolve inside the file, an external link, not a dataset, stored outside the file (external
    storage, virtual), empty, not of the dtype ``kinds`` (named ``expected``), or a contiguous dataset that stores fewer bytes than its
    shape declares (truncated, or a forged shape that would make a reader allocate for data it does not hold)."""
    import h5py

    try:
        link = f.get(key, getlink=True)
        if link is None:
            raise ToolkitError(f"{path}: missing key '{key}'")
        obj = _walk(f, "/" + key, 0)
    except _External as e:
        how = "is" if isinstance(link, h5py.ExternalLink) else "leads through"
        raise ToolkitError(f"{path}: key '{key}' {how} an external link to {e}; expected data stored in this file "
                           "(external links are not followed)") from None
    except _Unresolved as e:
        raise ToolkitError(f"{path}: key '{key}' is a soft link to '{link.path}', which does not resolve "
                           f"({e})") from None
    except READ_ERRORS as e:
        raise ToolkitError(f"{path}: key '{key}' cannot be opened (truncated or corrupt?): {one_line(e, 300)}") from e
    if not isinstance(obj, h5py.Dataset):
        raise ToolkitError(f"{path}: key '{key}' is a {type(obj).__name__}, expected a dataset of rows")
    try:
        _check_storage(path, key, obj, kinds, expected)
    except READ_ERRORS as e:
        raise ToolkitError(f"{path}: key '{key}' cannot be opened (truncated or corrupt?): {one_line(e, 300)}") from e
    return obj


def _check_storage(path, key: str, ds, kinds: str, expected: str) -> None:
    import h5py

    from toolkit.limits import check_declared_size

    plist = ds.id.get_create_plist()
    if plist.get_layout() == h5py.h5d.VIRTUAL:
        raise ToolkitError(f"{path}: key '{key}' is a virtual dataset (its data are mapped from other files); "
                           "expected data stored in this file")
    if plist.get_external_count():
        raise ToolkitError(f"{path}: key '{key}' keeps its data in another file (HDF5 external storage); "
                           "expected data stored in this file")
    if ds.shape is None:
        raise ToolkitError(f"{path}: key '{key}' has no data (an empty dataspace), expected an array")
    dt = ds.dtype
    if dt.kind not in kinds or dt.subdtype is not None:
        raise ToolkitError(f"{path}: key '{key}' has dtype {dtype_name(dt)}, expected {expected}")
    declared = math.prod(ds.shape) * dt.itemsize
    if plist.get_layout() == h5py.h5d.CONTIGUOUS:
        # Compressed data must be chunked, so contiguous data are stored whole: less is a truncated file or a
        # forged shape. (Chunked data may be smaller than declared: constant rows compress to almost nothing.)
        stored = ds.id.get_storage_size()
        if stored < declared:
            raise ToolkitError(f"{path}: key '{key}' declares {declared} bytes ({list(ds.shape)} {dt}) but stores "
                               f"{stored} (truncated, never written, or a forged shape)")
        check_declared_size(path, declared, f"key '{key}'")


def row_nbytes(ds) -> int:
    """Bytes that reading one row of ``ds`` allocates: the row, or the chunk HDF5 decompresses to get it."""
    row = math.prod(ds.shape[1:]) * ds.dtype.itemsize
    chunk = math.prod(ds.chunks) * ds.dtype.itemsize if ds.chunks else 0
    return max(row, chunk)


def chunk_count(ds, whole: bool = True) -> int:
    """HDF5 chunks that reading all of ``ds`` (``whole``) or one of its rows visits; 0 when not chunked."""
    if not ds.chunks:
        return 0
    dims = zip(ds.shape, ds.chunks, strict=True) if whole else zip(ds.shape[1:], ds.chunks[1:], strict=True)
    return math.prod(-(-n // c) for n, c in dims)


def check_chunk_reads(path, what: str, chunks: int) -> None:
    if chunks > MAX_CHUNK_READS:
        raise ToolkitError(f"{path}: {what} would visit {chunks} HDF5 chunks, more than {MAX_CHUNK_READS} (chunks "
                           "too small for this many rows, or a forged row count; rewrite the file with larger chunks)")


def read_selection(path, key: str, ds, sel=()) -> np.ndarray:
    """``ds[sel]`` as an array, a damaged file's error as one ToolkitError. The caller bounded its size."""
    try:
        return np.asarray(ds[sel])
    except READ_ERRORS as e:
        where = f" row {sel}" if isinstance(sel, (int, np.integer)) else ""
        raise ToolkitError(f"{path}: key '{key}'{where} cannot be read (truncated or corrupt?): {one_line(e, 300)}") from e


def read_array(path, f, key: str, *, copies: int = 1) -> np.ndarray:
    """The whole dataset ``key`` (checked by :func:`h5_dataset`), after bounding what it allocates with
    ``check_allocation``; ``copies``: how many arrays of its size the caller derives from it."""
    from toolkit.limits import check_allocation

    ds = h5_dataset(path, f, key)
    rows = f"{ds.shape[0]} rows" if ds.shape else "its value"
    check_allocation(math.prod(ds.shape) * ds.dtype.itemsize * copies, f"{path}: key '{key}': reading {rows}")
    check_chunk_reads(path, f"key '{key}': reading {rows}", chunk_count(ds))
    return read_selection(path, key, ds)
