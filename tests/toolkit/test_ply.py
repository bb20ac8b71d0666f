import json
import time

import numpy as np
import pytest
import torch

from tests.conftest import random_scene
from tests.toolkit.test_scene import _assert_scene_equal
from toolkit import ToolkitError
from toolkit.ply import SH_C0
from toolkit.scene import GaussianScene


@pytest.mark.parametrize("d,sh", [(3, None), (32, None), (3, 3), (5, 1)])
def test_ply_round_trip_is_exact(tmp_path, d, sh):
    s = random_scene(25, d=d, sh_degree=sh)
    s.to_ply(tmp_path / "s.ply")
    _assert_scene_equal(s, GaussianScene.from_ply(tmp_path / "s.ply"))


def write_graphdeco_ply(path, n=7, degree=3, fmt="binary_little_endian", seed=1):
    """A 3DGS PLY exactly as the original graphdeco code writes it (from the published layout)."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = rng.normal(size=(n, len(names))).astype(np.float32)
    data[:, 3:6] = 0
    header = "ply\nformat %s 1.0\nelement vertex %d\n" % (fmt, n)
    header += "".join(f"property float {nm}\n" for nm in names) + "end_header\n"
    with open(path, "wb") as f:
        f.write(header.encode())
        if fmt == "ascii":
            f.write("\n".join(" ".join(repr(float(v)) for v in row) for row in data).encode() + b"\n")
        elif fmt == "binary_big_endian":
            f.write(data.astype(">f4").tobytes())
        else:
            f.write(data.astype("<f4").tobytes())
    return names, data


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_foreign_graphdeco_ply_loads(tmp_path, fmt):
    p = tmp_path / "point_cloud.ply"
    names, data = write_graphdeco_ply(p, n=7, degree=3, fmt=fmt)
    s = GaussianScene.from_ply(p)
    col = {nm: torch.from_numpy(data[:, i].copy()) for i, nm in enumerate(names)}
    assert torch.equal(s.means[:, 0], col["x"]) and torch.equal(s.opacity_logits, col["opacity"])
    assert torch.equal(s.quats[:, 0], col["rot_0"]) and torch.equal(s.log_scales[:, 2], col["scale_2"])
    assert s.sh.shape == (7, 16, 3) and s.sh_degree == 3
    assert torch.equal(s.sh[:, 0, 1], col["f_dc_1"])
    # f_rest is channel-major: f_rest_0..14 are R's 15 higher-order coefficients, then G, then B.
    assert torch.equal(s.sh[:, 1, 0], col["f_rest_0"])
    assert torch.equal(s.sh[:, 1, 1], col["f_rest_15"])
    assert torch.equal(s.sh[:, 15, 2], col["f_rest_44"])
    expected_rgb = (0.5 + SH_C0 * torch.stack([col["f_dc_0"], col["f_dc_1"], col["f_dc_2"]], 1)).clamp(0, 1)
    assert torch.allclose(s.features, expected_rgb)
    assert (s.part == 0).all()
    # And it writes back to the same graphdeco columns.
    s.to_ply(tmp_path / "again.ply")
    t = GaussianScene.from_ply(tmp_path / "again.ply")
    assert torch.equal(t.sh, s.sh) and torch.equal(t.means, s.means)


def test_written_ply_has_graphdeco_layout(tmp_path):
    s = random_scene(4, sh_degree=1)
    s.to_ply(tmp_path / "s.ply")
    head = (tmp_path / "s.ply").read_bytes().split(b"end_header")[0].decode()
    props = [ln.split()[-1] for ln in head.splitlines() if ln.startswith("property")]
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[9:18] == [f"f_rest_{i}" for i in range(9)]
    assert props[18:26] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert all(ln.startswith("property float ") for ln in head.splitlines() if ln.startswith("property"))


def _good_ply(tmp_path):
    p = tmp_path / "good.ply"
    random_scene(20).to_ply(p)
    return p


def test_truncated_ply(tmp_path):
    p = _good_ply(tmp_path)
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(ToolkitError, match="truncated"):
        GaussianScene.from_ply(p)


def test_missing_property(tmp_path):
    p = tmp_path / "m.ply"
    names, _ = write_graphdeco_ply(p)
    raw = p.read_bytes().replace(b"property float opacity\n", b"property float opacitx\n")
    p.write_bytes(raw)
    with pytest.raises(ToolkitError, match=r"missing vertex properties \['opacity'\]"):
        GaussianScene.from_ply(p)


def test_wrong_count(tmp_path):
    p = _good_ply(tmp_path)
    p.write_bytes(p.read_bytes().replace(b"element vertex 20", b"element vertex 25"))
    with pytest.raises(ToolkitError, match="declares 25 vertices"):
        GaussianScene.from_ply(p)


def test_a_count_below_the_rows_is_refused_not_cut(tmp_path):
    """Binary rows past the declared count, with no other element to hold them: the count is wrong (19 of 20
    would load silently); a stray newline after the last row is no row and still loads."""
    p = _good_ply(tmp_path)
    p.write_bytes(p.read_bytes() + b"\n")
    assert len(GaussianScene.from_ply(p)) == 20
    p.write_bytes(p.read_bytes()[:-1].replace(b"element vertex 20", b"element vertex 19"))
    with pytest.raises(ToolkitError, match=r"bytes follow the 19 vertices the header declares"):
        GaussianScene.from_ply(p)


def test_nan_field(tmp_path):
    s = random_scene(5)
    s.to_ply(tmp_path / "n.ply")
    raw = bytearray((tmp_path / "n.ply").read_bytes())
    start = raw.index(b"end_header\n") + len(b"end_header\n")
    raw[start:start + 4] = np.array([np.nan], "<f4").tobytes()  # x of the first Gaussian
    (tmp_path / "n.ply").write_bytes(bytes(raw))
    with pytest.raises(ToolkitError, match=r"n.ply: vertex property 'x': 1 of 5 values are NaN or inf"):
        GaussianScene.from_ply(tmp_path / "n.ply")


@pytest.mark.parametrize(
    "content,msg",
    [
        (b"", "not a PLY"),
        (bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8)), "not a PLY"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex x\nend_header\n", "bad element"),
        (b"ply\nformat weird 1.0\nend_header\n", "unsupported PLY format"),
        (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n", "no 'vertex'"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1.0\n", "missing vertex properties"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty floot x\nend_header\n1.0\n", "bad property"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1.0\nabc\n", "not 1 numbers"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n1 2\n",
         "property 'x' of element 'vertex' is declared twice"),
    ],
)
def test_garbled_ply(tmp_path, content, msg):
    p = tmp_path / "bad.ply"
    p.write_bytes(content)
    with pytest.raises(ToolkitError, match=msg):
        GaussianScene.from_ply(p)


def test_bad_part_property(tmp_path):
    s = random_scene(3)
    s.to_ply(tmp_path / "p.ply")
    raw = bytearray((tmp_path / "p.ply").read_bytes())
    raw[-4:] = np.array([5.0], "<f4").tobytes()  # part of the last Gaussian is the last column
    (tmp_path / "p.ply").write_bytes(bytes(raw))
    with pytest.raises(ToolkitError, match="'part'"):
        GaussianScene.from_ply(tmp_path / "p.ply")


def test_ply_write_failure_leaves_no_file(tmp_path):
    s = random_scene(5)
    s.features[0, 0] = float("nan")
    with pytest.raises(ToolkitError):
        s.to_ply(tmp_path / "x.ply")
    assert list(tmp_path.iterdir()) == []


def test_metadata_naming_end_header_round_trips_and_oversized_metadata_is_refused(tmp_path):
    s = random_scene(4)
    s.metadata["note"] = "see end_header"  # the word, not the header's last line
    s.to_ply(tmp_path / "m.ply")
    assert GaussianScene.from_ply(tmp_path / "m.ply").metadata["note"] == "see end_header"
    s.metadata["note"] = "x" * (1 << 20)
    with pytest.raises(ToolkitError, match="metadata cannot be written to a PLY header: .* bytes"):
        s.to_ply(tmp_path / "big.ply")
    assert not (tmp_path / "big.ply").exists()


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_empty_foreign_ply_loads_as_an_empty_scene(tmp_path, fmt):
    write_graphdeco_ply(tmp_path / "e.ply", n=0, degree=0, fmt=fmt)
    assert GaussianScene.from_ply(tmp_path / "e.ply").means.shape == (0, 3)


def _with_header_line(path, old: bytes, new: bytes):
    raw = path.read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    assert old in head
    path.write_bytes(head.replace(old, new, 1) + b"end_header\n" + body)


def _ascii_ply(path, names, rows, extra_header=b""):
    head = b"ply\nformat ascii 1.0\n" + extra_header + b"element vertex %d\n" % len(rows)
    head += b"".join(b"property float %s\n" % n.encode() for n in names) + b"end_header\n"
    path.write_bytes(head + b"".join(b" ".join(b"%r" % v for v in r) + b"\n" for r in rows))


_GRAPHDECO = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
              "rot_0", "rot_1", "rot_2", "rot_3"]


@pytest.mark.parametrize("extra,msg", [
    (["f_rest_abc"], r"vertex property 'f_rest_abc': expected f_rest_<index>"),
    (["f_rest_0", "f_rest_01"], r"vertex property 'f_rest_01'"),
    (["f_rest_0", "f_rest_2", "f_rest_3"], r"f_rest_\*: 3 of them, but 'f_rest_1' is missing"),
    (["feat_x"], r"vertex property 'feat_x'"),
])
def test_misnamed_indexed_property_is_named(tmp_path, extra, msg):
    p = tmp_path / "n.ply"
    _ascii_ply(p, _GRAPHDECO + extra, [[0.0] * (len(_GRAPHDECO) + len(extra))] * 2)
    with pytest.raises(ToolkitError, match=msg):
        GaussianScene.from_ply(p)


@pytest.mark.parametrize("comment,msg", [
    (b"[1, 2]", "is not a JSON object \\(got a JSON array\\)"),
    (b'"text"', "is not a JSON object \\(got a JSON string\\)"),
    (b"[" * 5000, "nested deeper than 64 levels"),
    (b'{"a":' * 100 + b"1" + b"}" * 100, "nested deeper than 64 levels"),
    (b'{"a": ' + b"9" * 5000 + b"}", "is not valid JSON"),
    (b"{not json", "is not valid JSON"),
    (b'{"has_sh": "no"}', "has_sh: expected true or false"),
    (b'{"feature_dim": -1}', "feature_dim: expected an integer >= 0"),
    (b'{"feature_dim": 4}', "feature_dim=4, the vertex has 3 feat_"),
])
def test_bad_metadata_comment_is_one_error(tmp_path, comment, msg):
    p = tmp_path / "m.ply"
    random_scene(3).to_ply(p)
    head = p.read_bytes().split(b"\n")
    line = next(ln for ln in head if ln.startswith(b"comment ditgaze "))
    _with_header_line(p, line, b"comment ditgaze " + comment)
    with pytest.raises(ToolkitError, match=r"m.ply: .*" + msg):
        GaussianScene.from_ply(p)


@pytest.mark.parametrize("degree", [None, 0, 1, 2, 3])
@pytest.mark.parametrize("d", [0, 1, 3])
def test_empty_and_featureless_scenes_round_trip(tmp_path, degree, d):
    for n in (0, 4):
        s = random_scene(n, d=d, sh_degree=degree)
        s.to_ply(tmp_path / "e.ply")
        _assert_scene_equal(s, GaussianScene.from_ply(tmp_path / "e.ply"))


def test_metadata_strings_with_newlines_and_odd_characters_round_trip(tmp_path):
    s = random_scene(3)
    s.metadata.update(note="line one\nline two\r\nend_header\n\x00\x1b[31m\u2028é🙂", **{"key\nwith newline": [None, 1.5]})
    s.to_ply(tmp_path / "m.ply")
    assert GaussianScene.from_ply(tmp_path / "m.ply").metadata == s.metadata


def test_writer_refuses_what_the_reader_would_refuse(tmp_path):
    wide = random_scene(2, d=70000)  # a header of 70 000 property lines is over the bound readers read
    with pytest.raises(ToolkitError, match=r"w.ply: the PLY header for 70018 properties .* bytes, more than"):
        wide.to_ply(tmp_path / "w.ply")
    far = random_scene(2)
    far.means = far.means.double() * 1e300  # finite in float64, inf in a PLY's float32
    with pytest.raises(ToolkitError, match=r"f.ply: GaussianScene.means: values beyond float32's range"):
        far.to_ply(tmp_path / "f.ply")
    deep = random_scene(2)
    deep.metadata["deep"] = json.loads("[" * 70 + "]" * 70)
    with pytest.raises(ToolkitError, match=r"metadata: nested deeper than 64 levels"):
        deep.to_ply(tmp_path / "d.ply")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_a_huge_declared_count_is_refused_before_allocating(tmp_path, monkeypatch, fmt):
    p = tmp_path / "h.ply"
    write_graphdeco_ply(p, n=3, degree=0, fmt=fmt)
    _with_header_line(p, b"element vertex 3", b"element vertex 20000000")
    # Were the body read or parsed, these would run: the count must be refused from the header and file size.
    monkeypatch.setattr(np, "frombuffer", lambda *a, **k: pytest.fail("read the body"))
    monkeypatch.setattr(np, "loadtxt", lambda *a, **k: pytest.fail("parsed the body"))
    with pytest.raises(ToolkitError, match=r"h.ply: element 'vertex' \(the header declares 20000000 vertices of "
                                           r".*bytes\) needs \d+ bytes but the file holds \d+"):
        GaussianScene.from_ply(p)


@pytest.mark.parametrize("content,msg", [
    (b"ply\nformat ascii 1.0\nelement vertex " + b"9" * 5000 + b"\nproperty float x\nend_header\n", "bad element line 3"),
    (b"ply\nformat ascii 1.0\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n", "second format"),
    (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nelement vertex 0\nend_header\n", "declared twice"),
    (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty half x\nend_header\n", "bad property line 4: .*expected"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n1\n", "not a PLY file"),
    (b"plyfoo\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n", "not a PLY file"),
    (b"ply\nformat ascii 1.0\ncomment \xff\xfe\nelement vertex 0\nproperty float x\nend_header\n", "not UTF-8"),
    (b"ply\nformat ascii 1.0\nelement vertex 5\nend_header\n", "declares no properties"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n1 2\n3  \n",
     "not 2 numbers each"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2 3\n",
     "rows have 3 values"),
])
def test_malformed_headers_and_bodies(tmp_path, content, msg):
    p = tmp_path / "bad.ply"
    p.write_bytes(content)
    with pytest.raises(ToolkitError, match=msg):
        GaussianScene.from_ply(p)


def test_utf8_comments_of_other_tools_are_read(tmp_path):
    p = tmp_path / "u.ply"
    _ascii_ply(p, _GRAPHDECO, [[0.0] * len(_GRAPHDECO)], extra_header="comment créé par un outil\n".encode())
    assert len(GaussianScene.from_ply(p)) == 1


def test_many_declared_properties_are_quick(tmp_path):
    p = tmp_path / "wide.ply"
    names = _GRAPHDECO + [f"e{i}" for i in range(45000)]  # about the most 1 MiB of header holds
    _ascii_ply(p, names, [[0.0] * len(names)])
    t0 = time.perf_counter()
    assert len(GaussianScene.from_ply(p)) == 1
    assert time.perf_counter() - t0 < 10


@pytest.mark.parametrize("name", ["opacity", "scale_1", "rot_3", "f_dc_2", "x"])
def test_non_finite_values_of_used_properties_are_named(tmp_path, name):
    p = tmp_path / "nf.ply"
    row = [0.0] * len(_GRAPHDECO)
    row[_GRAPHDECO.index(name)] = float("inf")
    _ascii_ply(p, _GRAPHDECO, [[0.0] * len(_GRAPHDECO), row])
    with pytest.raises(ToolkitError, match=rf"nf.ply: vertex property '{name}': 1 of 2 values are NaN or inf"):
        GaussianScene.from_ply(p)


def test_non_finite_normals_are_unused_and_kept(tmp_path):
    p = tmp_path / "nn.ply"
    names = _GRAPHDECO + ["nx", "ny", "nz"]
    _ascii_ply(p, names, [[0.0] * len(_GRAPHDECO) + [float("nan")] * 3])
    assert len(GaussianScene.from_ply(p)) == 1


def test_a_double_beyond_float32_is_refused(tmp_path):
    p = tmp_path / "d.ply"
    _ascii_ply(p, _GRAPHDECO, [[1e300] + [0.0] * (len(_GRAPHDECO) - 1)])
    with pytest.raises(ToolkitError, match=r"vertex property 'x': .*beyond float32"):
        GaussianScene.from_ply(p)


def test_many_declared_elements_are_quick(tmp_path):
    p = tmp_path / "many.ply"
    _ascii_ply(p, _GRAPHDECO, [[0.0] * len(_GRAPHDECO)])
    raw = p.read_bytes()
    elements = b"".join(b"element e%d 0\n" % i for i in range(60000))  # about the most 1 MiB of header holds
    p.write_bytes(raw.replace(b"end_header\n", elements + b"end_header\n", 1))
    t0 = time.perf_counter()
    assert len(GaussianScene.from_ply(p)) == 1
    assert time.perf_counter() - t0 < 10
