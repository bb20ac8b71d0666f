"""Forged and malformed subject files: links, external storage, forged shapes, odd dtypes and attributes.

Every reader of subject files (validation, GazeDataset, ``train.data inspect``'s summary, ``geometry fit``'s
reader) refuses each with one ToolkitError naming the file and key, before reading rows into memory."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from tests.train.data.tiny_subject import (
    edited_copy,
    huge_rows,
    link_key,
    replace_key,
    tiny_rows,
    write_tiny_subject,
)
from toolkit.errors import ToolkitError
from train.data.dataset import GazeDataset
from train.data.format import validate_subject_file


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return write_tiny_subject(tmp_path_factory.mktemp("tiny") / "base.h5")


def _mutated(base, tmp_path, edit, name="bad.h5"):
    return edited_copy(base, tmp_path / name, edit)


_replace, _link = replace_key, link_key


def _readers(p):
    """Each reader of a subject file, called on ``p``."""
    from geometry.fit_dataset import read_subject
    from train.data.__main__ import summarize

    def inspect_summary():
        summarize(p, validate_subject_file(p))

    return {"validate": lambda: validate_subject_file(p), "dataset": lambda: GazeDataset(p, with_mesh=True)[0],
            "inspect": inspect_summary, "geometry": lambda: read_subject(p)}


def _assert_refused(p, match, readers=("validate", "dataset", "inspect", "geometry")):
    for name in readers:
        with pytest.raises(ToolkitError, match=match) as e:
            _readers(p)[name]()
        msg = str(e.value)
        assert str(p) in msg and "\n" not in msg, (name, msg)


def test_the_tiny_base_file_is_valid(base):
    for call in _readers(base).values():
        call()


@pytest.mark.parametrize("key", ["pose", "head_mask", "w2c_Rmat"])
def test_a_dangling_soft_link_is_refused(base, tmp_path, key):
    p = _mutated(base, tmp_path, _link(key, h5py.SoftLink("/nowhere")))
    _assert_refused(p, rf"key '{key}' is a soft link to '/nowhere', which does not resolve")


def test_soft_link_loops_are_refused(base, tmp_path):
    p = _mutated(base, tmp_path, _link("pose", h5py.SoftLink("/pose")))
    _assert_refused(p, r"key 'pose' is a soft link .* (does not resolve|nest)")


def test_a_soft_link_that_resolves_inside_the_file_is_read(base, tmp_path):
    def edit(f):
        f.move("pose", "moved_pose")
        f["pose"] = h5py.SoftLink("/moved_pose")
    p = _mutated(base, tmp_path, edit)
    assert validate_subject_file(p)["n"] == 4
    assert GazeDataset(p)[1]["pose"].shape == (6,)


@pytest.mark.parametrize("target_exists", [False, True])
def test_external_links_are_refused(base, tmp_path, target_exists):
    other = tmp_path / "other.h5"
    if target_exists:
        with h5py.File(other, "w") as g:
            g["pose"] = np.zeros((4, 6), np.float32)
    p = _mutated(base, tmp_path, _link("pose", h5py.ExternalLink(str(other), "/pose")))
    _assert_refused(p, r"key 'pose' is an external link to .*other\.h5.*expected data stored in this file")


def test_a_soft_link_through_an_external_link_is_refused(base, tmp_path):
    def edit(f):
        f["ext"] = h5py.ExternalLink(str(base), "/")
        del f["pose"]
        f["pose"] = h5py.SoftLink("/ext/pose")
    p = _mutated(base, tmp_path, edit)
    _assert_refused(p, r"key 'pose' .*external link")


def test_external_storage_is_refused(base, tmp_path):
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.zeros((4, 6), np.float32).tobytes())
    p = _mutated(base, tmp_path, _replace("pose", shape=(4, 6), dtype=np.float32, external=[(str(secret), 0, 96)]))
    _assert_refused(p, r"key 'pose' keeps its data in another file \(HDF5 external storage\)")


def test_virtual_datasets_are_refused(base, tmp_path):
    layout = h5py.VirtualLayout(shape=(4, 6), dtype=np.float32)
    layout[:] = h5py.VirtualSource(str(base), "pose", shape=(4, 6))

    def edit(f):
        del f["pose"]
        f.create_virtual_dataset("pose", layout)
    p = _mutated(base, tmp_path, edit)
    _assert_refused(p, r"key 'pose' is a virtual dataset")


def test_contiguous_data_shorter_than_declared_is_refused(base, tmp_path):
    p = _mutated(base, tmp_path, _replace("latent_codes", shape=(4, 144), dtype=np.float32))  # never written
    _assert_refused(p, r"key 'latent_codes' declares 2304 bytes .* stores 0", ("validate", "dataset", "inspect"))


def test_millions_of_declared_rows_are_refused_before_reading_them(base, tmp_path, monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "1")
    p = _mutated(base, tmp_path, huge_rows(20_000_000))
    assert p.stat().st_size < 200_000
    _assert_refused(p, r"20000000 rows.* would allocate .* more than the memory budget")


def test_millions_of_tiny_chunks_are_refused_before_visiting_them(base, tmp_path, monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "64")  # memory would allow it: the time would not
    p = _mutated(base, tmp_path, huge_rows(100_000))
    _assert_refused(p, r"reading the labels of 100000 rows would visit \d+ HDF5 chunks, more than 1048576",
                    ("validate", "dataset"))


def test_a_row_spread_over_many_chunks_is_refused(base, tmp_path):
    p = _mutated(base, tmp_path, _replace("face_patch", shape=(4, 128, 128, 3), dtype=np.uint8, chunks=(1, 1, 1, 1)))
    _assert_refused(p, r"key 'face_patch': one row spans 49152 HDF5 chunks", ("validate", "dataset"))


def test_a_huge_row_is_refused_before_reading_one(base, tmp_path, monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "1")
    p = _mutated(base, tmp_path, _replace("vertice", shape=(4, 100_000_000, 3), dtype=np.float32,
                                          chunks=(1, 1 << 20, 3), compression="gzip"))
    _assert_refused(p, r"key 'vertice'.* would allocate .* more than the memory budget", ("validate", "dataset"))


@pytest.mark.parametrize("key,kw,match", [
    ("pose", dict(data=np.array([b"abc"] * 4)), r"key 'pose' has dtype .*string.*expected float"),
    ("pose", dict(data=np.array(["abc"] * 4, dtype=h5py.string_dtype())), r"key 'pose' has dtype .*string"),
    ("pose", dict(data=np.zeros(4, [("a", "f4"), ("b", "i4")])), r"key 'pose' has dtype compound"),
    ("pose", dict(shape=(4,), dtype=h5py.vlen_dtype(np.float32)), r"key 'pose' has dtype variable-length"),
    ("cam_index", dict(data=np.zeros(4, bool)), r"key 'cam_index' has dtype bool, expected integer"),
    ("pose", dict(data=np.zeros((4, 6), np.complex64)), r"key 'pose' has dtype complex64, expected float"),
    ("pose", dict(data=np.float32(0)), r"key 'pose' has shape \[\], expected \[N, 6\]"),
    ("pose", dict(data=h5py.Empty(np.float32)), r"key 'pose' has no data"),
    ("pose", dict(data=np.zeros((4, 6, 1), np.float32)), r"key 'pose' has shape \[4, 6, 1\]"),
    ("face_patch", dict(data=np.zeros((4, 0, 24, 3), np.uint8)), r"key 'face_patch' has H = 0, expected"),
    ("vertice", dict(data=np.zeros((4, 0, 3), np.float32)), r"key 'vertice' has V = 0, expected"),
    ("pitchyaw_cam", dict(data=np.full((4, 2), np.inf, np.float32)), r"key 'pitchyaw_cam' contains NaN or inf"),
    ("light_dir", dict(data=np.full((3, 3), 0.5, np.float32)), r"key 'light_dir' has 3 rows, face_patch has 4"),
    ("cam_index", dict(data=np.full(4, 2**64 - 1, np.uint64)), r"key 'cam_index' has values above 2147483647"),
])
def test_wrong_dtypes_ranks_and_values_are_named(base, tmp_path, key, kw, match):
    p = _mutated(base, tmp_path, _replace(key, **kw))
    _assert_refused(p, match, ("validate", "dataset"))


def test_a_group_where_a_dataset_belongs(base, tmp_path):
    def edit(f):
        del f["pose"]
        f.create_group("pose")
    _assert_refused(_mutated(base, tmp_path, edit), r"key 'pose' is a Group, expected a dataset")


def test_a_row_with_nan_vertices_is_named_when_read(base, tmp_path):
    v = tiny_rows()["vertice"]
    v[2, 1, 0] = np.nan
    p = _mutated(base, tmp_path, _replace("vertice", data=v))
    ds = GazeDataset(p, with_mesh=True)
    ds[1]
    with pytest.raises(ToolkitError, match=r"bad\.h5: key 'vertice' row 2 contains NaN or inf"):
        ds[2]


@pytest.mark.parametrize("key,value,match", [
    ("neutral_vertice", np.full((5, 3), np.nan, np.float32), r"key 'neutral_vertice' contains NaN"),
    ("neutral_vertice", np.zeros((5, 2), np.float32), r"key 'neutral_vertice' has shape \[5, 2\], expected \[V, 3\]"),
    ("mesh_faces", np.array([[0, 1, 9]], np.int32), r"key 'mesh_faces' has vertex indices outside \[0, 5\)"),
    ("mesh_faces", np.zeros((2, 3), np.float32), r"key 'mesh_faces' has dtype float32, expected integer"),
    ("eyeball_radii", np.array([0.01, -1], np.float32), r"key 'eyeball_radii' has non-positive"),
])
def test_subject_level_arrays_are_checked(base, tmp_path, key, value, match):
    p = _mutated(base, tmp_path, _replace(key, data=value))
    _assert_refused(p, match, ("validate", "dataset"))
    if key in ("neutral_vertice", "mesh_faces"):  # the ground truth geometry fit compares with (its own words)
        _assert_refused(p, rf"bad\.h5: .*{key}", ("geometry",))


@pytest.mark.parametrize("name,value,match", [
    ("subject_params", 5, r"attribute 'subject_params' .*expected JSON text"),
    ("subject_params", "{not json", r"attribute 'subject_params' .*expected JSON text"),
    ("subject_params", '{"identity": [1, 2]}', r"attribute 'subject_params'.*22 finite numbers"),
    ("ambient", "bright", r"attribute 'ambient' .*expected a number in \[0, 1\]"),
    ("ambient", np.nan, r"attribute 'ambient' .*expected a number in \[0, 1\]"),
    ("format_version", 99, r"attribute 'format_version' is 99, expected an integer in \[1, 1\]"),
    ("format_version", "1", r"attribute 'format_version' is '1', expected an integer"),
    ("note", np.zeros(2, [("a", "f4"), ("b", "i4")]), r"attribute 'note' has type compound"),
    ("note", np.zeros(70000, np.uint8), r"attribute 'note' holds 70000 bytes"),
    ("note", b"\xff\xfe", r"attribute 'note' is not UTF-8 text"),
])
def test_attributes_of_wrong_types(base, tmp_path, name, value, match):
    p = tmp_path / "bad.h5"
    with h5py.File(base, "r") as src, h5py.File(p, "w", libver="latest") as f:  # latest: attributes over 64 KiB
        for k in src:
            src.copy(src[k], f)
        f.attrs.update(src.attrs)
        f.attrs[name] = value
    _assert_refused(p, match, ("validate", "dataset"))


def test_truncated_copies_are_one_error(base, tmp_path):
    data = base.read_bytes()
    for cut in (len(data) // 5, len(data) // 2, len(data) - 100):
        p = tmp_path / f"cut{cut}.h5"
        p.write_bytes(data[:cut])
        _assert_refused(p, r"(truncated|corrupt)")
