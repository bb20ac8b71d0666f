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


def test_nan_field(tmp_path):
    s = random_scene(5)
    s.to_ply(tmp_path / "n.ply")
    raw = bytearray((tmp_path / "n.ply").read_bytes())
    start = raw.index(b"end_header\n") + len(b"end_header\n")
    raw[start:start + 4] = np.array([np.nan], "<f4").tobytes()  # x of the first Gaussian
    (tmp_path / "n.ply").write_bytes(bytes(raw))
    with pytest.raises(ToolkitError, match="means: 1 Gaussian"):
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
