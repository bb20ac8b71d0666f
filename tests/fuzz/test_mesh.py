"""Property tests of the mesh readers and of compare_meshes.

- Any OBJ, OFF or PLY (ASCII or binary) text, well formed or mutated: ``load_mesh`` returns a valid mesh
  (finite float32 vertices, every face index in range, at least one triangle) or raises one ``ToolkitError``
  line naming the file; never another exception.
- A well-formed file reads back exactly what was written (polygons fan-triangulated), in every format and
  index style (OBJ's 1-based, negative-relative and ``i/t/n`` indices).
- ``compare_meshes(mesh, mesh)`` is ~0 at any scale from 1e-30 to 1e30, and a known gap is measured right.
"""

from __future__ import annotations

import math
import struct
import tempfile
from pathlib import Path

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from geometry.mesh_files import load_mesh
from geometry.mesh_stats import compare_meshes
from toolkit.errors import ToolkitError

FORMATS = ("obj", "off", "ply-ascii", "ply-binary")
SPECIAL = [0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 1e39, -3.5e38, 1e-30, 3.4e38]
coords = st.one_of(st.floats(-1e3, 1e3, allow_nan=False, width=32), st.sampled_from(SPECIAL))
fine = st.floats(-1e3, 1e3, allow_nan=False, width=32)  # float32 values: they survive the round trip exactly


@st.composite
def raw_meshes(draw, coord=coords, valid=False):
    """(vertices [(x, y, z)], polygons [[0-based ids]]); with ``valid`` every polygon has >= 3 ids in range."""
    nv = draw(st.integers(3 if valid else 0, 7))
    verts = draw(st.lists(st.tuples(coord, coord, coord), min_size=nv, max_size=nv))
    ids = st.integers(0, nv - 1) if valid else st.integers(-2, nv + 1)
    polys = draw(st.lists(st.lists(ids, min_size=3 if valid else 0, max_size=5), min_size=1 if valid else 0, max_size=5))
    return verts, polys


def _obj(verts, polys, style: str) -> bytes:
    lines = ["# written by the fuzz test", "o thing"] + [f"v {x!r} {y!r} {z!r}" for x, y, z in verts]
    lines += ["vt 0 0", "vn 0 0 1", "s off"]
    for p in polys:
        if style == "negative":  # after every vertex: -1 is the last
            refs = [str(i - len(verts)) for i in p]
        else:
            refs = [{"plain": f"{i + 1}", "vt": f"{i + 1}/1", "vtn": f"{i + 1}/1/1", "vn": f"{i + 1}//1"}[style] for i in p]
        lines.append("f " + " ".join(refs))
    return ("\n".join(lines) + "\n").encode()


def _off(verts, polys) -> bytes:
    lines = ["OFF", f"{len(verts)} {len(polys)} 0"] + [f"{x!r} {y!r} {z!r}" for x, y, z in verts]
    lines += [f"{len(p)} " + " ".join(map(str, p)) for p in polys]
    return ("\n".join(lines) + "\n").encode()


def _ply(verts, polys, binary: bool) -> bytes:
    real = "double" if binary else "float"  # binary doubles: 1e39 and NaN are representable
    head = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment fuzz",
            f"element vertex {len(verts)}", f"property {real} x", f"property {real} y", f"property {real} z",
            f"element face {len(polys)}", "property list uchar int vertex_indices", "end_header"]
    out = ("\n".join(head) + "\n").encode()
    if not binary:
        rows = [f"{x!r} {y!r} {z!r}" for x, y, z in verts] + [f"{len(p)} " + " ".join(map(str, p)) for p in polys]
        return out + ("\n".join(rows) + "\n").encode()
    out += b"".join(struct.pack("<3d", *v) for v in verts)
    return out + b"".join(struct.pack(f"<B{len(p)}i", len(p), *p) for p in polys)


def _write(fmt: str, verts, polys, style: str = "plain") -> bytes:
    if fmt == "obj":
        return _obj(verts, polys, style)
    if fmt == "off":
        return _off(verts, polys)
    return _ply(verts, polys, fmt == "ply-binary")


TOKENS = [b"-1", b"0", b"1", b"nan", b"inf", b"\n", b" ", b"99999999", b"1e40", b"#", b"\xff\xfe", b"3", b"f 0 1 2\n",
          b"element face 5\n", b"/", b"\x00", b"end_header\n", b"4294967295"]


@st.composite
def mutations(draw, data: bytes):
    """``data`` with up to 3 edits: a byte replaced, a span cut, a token inserted, a number changed, truncation."""
    for _ in range(draw(st.integers(0, 3))):
        n = len(data)
        at = draw(st.integers(0, n))
        kind = draw(st.sampled_from(["replace", "cut", "insert", "number", "truncate"]))
        if kind == "replace" and n:
            at = min(at, n - 1)
            data = data[:at] + bytes([draw(st.integers(0, 255))]) + data[at + 1:]
        elif kind == "cut":
            data = data[:at] + data[at + draw(st.integers(1, 40)):]
        elif kind == "insert":
            data = data[:at] + draw(st.sampled_from(TOKENS)) + data[at:]
        elif kind == "number":  # the next digit becomes another count, index or coordinate
            digits = [i for i in range(at, n) if 48 <= data[i] <= 57]
            if digits:
                i = digits[0]
                data = data[:i] + str(draw(st.sampled_from([0, 2, 7, 255, 99999999, -5]))).encode() + data[i + 1:]
        else:
            data = data[:at]
    return data


def _load(fmt: str, data: bytes):
    """load_mesh on ``data`` -> (verts, faces) or the ToolkitError, after checking the promise."""
    ext = "ply" if fmt.startswith("ply") else fmt
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"mesh.{ext}"
        path.write_bytes(data)
        try:
            v, f = load_mesh(path)
        except ToolkitError as e:
            msg = str(e)
            assert "\n" not in msg and str(path) in msg, msg
            return e
    assert v.dtype == torch.float32 and v.dim() == 2 and v.shape[1] == 3 and bool(torch.isfinite(v).all())
    assert f.dtype == torch.int64 and f.dim() == 2 and f.shape[1] == 3 and f.shape[0] >= 1
    assert int(f.min()) >= 0 and int(f.max()) < v.shape[0]
    return v, f


@pytest.mark.filterwarnings("error")  # a warning is one more stderr line: none may escape
@given(fmt=st.sampled_from(FORMATS), mesh=raw_meshes(), data=st.data())
def test_any_mesh_file_reads_or_is_one_error_line(fmt, mesh, data):
    verts, polys = mesh
    if fmt == "ply-binary":  # struct packs what an int32 and a uchar count hold
        polys = [p for p in polys if len(p) < 256]
    text = data.draw(mutations(_write(fmt, verts, polys)))
    _load(fmt, text)


def _fan(polys) -> list[list[int]]:
    return [[p[0], p[j], p[j + 1]] for p in polys for j in range(1, len(p) - 1)]


@given(fmt=st.sampled_from(FORMATS), mesh=raw_meshes(coord=fine, valid=True),
       style=st.sampled_from(["plain", "vt", "vtn", "vn", "negative"]))
def test_well_formed_file_reads_back_exactly(fmt, mesh, style):
    verts, polys = mesh
    out = _load(fmt, _write(fmt, verts, polys, style))
    assert not isinstance(out, ToolkitError), out
    v, f = out
    assert torch.equal(v, torch.tensor(verts, dtype=torch.float32).reshape(-1, 3))
    assert f.tolist() == _fan(polys)


@given(fmt=st.sampled_from(FORMATS), mesh=raw_meshes(coord=fine, valid=True), data=st.data())
def test_an_out_of_range_index_is_refused_naming_where(fmt, mesh, data):
    verts, polys = mesh
    bad = data.draw(st.sampled_from([len(verts), len(verts) + 5] + ([-1] if fmt != "obj" else [])))
    polys = [*polys[:-1], [*polys[-1][:-1], bad]]
    out = _load(fmt, _write(fmt, verts, polys))
    assert isinstance(out, ToolkitError) and "out of range" in str(out), out


def test_obj_zero_index_and_off_forged_count_are_refused(tmp_path):
    (tmp_path / "zero.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n")
    with pytest.raises(ToolkitError, match=r"zero\.obj: line 4: face index 0 is out of range \(OBJ indices start at 1"):
        load_mesh(tmp_path / "zero.obj")
    (tmp_path / "big.off").write_text("OFF\n3 99999999 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(ToolkitError, match=r"big\.off: the OFF header's 3 vertices and 99999999 faces needs \d+ bytes"):
        load_mesh(tmp_path / "big.off")


@pytest.mark.filterwarnings("error")
def test_binary_ply_signalling_nan_is_refused_without_a_warning(tmp_path):
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    snan = struct.pack("<I", 0x7F9E8C7A)  # a float32 NaN without the quiet bit
    body = struct.pack("<6f", 0, 0, 0, 1, 0, 0) + b"\0" * 4 + snan + b"\0" * 4 + struct.pack("<B3i", 3, 0, 1, 2)
    (tmp_path / "s.ply").write_bytes(head + body)
    with pytest.raises(ToolkitError, match=r"s\.ply: vertex row 2: vertex coordinates must be finite"):
        load_mesh(tmp_path / "s.ply")


# ---------------------------------------------------------------------------------------- compare
def _octahedron(r: float) -> tuple[torch.Tensor, torch.Tensor]:
    v = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float64) * r
    f = torch.tensor([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return v, f


@pytest.mark.parametrize("scale", [1e-30, 1e-3, 1.0, 1e6, 1e30])
def test_compare_a_mesh_with_itself_is_zero_at_any_scale(scale):
    v, f = _octahedron(scale)
    res = compare_meshes(v.float(), f, v.float(), f, n_samples=500)
    assert res["chamfer_rel_diag"] < 1e-6 and res["hausdorff_rel_diag"] < 1e-5, res
    assert res["normal_consistency"] > 0.999


@given(exp=st.integers(-30, 30), gap=st.floats(0.01, 0.5), shift=st.floats(-10, 10))
def test_compare_measures_a_known_gap_at_any_scale(exp, gap, shift):
    """A an octahedron of radius r, B the same scaled by 1 + gap: every point of A is exactly gap r / sqrt(3)
    from B (the parallel face), and B's farthest points (its vertices) are gap r from A. Moving both by
    ``shift`` x r changes nothing but float32 rounding."""
    r = 10.0**exp
    v, f = _octahedron(r)
    res = compare_meshes(v.float(), f, (v * (1 + gap)).float(), f, n_samples=300)
    assert res["mean_a_to_b"] == pytest.approx(gap * r / math.sqrt(3), rel=1e-4)
    assert gap * r / math.sqrt(3) < res["mean_b_to_a"] < res["hausdorff"] <= gap * r * (1 + 1e-4)
    assert res["chamfer_rel_diag"] == pytest.approx(res["chamfer"] / (2 * math.sqrt(3) * r), rel=1e-6)
    off = torch.tensor([shift, -shift, 0.5 * shift], dtype=torch.float64) * r
    moved = compare_meshes((v + off).float(), f, (v * (1 + gap) + off).float(), f, n_samples=300)
    assert moved["chamfer"] == pytest.approx(res["chamfer"], rel=1e-2)
