"""Property tests of the scene readers: 3DGS PLY (ASCII and binary), safetensors scenes and checkpoints.

- Any file, well formed, mutated (byte flips, truncations, insertions, header edits) or with a random header:
  the reader returns a valid scene (or state dict) or raises one ``ToolkitError`` line naming the file; never
  another exception. A scene it accepts is written back by the same format's writer and reads back equal
  (whatever the reader takes, the writer can write).
- Any scene (0 Gaussians included, feature widths 0..5, SH degrees none and 0..3, JSON metadata with any
  characters) written as PLY or safetensors, or converted by ``python -m toolkit convert``, reads back the
  same tensors and metadata.

The memory budget is set to 1 GiB here, so that a forged count that slipped past the size checks would be
refused loudly rather than allocated.
"""

from __future__ import annotations

import functools
import json
import os
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tests.conftest import random_scene
from tests.toolkit.test_scene import _assert_scene_equal
from toolkit.errors import ToolkitError
from toolkit.io import load_checkpoint, load_state_dict_file, save_checkpoint
from toolkit.ply import read_ply_vertices
from toolkit.scene import FORMAT_NAME, FORMAT_VERSION, GaussianScene


@pytest.fixture(autouse=True, scope="module")
def _small_memory_budget():
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DITGAZE_MEMORY_GB", "1")
        yield


# ---------------------------------------------------------------------------------------------- valid files
@functools.cache
def binary_ply() -> bytes:
    """Our binary PLY of a small scene with SH degree 1, eye metadata and every part label."""
    s = random_scene(6, d=3, sh_degree=1, seed=3)
    s.metadata["eyes"] = {"left": {"center": [0.0, 0.0, 0.0], "radius": 0.01}}
    with tempfile.TemporaryDirectory() as tmp:
        s.to_ply(Path(tmp) / "s.ply")
        return (Path(tmp) / "s.ply").read_bytes()


@functools.cache
def ascii_ply() -> bytes:
    """The same file in ASCII (float32 values printed exactly)."""
    head, _ = binary_ply().split(b"end_header\n", 1)
    head = head.replace(b"format binary_little_endian 1.0", b"format ascii 1.0")
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "s.ply").write_bytes(binary_ply())
        cols, _ = read_ply_vertices(Path(tmp) / "s.ply")
    rows = np.stack(list(cols.values()), 1).astype(np.float32)
    body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in rows)
    return head + b"end_header\n" + body.encode()


@functools.cache
def scene_safetensors() -> bytes:
    s = random_scene(6, d=4, sh_degree=0, seed=4)
    with tempfile.TemporaryDirectory() as tmp:
        s.save(Path(tmp) / "s.safetensors")
        return (Path(tmp) / "s.safetensors").read_bytes()


@functools.cache
def checkpoint_safetensors() -> bytes:
    g = torch.Generator().manual_seed(5)
    state = {"enc.weight": torch.randn(4, 3, generator=g), "enc.bias": torch.zeros(4, dtype=torch.float16),
             "step": torch.tensor(7), "mask": torch.ones(2, 2, dtype=torch.bool)}
    with tempfile.TemporaryDirectory() as tmp:
        save_checkpoint(Path(tmp) / "c.safetensors", state, {"step": 7, "config": {"lr": 1e-3, "name": "x"}})
        return (Path(tmp) / "c.safetensors").read_bytes()


@functools.cache
def checkpoint_pt() -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        torch.save({"w": torch.arange(6.0).reshape(2, 3), "b": torch.zeros(2)}, Path(tmp) / "c.pt")
        return (Path(tmp) / "c.pt").read_bytes()


def header_end(data: bytes) -> int:
    """Bytes of a PLY's header, or of a safetensors' length and JSON header: where edits matter most."""
    if data.startswith(b"ply"):
        return data.index(b"end_header\n") + len("end_header\n")
    return 8 + struct.unpack("<Q", data[:8])[0] if len(data) >= 8 else len(data)


# ---------------------------------------------------------------------------------------------- mutations
@st.composite
def mutated(draw, base: bytes) -> bytes:
    """``base`` with 1-4 byte edits, each in the header or in the body (most truncations in the body: one in
    the header only ever loses end_header)."""
    data, head = bytearray(base), header_end(base)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "set", "truncate", "insert", "delete", "digit"]))
        in_body = draw(st.sampled_from([True, True, True, False] if op == "truncate" else [True, False]))
        lo, hi = (head, len(data) - 1) if in_body else (0, min(head, len(data)) - 1)
        if hi < lo:
            continue
        at = draw(st.integers(lo, hi))
        if op == "flip":
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "set":
            data[at] = draw(st.sampled_from([0, 0x0A, 0x20, 0x39, 0x7F, 0x80, 0xFF]))
        elif op == "truncate":
            del data[at:]
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[at:at + draw(st.integers(1, 16))]
        else:  # a digit: counts and lengths are where a forged file hurts
            data[at] = ord(draw(st.sampled_from("0123456789")))
    return bytes(data)


PLY_LINES = [
    "element vertex 20000000", "element vertex 0", "element vertex 99999999999999999999", "element face 3",
    "element vertex -1", "element vertex", "property float f_rest_abc", "property float f_rest_7",
    "property float feat_9", "property half x", "property double opacity", "property uchar part",
    "property list uchar int vertex_indices", "property float x", "format ascii 1.0",
    "format binary_big_endian 1.0", "format binary_little_endian 1.0", "format weird 1.0", "comment ditgaze [1]",
    'comment ditgaze {"has_sh": 3}', 'comment ditgaze {"feature_dim": 99}', "comment ditgaze " + "[" * 3000,
    'comment ditgaze {"eyes": {"left": {"center": [0, 0], "radius": -1}}}', "end_header", "obj_info x",
    "ply", "", "comment \u00e9t\u00e9",
]


@st.composite
def edited_ply_header(draw, base: bytes) -> bytes:
    """``base`` with header lines deleted, duplicated, swapped or replaced by lines a forger would write."""
    head, body = base.split(b"\nend_header\n", 1)
    lines = head.decode().split("\n")
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["replace", "insert", "delete", "duplicate", "swap", "retype"]))
        if op == "replace":
            lines[i] = draw(st.sampled_from(PLY_LINES))
        elif op == "insert":
            lines.insert(i, draw(st.one_of(st.sampled_from(PLY_LINES), st.text(max_size=20))))
        elif op == "delete" and len(lines) > 1:
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif lines[i].startswith("property "):
            lines[i] = "property " + draw(st.sampled_from(["double", "uchar", "int", "short", "char"])) + " " + \
                lines[i].split()[-1]
    return "\n".join(lines).encode("utf-8", "surrogatepass") + b"\nend_header\n" + body


GAUSSIAN_PROPERTIES = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


@st.composite
def random_ply(draw) -> bytes:
    """A header built from PLY-like lines (most of a Gaussian's properties, in any order and type) over a random
    body: ASCII numbers, or bytes of about the size the header declares."""
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
    n = draw(st.integers(0, 4))
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {n}"]
    extra = ["f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0", "f_rest_1", "f_rest_2", "feat_0", "feat_1", "part", "nx"]
    names = draw(st.permutations(GAUSSIAN_PROPERTIES + draw(st.lists(st.sampled_from(extra), unique=True))))
    names = names[:draw(st.integers(len(names) - 2, len(names)))]
    types = {"float": 4, "double": 8, "uchar": 1, "int": 4}
    kinds = [draw(st.sampled_from(sorted(types))) for _ in names]
    lines += [f"property {k} {name}" for k, name in zip(kinds, names)]
    lines += draw(st.lists(st.sampled_from(PLY_LINES), max_size=2))
    row = sum(types[k] for k in kinds)
    body = draw(st.one_of(
        st.binary(min_size=max(n * row - 2, 0), max_size=n * row + 2),
        st.lists(st.floats(width=32) | st.integers(0, 2), min_size=n * len(names), max_size=n * len(names) + 1).map(
            lambda v: "\n".join(" ".join(map(repr, v[i:i + len(names)])) for i in range(0, len(v), len(names) or 1))
            .encode())))
    return ("\n".join(lines) + "\nend_header\n").encode() + body


SAFETENSORS_DTYPES = ["F32", "F16", "BF16", "F64", "I8", "U8", "I16", "I32", "I64", "U16", "U32", "U64", "BOOL",
                      "F8_E4M3", "F8_E5M2", "F8_E8M0", "F6_E2M3", "F4", "C64", "XX", ""]
JSON_ODDITIES = ["[1, 2]", '"text"', "5", "null", "{not json", "[" * 3000, '{"a": ' + "9" * 5000 + "}",
                 json.dumps({"format": FORMAT_NAME, "format_version": True}),
                 json.dumps({"format": FORMAT_NAME, "format_version": 99}),
                 json.dumps({"format": FORMAT_NAME, "format_version": 1, "eyes": [1, 2]}),
                 json.dumps({"format": FORMAT_NAME, "format_version": 1, "eyes": {"right": {"center": "x"}}}),
                 json.dumps({"format": FORMAT_NAME, "format_version": 1, "eyes": {"left": {"center": [0, 0, 0],
                                                                                          "radius": 0.01}}})]
shapes = st.lists(st.one_of(st.integers(0, 8), st.sampled_from([-1, 2**31, 2**62, 2**64])), max_size=4)


@st.composite
def edited_safetensors_header(draw, base: bytes) -> bytes:
    """``base`` with its JSON header edited: a tensor's dtype, shape or byte range, the metadata, a new entry,
    a deleted one; the length prefix right or wrong."""
    n = struct.unpack("<Q", base[:8])[0]
    header, body = json.loads(base[8:8 + n]), base[8 + n:]
    names = [k for k in header if k != "__metadata__"]
    for _ in range(draw(st.integers(1, 2))):
        name = draw(st.sampled_from(names))
        entry = header.setdefault(name, {})  # dropped by an earlier edit: an entry with only what is set now
        # Edits the library lets through (a consistent retype, metadata) first and twice: they reach our checks.
        op = draw(st.sampled_from(["retype", "meta", "retype", "meta", "dtype", "shape", "offsets", "meta_value",
                                   "drop", "add"]))
        span = entry.get("data_offsets")
        if op == "retype" and isinstance(span, list) and len(span) == 2:  # right byte size: a wrong tensor
            nbytes = max(span[1] - span[0], 0)
            dtype, size = draw(st.sampled_from([("F32", 4), ("F16", 2), ("BF16", 2), ("F64", 8), ("I8", 1), ("U8", 1),
                                                 ("I32", 4), ("I64", 8), ("BOOL", 1), ("F8_E4M3", 1)]))
            numel = nbytes // size
            rows = draw(st.sampled_from([r for r in range(1, 13) if numel % r == 0] or [1]))
            entry["dtype"] = dtype
            entry["shape"] = draw(st.sampled_from([[numel], [rows, numel // rows], [numel // rows, rows, 1]]))
        elif op == "dtype":
            entry["dtype"] = draw(st.sampled_from(SAFETENSORS_DTYPES))
        elif op == "shape":
            entry["shape"] = draw(shapes)
        elif op == "offsets":
            entry["data_offsets"] = draw(st.lists(st.integers(-2, len(body) + 8), min_size=0, max_size=3))
        elif op == "meta":
            header["__metadata__"] = {"json": draw(st.one_of(st.sampled_from(JSON_ODDITIES), st.text(max_size=30)))}
        elif op == "meta_value":
            header["__metadata__"] = draw(st.sampled_from([{"json": 5}, [1], None, {"json": ["x"]}, {"other": "x"}]))
        elif op == "drop":
            header.pop(name, None)
        else:
            header[draw(st.text(min_size=1, max_size=5))] = {"dtype": "F32", "shape": draw(shapes),
                                                            "data_offsets": [len(body), len(body) + 4]}
    raw = json.dumps(header).encode()
    wrong = draw(st.integers(0, 4)) == 4  # a length that lies, one time in five (Hypothesis favours 0)
    length = draw(st.sampled_from([len(raw) + 1, len(raw) - 1, 2**63, 10**8 + 1, 0])) if wrong else len(raw)
    return struct.pack("<Q", max(length, 0)) + raw + body


# ---------------------------------------------------------------------------------------------- the property
def parses_or_refuses(read, data: bytes, suffix: str):
    """``read(path)`` on ``data``: its result, or None after checking the refusal is one line naming the file."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"fuzzed{suffix}"
        path.write_bytes(data)
        try:
            return read(path)
        except ToolkitError as e:
            msg = str(e)
            assert msg and "\n" not in msg and "\r" not in msg, repr(msg)
            assert "fuzzed" in msg, f"the message does not name the file: {msg!r}"
            return None


def rewrites_equal(scene: GaussianScene, suffix: str) -> None:
    """A scene a reader accepted: the same format's writer writes it, and it reads back equal."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"again{suffix}"
        try:
            scene.to_ply(path) if suffix == ".ply" else scene.save(path)
        except ToolkitError as e:  # only what a PLY cannot hold: float64 beyond float32, an over-long header
            assert suffix == ".ply" and ("float32" in str(e) or "header" in str(e)), str(e)
            return
        _assert_scene_equal(scene, GaussianScene.read(path))


def _read_scene(path: Path) -> GaussianScene:
    return GaussianScene.read(path).validate()


def _check_scene(data: bytes, suffix: str) -> None:
    scene = parses_or_refuses(_read_scene, data, suffix)
    if scene is not None:
        rewrites_equal(scene, suffix)


@given(st.data())
def test_mutated_binary_ply_parses_or_is_refused(data):
    base = binary_ply()
    _check_scene(data.draw(st.one_of(mutated(base), edited_ply_header(base))), ".ply")


@given(st.data())
def test_mutated_ascii_ply_parses_or_is_refused(data):
    base = ascii_ply()
    _check_scene(data.draw(st.one_of(mutated(base), edited_ply_header(base))), ".ply")


@given(random_ply())
def test_random_ply_parses_or_is_refused(data):
    _check_scene(data, ".ply")


@given(st.data())
def test_mutated_scene_safetensors_parses_or_is_refused(data):
    base = scene_safetensors()
    _check_scene(data.draw(st.one_of(mutated(base), edited_safetensors_header(base))), ".safetensors")


def _read_checkpoint(path: Path) -> dict:
    state, info = load_checkpoint(path)
    assert isinstance(info, dict) and all(isinstance(v, torch.Tensor) for v in state.values())
    assert load_state_dict_file(path).keys() == state.keys()
    return state


@given(st.data())
def test_mutated_checkpoint_parses_or_is_refused(data):
    base = checkpoint_safetensors()
    parses_or_refuses(_read_checkpoint, data.draw(st.one_of(mutated(base), edited_safetensors_header(base))),
                      ".safetensors")


@given(st.data())
def test_mutated_torch_checkpoint_parses_or_is_refused(data):
    parses_or_refuses(load_state_dict_file, data.draw(mutated(checkpoint_pt())), ".pt")


# ---------------------------------------------------------------------------------------------- round trips
RESERVED = {"format", "format_version", "has_sh", "feature_dim", "eyes"}  # managed by the writers, or checked
json_text = st.text(alphabet=st.characters(codec=None, exclude_categories=()), max_size=12)
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | json_text,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(json_text, inner, max_size=3),
    max_leaves=8,
)
f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


@st.composite
def scenes(draw) -> GaussianScene:
    n, d = draw(st.integers(0, 9)), draw(st.integers(0, 5))
    degree = draw(st.sampled_from([None, 0, 1, 2, 3]))

    def field(*shape):
        return torch.from_numpy(draw(arrays(np.float32, shape, elements=f32)))

    meta = draw(st.dictionaries(json_text.filter(lambda k: k not in RESERVED), json_values, max_size=4))
    if draw(st.booleans()):
        meta["feature_kind"] = draw(st.sampled_from(["rgb", "neural"]))
    if draw(st.booleans()):
        meta["eyes"] = {"left": {"center": [0.0, 1.5, -2.0], "radius": 0.012, "part": 1}}
    part = torch.from_numpy(draw(arrays(np.int8, (n,), elements=st.integers(0, 2))))
    return GaussianScene(means=field(n, 3), quats=field(n, 4), log_scales=field(n, 3), opacity_logits=field(n),
                         features=field(n, d), part=part,
                         sh=None if degree is None else field(n, (degree + 1) ** 2, 3), metadata=meta)


def _odd_metadata_scene() -> GaussianScene:
    s = random_scene(2, d=0, sh_degree=3)
    s.metadata.update({"line\nbreak": "end_header\ncomment x\r\n\x00\u2028\ud800 \U0001f600", "deep": [[[{}]]]})
    return s


@given(scenes())
@example(random_scene(0, sh_degree=0)).via("no Gaussians, SH degree 0")
@example(random_scene(0, d=0, sh_degree=1)).via("no Gaussians and no features, SH degree 1")
@example(random_scene(0, d=5, sh_degree=2)).via("no Gaussians, SH degree 2")
@example(random_scene(0, sh_degree=3)).via("no Gaussians, SH degree 3")
@example(_odd_metadata_scene()).via("metadata strings with newlines and odd characters")
def test_any_scene_round_trips_through_both_formats_and_convert(scene):
    from toolkit.__main__ import main

    with tempfile.TemporaryDirectory() as tmp:
        ply, st_file, back = Path(tmp) / "s.ply", Path(tmp) / "s.safetensors", Path(tmp) / "back.safetensors"
        scene.to_ply(ply)
        _assert_scene_equal(scene, GaussianScene.from_ply(ply))
        scene.save(st_file)
        _assert_scene_equal(scene, GaussianScene.load(st_file))
        with open(os.devnull, "w") as null, _stdout_to(null):
            assert main(["convert", str(st_file), str(Path(tmp) / "c.ply")]) == 0
            assert main(["convert", str(Path(tmp) / "c.ply"), str(back)]) == 0
        _assert_scene_equal(scene, GaussianScene.load(back))


def _stdout_to(stream):
    import contextlib

    return contextlib.redirect_stdout(stream)


def test_the_valid_bases_read():
    """The mutations start from files that read: a refusal found above is the mutation's doing."""
    assert parses_or_refuses(_read_scene, binary_ply(), ".ply") is not None
    assert parses_or_refuses(_read_scene, ascii_ply(), ".ply") is not None
    assert parses_or_refuses(_read_scene, scene_safetensors(), ".safetensors") is not None
    assert parses_or_refuses(_read_checkpoint, checkpoint_safetensors(), ".safetensors") is not None
    assert parses_or_refuses(load_state_dict_file, checkpoint_pt(), ".pt") is not None
    assert FORMAT_VERSION == 1
