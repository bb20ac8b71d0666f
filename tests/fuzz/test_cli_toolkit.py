"""Bad scene files given to ``python -m toolkit info`` and ``convert``: each is refused in one line naming the file
and what was wrong, exit 2, no traceback, the input unchanged and no output (not even a temporary file) written.

Every failure class of the readers has a case: malformed or forged PLY headers and bodies, values a scene cannot
hold, forged safetensors headers, wrong tensors and metadata in a scene file, and scenes that one format can
hold but the other cannot.
"""

from __future__ import annotations

import json
import struct
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch

from tests.conftest import random_scene
from tests.fuzz.cli import assert_refused
from tests.fuzz.test_ply_scene import binary_ply, scene_safetensors
from toolkit.io import save_tensors
from toolkit.scene import FORMAT_NAME, FORMAT_VERSION


# ---------------------------------------------------------------------------------------------- PLY builders
def ply_edit(old: bytes, new: bytes) -> Callable[[], bytes]:
    """Our binary PLY with one header text replaced."""
    def build() -> bytes:
        head, body = binary_ply().split(b"end_header\n", 1)
        assert old in head, old
        return head.replace(old, new, 1) + b"end_header\n" + body
    return build


def ply_meta(comment: bytes) -> Callable[[], bytes]:
    """Our binary PLY with its metadata comment replaced."""
    def build() -> bytes:
        line = next(ln for ln in binary_ply().split(b"\n") if ln.startswith(b"comment ditgaze "))
        return ply_edit(line, b"comment ditgaze " + comment)()
    return build


def ply_value(prop: str, value: float) -> Callable[[], bytes]:
    """Our binary PLY with one value of the first Gaussian's ``prop`` replaced."""
    def build() -> bytes:
        head, body = binary_ply().split(b"end_header\n", 1)
        props = [ln.split()[-1] for ln in head.decode().split("\n") if ln.startswith("property")]
        body = bytearray(body)
        at = 4 * props.index(prop)
        body[at:at + 4] = np.array([value], "<f4").tobytes()
        return head + b"end_header\n" + bytes(body)
    return build


GRAPHDECO = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0",
             "rot_1", "rot_2", "rot_3"]


def ascii_ply(names=GRAPHDECO, rows=((0.0,) * 14,), count=None, fmt=b"ascii") -> Callable[[], bytes]:
    def build() -> bytes:
        head = b"ply\nformat " + fmt + b" 1.0\nelement vertex %d\n" % (len(rows) if count is None else count)
        head += b"".join(b"property float %s\n" % n.encode() for n in names) + b"end_header\n"
        return head + b"".join(" ".join(map(str, r)).encode() + b"\n" for r in rows)
    return build


def raw(data: bytes) -> Callable[[], bytes]:
    return lambda: data


# ---------------------------------------------------------------------------------------------- safetensors builders
def st_header(edit: Callable[[dict], None], length_delta: int | None = 0, length: int | None = None):
    """Our scene file with its JSON header edited in place, and its length prefix right, off by
    ``length_delta`` or set to ``length``."""
    def build() -> bytes:
        base = scene_safetensors()
        n = struct.unpack("<Q", base[:8])[0]
        header, body = json.loads(base[8:8 + n]), base[8 + n:]
        edit(header)
        text = json.dumps(header).encode()
        return struct.pack("<Q", len(text) + length_delta if length is None else length) + text + body
    return build


def st_meta(meta) -> Callable[[], bytes]:
    """Our scene file whose metadata ``json`` entry is ``meta`` (a value, written as the library stores it)."""
    def edit(h):
        h["__metadata__"]["json"] = meta
    return st_header(edit)


def st_scene(tensors: dict | None = None, drop: tuple[str, ...] = (), **meta) -> Callable[[], bytes]:
    """A scene file written by the toolkit's own writer, with tensors replaced or dropped and metadata added:
    what a buggy or foreign writer could leave."""
    def build() -> bytes:
        t = random_scene(5).tensors()
        t.update(tensors or {})
        for name in drop:
            del t[name]
        m = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, **meta}
        with tempfile.TemporaryDirectory() as tmp:
            save_tensors(Path(tmp) / "s.safetensors", t, m)
            return (Path(tmp) / "s.safetensors").read_bytes()
    return build


def scene_file(**changes) -> Callable[[], bytes]:
    """A valid scene, as .safetensors, that convert must refuse to write as PLY."""
    def build() -> bytes:
        s = random_scene(3, d=changes.pop("d", 3))
        for k, v in changes.items():
            setattr(s, k, v(s))
        with tempfile.TemporaryDirectory() as tmp:
            s.save(Path(tmp) / "s.safetensors")
            return (Path(tmp) / "s.safetensors").read_bytes()
    return build


def _drop(key):
    return lambda h: h.pop(key)


def _set(key, field, value):
    def edit(h):
        h[key][field] = value
    return edit


# (id, input name, builder, command, error regex). Commands: "info", "ply" (convert to .ply), "st" (convert to
# .safetensors), "obj" (convert to an unknown extension).
CASES = [
    # -- PLY: header structure
    ("ply-empty-file", "e.ply", raw(b""), "info", r"e.ply: not a PLY file"),
    ("ply-random-bytes", "r.ply", raw(bytes(range(256)) * 8), "st", r"r.ply: not a PLY file"),
    ("ply-no-end-header", "h.ply", raw(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n1\n"), "info",
     r"h.ply: not a PLY file \(missing 'ply' magic or 'end_header'"),
    ("ply-non-utf8-header", "u.ply", ply_edit(b"format binary", b"comment \xff\xfe\nformat binary"), "info",
     r"u.ply: PLY header is not UTF-8 text"),
    ("ply-unknown-format", "f.ply", ply_edit(b"binary_little_endian", b"binary_middle_endian"), "st",
     r"f.ply: unsupported PLY format line"),
    ("ply-unknown-type", "t.ply", ply_edit(b"property float opacity", b"property half opacity"), "info",
     r"t.ply: bad property line \d+: 'property half opacity' \(expected 'property TYPE NAME'"),
    ("ply-duplicate-property", "d.ply", ply_edit(b"property float rot_3", b"property float rot_2"), "st",
     r"d.ply: property 'rot_2' of element 'vertex' is declared twice"),
    ("ply-duplicate-element", "d.ply", ply_edit(b"element vertex 6", b"element vertex 6\nelement vertex 6"), "info",
     r"d.ply: element 'vertex' is declared twice"),
    ("ply-two-formats", "f.ply", ply_edit(b"format binary_little_endian 1.0", b"format ascii 1.0\nformat ascii 1.0"),
     "info", r"f.ply: a second format line"),
    ("ply-list-in-vertex", "l.ply", ply_edit(b"property float part", b"property list uchar int part"), "info",
     r"l.ply: list properties in the vertex element are not supported"),
    ("ply-f_rest-abc", "r.ply", ply_edit(b"property float f_rest_8", b"property float f_rest_abc"), "st",
     r"r.ply: vertex property 'f_rest_abc': expected f_rest_<index>"),
    ("ply-f_rest-gap", "g.ply", ply_edit(b"property float f_rest_4", b"property float f_rest_40"), "st",
     r"g.ply: vertex properties f_rest_\*: 9 of them, but 'f_rest_4' is missing"),
    ("ply-feat-named-oddly", "f.ply", ply_edit(b"property float feat_1", b"property float feat_x"), "info",
     r"f.ply: vertex property 'feat_x'"),
    ("ply-missing-rot", "m.ply", ply_edit(b"property float rot_3", b"property float rot_9"), "info",
     r"m.ply: not a 3DGS PLY: missing vertex properties \['rot_3'\]"),
    ("ply-no-colour", "c.ply", ascii_ply(GRAPHDECO[:3] + GRAPHDECO[6:], ((0.0,) * 11,)), "st",
     r"c.ply: no colour: neither f_dc_0..2 nor feat_\*"),
    # -- PLY: counts a file cannot hold, refused before reading the body
    ("ply-20M-vertices-binary", "big.ply", ply_edit(b"element vertex 6", b"element vertex 20000000"), "info",
     r"big.ply: element 'vertex' \(the header declares 20000000 vertices of 120 bytes\) needs \d+ bytes but the "
     r"file holds \d+"),
    ("ply-20M-vertices-ascii", "big.ply", ascii_ply(count=20_000_000), "st",
     r"big.ply: element 'vertex' \(the header declares 20000000 vertices of at least 28 bytes\)"),
    ("ply-5000-digit-count", "n.ply", ply_edit(b"element vertex 6", b"element vertex " + b"9" * 5000), "info",
     r"n.ply: bad element line \d+: 'element vertex 9999.*a count below 10\^15"),
    ("ply-truncated-body", "t.ply", lambda: binary_ply()[:-7], "st",
     r"t.ply: element 'vertex' \(the header declares 6 vertices.*truncated"),
    ("ply-ascii-short-rows", "s.ply", ascii_ply(rows=((0.0,) * 14, (0.0,) * 13)), "info",
     r"s.ply: vertex rows are not 14 numbers each"),
    ("ply-ascii-word", "w.ply", ascii_ply(rows=((0.0,) * 13 + ("one",),)), "info",
     r"w.ply: vertex rows are not 14 numbers each \(could not convert string 'one'"),
    # -- PLY: values and metadata a scene cannot hold
    ("ply-nan-opacity", "n.ply", ply_value("opacity", np.nan), "st",
     r"n.ply: vertex property 'opacity': 1 of 6 values are NaN or inf"),
    ("ply-inf-scale", "i.ply", ascii_ply(rows=((0.0,) * 7 + (float("-inf"), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0),)), "info",
     r"i.ply: vertex property 'scale_0': 1 of 1 values are NaN or inf"),
    ("ply-double-overflow", "o.ply", lambda: ascii_ply(rows=((1e300,) + (0.0,) * 13,))().replace(
        b"property float x", b"property double x"), "st", r"o.ply: vertex property 'x': .*beyond float32"),
    ("ply-part-7", "p.ply", ply_value("part", 7.0), "info", r"p.ply: vertex property 'part' must hold 0"),
    ("ply-metadata-json-list", "m.ply", ply_meta(b"[1, 2]"), "info",
     r"m.ply: the ditgaze metadata comment of the PLY header is not a JSON object \(got a JSON array\)"),
    ("ply-metadata-garbage", "m.ply", ply_meta(b"{oops"), "st", r"m.ply: .*metadata comment .* is not valid JSON"),
    ("ply-metadata-deep", "m.ply", ply_meta(b"[" * 10_000), "info", r"m.ply: .* nested deeper than 64 levels"),
    ("ply-metadata-5000-digits", "m.ply", ply_meta(b'{"a": ' + b"9" * 5000 + b"}"), "info",
     r"m.ply: .* is not valid JSON \(Exceeds the limit"),
    ("ply-metadata-has_sh-string", "m.ply", ply_meta(b'{"has_sh": "yes", "feature_dim": 3}'), "info",
     r"m.ply: ditgaze metadata has_sh: expected true or false, got 'yes'"),
    ("ply-metadata-feature_dim-lies", "m.ply", ply_meta(b'{"has_sh": true, "feature_dim": 7}'), "st",
     r"m.ply: the header's metadata says feature_dim=7, the vertex has 3 feat_\* properties"),
    ("ply-metadata-eyes-list", "e.ply", ply_meta(b'{"has_sh": true, "feature_dim": 3, "eyes": [1, 2]}'), "info",
     r"e.ply: GaussianScene.metadata.eyes: expected a mapping of left/right eyeballs, got list"),
    ("ply-metadata-eye-radius", "e.ply",
     ply_meta(b'{"has_sh": true, "feature_dim": 3, "eyes": {"left": {"center": [0, 0, 0], "radius": -1}}}'), "st",
     r"e.ply: GaussianScene.metadata.eyes.left.radius: expected a finite number > 0, got -1"),
    # -- safetensors: the container (what the library refuses, wrapped)
    ("st-empty", "e.safetensors", raw(b""), "info", r"e.safetensors: not a valid safetensors file"),
    ("st-header-length-past-end", "h.safetensors", st_header(lambda h: None, length=10_000), "info",
     r"h.safetensors: not a valid safetensors file \(SafetensorError: .*invalid header length"),
    ("st-header-length-2^63", "h.safetensors", st_header(lambda h: None, length=2**63), "ply",
     r"h.safetensors: not a valid safetensors file \(SafetensorError: .*header too large"),
    ("st-header-length-short", "h.safetensors", st_header(lambda h: None, length_delta=-3), "info",
     r"h.safetensors: not a valid safetensors file"),
    ("st-garbage-json", "g.safetensors", raw(struct.pack("<Q", 16) + b"{not json at all" + b"\0" * 8), "ply",
     r"g.safetensors: not a valid safetensors file \(SafetensorError: .*invalid JSON"),
    ("st-shape-vs-bytes", "s.safetensors", st_header(_set("means", "shape", [6, 4])), "info",
     r"s.safetensors: not a valid safetensors file \(.*invalid shape, data type, or offset"),
    ("st-dtype-vs-bytes", "d.safetensors", st_header(_set("means", "dtype", "F64")), "info",
     r"d.safetensors: not a valid safetensors file"),
    ("st-offsets-overlap", "o.safetensors", st_header(_set("means", "data_offsets", [0, 72])), "ply",
     r"o.safetensors: not a valid safetensors file \(.*invalid offset"),
    ("st-unknown-dtype", "u.safetensors", st_header(_set("means", "dtype", "F99")), "info",
     r"u.safetensors: not a valid safetensors file \(.*unknown variant `F99`"),
    ("st-shape-overflow", "s.safetensors", st_header(_set("means", "shape", [2**40, 2**40, 2**40])), "info",
     r"s.safetensors: not a valid safetensors file \(.*overflow"),
    ("st-metadata-value-int", "m.safetensors", st_meta(5), "info",
     r"m.safetensors: not a valid safetensors file \(.*expected a string"),
    # -- safetensors: metadata
    ("st-metadata-json-list", "m.safetensors", st_meta("[1, 2]"), "ply",
     r"m.safetensors: metadata 'json' is not a JSON object \(got a JSON array\)"),
    ("st-metadata-garbage", "m.safetensors", st_meta("{oops"), "info",
     r"m.safetensors: metadata 'json' is not valid JSON"),
    ("st-metadata-deep", "m.safetensors", st_meta("[" * 100_000), "info",
     r"m.safetensors: metadata 'json' is JSON nested deeper than 64 levels"),
    ("st-metadata-5000-digits", "m.safetensors", st_meta('{"a": ' + "9" * 5000 + "}"), "ply",
     r"m.safetensors: metadata 'json' is not valid JSON \(Exceeds the limit"),
    ("st-not-a-scene", "c.safetensors", st_meta("{}"), "info", r"c.safetensors: not a GaussianScene file"),
    ("st-format-version-true", "v.safetensors", st_scene(format_version=True), "info",
     r"v.safetensors: scene format version True is not supported"),
    ("st-format-version-2", "v.safetensors", st_scene(format_version=FORMAT_VERSION + 1), "ply",
     r"v.safetensors: scene format version 2 is not supported .* upgrade"),
    ("st-eyes-list", "e.safetensors", st_scene(eyes=[1, 2]), "ply",
     r"e.safetensors: GaussianScene.metadata.eyes: expected a mapping"),
    ("st-eyes-center", "e.safetensors", st_scene(eyes={"right": {"center": [0, 0], "radius": 0.01}}), "info",
     r"e.safetensors: GaussianScene.metadata.eyes.right.center: expected 3 finite numbers, got \[0, 0\]"),
    # -- safetensors: tensors a scene cannot hold
    ("st-missing-tensor", "m.safetensors", st_scene(drop=("quats",)), "info",
     r"m.safetensors: missing tensor\(s\) \['quats'\]"),
    ("st-entry-dropped", "d.safetensors", st_header(_drop("quats")), "info",
     r"d.safetensors: not a valid safetensors file \(.*invalid offset for tensor `sh`"),
    ("st-means-N2", "m.safetensors", st_scene({"means": torch.zeros(5, 2)}), "info",
     r"m.safetensors: GaussianScene.means: expected shape \[N, 3\], got \[5, 2\]"),
    ("st-quats-count", "q.safetensors", st_scene({"quats": torch.zeros(4, 4)}), "ply",
     r"q.safetensors: GaussianScene.quats: expected shape \[5, 4\] \(N=5 from means\), got \[4, 4\]"),
    ("st-part-3", "p.safetensors", st_scene({"part": torch.full((5,), 3, dtype=torch.int8)}), "info",
     r"p.safetensors: GaussianScene.part: labels must be 0 \(face\), 1 \(left eye\) or 2 \(right eye\)"),
    ("st-part-int64", "p.safetensors", st_scene({"part": torch.zeros(5, dtype=torch.int64)}), "ply",
     r"p.safetensors: GaussianScene.part: expected int8 labels, got torch.int64"),
    ("st-float8-quats", "q.safetensors", st_scene({"quats": torch.zeros(5, 4, dtype=torch.float8_e4m3fn)}), "info",
     r"q.safetensors: GaussianScene.quats: expected a floating-point tensor .*got torch.float8_e4m3fn"),
    ("st-int-features", "f.safetensors", st_scene({"features": torch.zeros(5, 3, dtype=torch.int32)}), "info",
     r"f.safetensors: GaussianScene.features: expected a floating-point tensor"),
    ("st-sh-not-square", "s.safetensors", st_scene({"sh": torch.zeros(5, 5, 3)}), "ply",
     r"s.safetensors: GaussianScene.sh: expected shape \[N=5, K=\(degree\+1\)\^2, 3\], got \[5, 5, 3\]"),
    ("st-nan-opacity", "n.safetensors", st_scene({"opacity_logits": torch.tensor([0, float("nan"), 0, 0, 0])}),
     "info", r"n.safetensors: GaussianScene.opacity_logits: 1 Gaussian\(s\) have NaN or inf values"),
    # -- scenes one format holds and the other cannot: refused before writing
    ("convert-float64-beyond-float32", "w.safetensors", scene_file(means=lambda s: s.means.double() * 1e300),
     "ply", r"x.ply: GaussianScene.means: values beyond float32's range, which a PLY stores"),
    ("convert-too-many-features", "w.safetensors", scene_file(d=70_000), "ply",
     r"x.ply: the PLY header for 70018 properties per Gaussian would be \d+ bytes, more than readers look"),
    ("convert-unknown-extension", "s.safetensors", lambda: scene_safetensors(), "obj",
     r"x.obj: unknown output extension; expected .safetensors or .ply"),
    ("info-unknown-extension", "s.obj", lambda: scene_safetensors(), "info",
     r"s.obj: unknown scene extension '.obj'; expected .safetensors or .ply"),
]


OUTPUT_EXTENSIONS = {"ply": "ply", "st": "safetensors", "obj": "obj"}


@pytest.mark.parametrize("name, build, command, match", [pytest.param(*c[1:], id=c[0]) for c in CASES])
def test_bad_scene_files_are_refused_in_one_line(tmp_path, name, build, command, match):
    src, out = tmp_path / name, tmp_path / "out"
    src.write_bytes(build())
    out.mkdir()
    argv = ["info", src] if command == "info" else ["convert", src, out / ("x." + OUTPUT_EXTENSIONS[command])]
    assert_refused("toolkit", argv, match, inputs=[src], out_dir=out)


def test_every_case_has_its_own_id():
    ids = [c[0] for c in CASES]
    assert len(ids) == len(set(ids)) >= 20
