"""3DGS PLY files in the graphdeco layout (the format of the original 3D Gaussian Splatting code).

One ``vertex`` element, every property float32, values **pre-activation**::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3

``f_rest`` is channel-major (all R coefficients, then G, then B); ``rot`` is wxyz; ``scale`` is log-scale;
``opacity`` is the logit. This toolkit adds ``feat_0..feat_{D-1}`` (the scene's features, so non-RGB
features and exact RGB round-trip) and ``part``, plus a ``comment ditgaze {json}`` header line with the
scene metadata. Files from other tools load too: features become the SH DC colour
``clamp(0.5 + C0 · f_dc, 0, 1)`` and all SH coefficients are kept.

The reader accepts ``binary_little_endian``, ``binary_big_endian`` and ``ascii`` PLY with any scalar types. A file
is user input: every count its header declares is checked against the file's size and the memory budget before
anything is allocated (``toolkit.limits``), and every way a file can be malformed is one ``ToolkitError`` naming
the file and the line, property or field. What the writer writes, the reader reads back exactly (float32).

This module speaks plain tensors (the pre-activation fields of ``toolkit.scene.GaussianScene``, by name) and
knows nothing of the scene class: ``GaussianScene.to_ply`` / ``from_ply`` call it, never the other way round.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.io import MAX_JSON_DEPTH, atomic_write, check_readable_file, json_depth, parse_json_object
from toolkit.limits import check_allocation, check_declared_size

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi)), the degree-0 SH basis constant
_META_TAG = "ditgaze"
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_MAX_HEADER_BYTES = 1 << 20  # what the reader reads to find end_header, and so the most the writer may write
_MAX_COUNT_DIGITS = 15  # an element count of 10^15 rows or more cannot be a file on disk (and int() stays cheap)
_RESERVED_META = ("has_sh", "feature_dim", "format", "format_version")  # written or managed here, not kept


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return dc * SH_C0 + 0.5


def write_gaussian_ply(path: str | os.PathLike, tensors: dict[str, torch.Tensor], metadata: dict) -> None:
    """Write Gaussians to ``path`` as a binary little-endian 3DGS PLY, atomically.

    ``tensors``: the pre-activation fields, checked by the caller (``GaussianScene.tensors()``): means [N, 3],
    quats [N, 4] wxyz, log_scales [N, 3], opacity_logits [N], features [N, D], part [N] int, optional
    sh [N, K, 3]. ``metadata``: JSON-able, written to the header (``feature_kind`` "rgb", the default, makes
    the first three features the SH DC colour when there is no ``sh``). Whatever :func:`read_gaussian_ply`
    would refuse (values beyond float32, a header over its bound, metadata it cannot parse) is refused here,
    before anything is written.
    """
    cols = _columns(path, tensors, metadata)
    meta = dict(metadata)
    meta["has_sh"] = tensors.get("sh") is not None
    meta["feature_dim"] = int(tensors["features"].shape[1])
    lines = ["ply", "format binary_little_endian 1.0", f"comment {_META_TAG} {_metadata_json(path, meta)}",
             f"element vertex {tensors['means'].shape[0]}"]
    lines += [f"property float {name}" for name, _ in cols]
    header = ("\n".join(lines + ["end_header"]) + "\n").encode("ascii")
    if len(header) > _MAX_HEADER_BYTES:
        raise ToolkitError(f"{path}: the PLY header for {len(cols)} properties per Gaussian would be {len(header)} "
                           f"bytes, more than readers look through ({_MAX_HEADER_BYTES}); fewer features or a lower "
                           "SH degree, or write .safetensors")
    n = tensors["means"].shape[0]
    data = np.stack([c.numpy() for _, c in cols], axis=1).astype("<f4") if n else np.zeros((0, len(cols)), "<f4")
    with atomic_write(path, "wb") as f:
        f.write(header)
        f.write(np.ascontiguousarray(data).tobytes())


def _columns(path, tensors: dict[str, torch.Tensor], metadata: dict) -> list[tuple[str, torch.Tensor]]:
    """The PLY's float32 columns in graphdeco order; a field whose values overflow float32 is refused (the
    reader would find inf where the scene had a finite number)."""
    n, d = tensors["means"].shape[0], tensors["features"].shape[1]

    def f32(name: str) -> torch.Tensor:
        t = tensors[name].detach().to("cpu", torch.float32)
        if t.numel() and not bool(torch.isfinite(t).all()):
            raise ToolkitError(f"{path}: GaussianScene.{name}: values beyond float32's range, which a PLY stores; "
                               "write .safetensors to keep them")
        return t

    means, feats = f32("means"), f32("features")
    cols = [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
    cols += [(f"n{a}", torch.zeros(n)) for a in "xyz"]
    if tensors.get("sh") is not None:
        sh = f32("sh")
        # channel-major; the width is spelled out, as reshape cannot infer it when there are no Gaussians
        dc, rest = sh[:, 0, :], sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (sh.shape[1] - 1))
    else:
        # Other tools show the DC colour: that of RGB features in [0, 1] (clamped, so no huge feature overflows)
        rgb = d >= 3 and metadata.get("feature_kind", "rgb") == "rgb"
        dc = rgb_to_sh_dc(feats[:, :3].clamp(0, 1)) if rgb else torch.zeros(n, 3)
        rest = torch.zeros(n, 0)
    cols += [(f"f_dc_{i}", dc[:, i]) for i in range(3)]
    cols += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    cols += [("opacity", f32("opacity_logits"))]
    ls, q = f32("log_scales"), f32("quats")
    cols += [(f"scale_{i}", ls[:, i]) for i in range(3)]
    cols += [(f"rot_{i}", q[:, i]) for i in range(4)]
    cols += [(f"feat_{i}", feats[:, i]) for i in range(d)]
    cols += [("part", tensors["part"].to("cpu", torch.float32))]
    return cols


def _metadata_json(path, meta: dict) -> str:
    """``meta`` as one line of ASCII JSON the reader parses back to an equal dict (non-ASCII characters and
    newlines in strings are escaped by ``json.dumps``, so the header stays one line per comment)."""
    if json_depth(meta) > MAX_JSON_DEPTH:
        raise ToolkitError(f"{path}: scene metadata cannot be written to a PLY header: nested deeper than "
                           f"{MAX_JSON_DEPTH} levels")
    try:
        text = json.dumps(meta, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    except (TypeError, ValueError) as e:  # not JSON-able, a cycle, an integer over Python's digit limit
        raise ToolkitError(f"{path}: scene metadata cannot be written to a PLY header ({e})") from None
    if len(text) > _MAX_HEADER_BYTES // 2:  # readers read a bounded header
        raise ToolkitError(f"{path}: scene metadata cannot be written to a PLY header: {len(text)} bytes of JSON, "
                           f"expected at most {_MAX_HEADER_BYTES // 2}")
    return text


Element = tuple[str, int, list[tuple[str, str]]]  # (name, count, [(property, numpy type or "list:...")])


def _header_text(raw: bytes, path: Path) -> tuple[str, int]:
    """The header's text (up to, not including, the end_header line's newline) and the body's offset."""
    # The header ends at the first *line* "end_header": a comment may contain the word.
    m = re.search(rb"\nend_header[ \t]*\r?(\n|$)", raw)
    if raw.split(b"\n", 1)[0].rstrip(b"\r") != b"ply" or m is None:
        raise ToolkitError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header' within the first "
                           f"{len(raw)} bytes)")
    if not m.group(1):
        raise ToolkitError(f"{path}: truncated PLY header (no newline after end_header)")
    nl = m.end(1) - 1
    try:
        return raw[:nl].decode("utf-8"), nl + 1
    except UnicodeDecodeError as e:
        raise ToolkitError(f"{path}: PLY header is not UTF-8 text (byte {e.start})") from None


def _parse_header(raw: bytes, path: Path) -> tuple[str, list[Element], list[str], int]:
    """-> (format, elements, comments, body offset); every malformed line is one ToolkitError naming it."""
    text, offset = _header_text(raw, path)
    fmt = None
    elements: list[Element] = []
    # Sets, not list scans: a forged 1 MiB header may declare 70 000 properties or 40 000 elements.
    element_names: set[str] = set()
    seen: set[str] = set()  # the current element's property names
    comments: list[str] = []
    for lineno, line in enumerate(text.replace("\r", "").split("\n")[1:], start=2):
        parts = line.split()
        if not parts or parts[0] in ("end_header", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise ToolkitError(f"{path}: unsupported PLY format line {line!r}")
            if fmt is not None:
                raise ToolkitError(f"{path}: a second format line on line {lineno}: {line!r}")
            fmt = parts[1]
        elif parts[0] == "comment":
            comments.append(line[len("comment "):])
        elif parts[0] == "element":
            if len(parts) != 3 or not re.fullmatch(rf"[0-9]{{1,{_MAX_COUNT_DIGITS}}}", parts[2]):
                raise ToolkitError(f"{path}: bad element line {lineno}: {_short(line)!r} (expected 'element NAME "
                                   f"COUNT', a count below 10^{_MAX_COUNT_DIGITS})")
            if parts[1] in element_names:
                raise ToolkitError(f"{path}: element {parts[1]!r} is declared twice (line {lineno})")
            element_names.add(parts[1])
            elements.append((parts[1], int(parts[2]), []))
            seen = set()
        elif parts[0] == "property":
            if not elements:
                raise ToolkitError(f"{path}: property before any element on line {lineno}")
            prop = _property(parts, line, lineno, path)
            if prop[0] in seen:
                raise ToolkitError(f"{path}: property {prop[0]!r} of element {elements[-1][0]!r} "
                                   f"is declared twice (line {lineno})")
            seen.add(prop[0])
            elements[-1][2].append(prop)
        else:
            raise ToolkitError(f"{path}: unexpected PLY header line {lineno}: {_short(line)!r}")
    if fmt is None:
        raise ToolkitError(f"{path}: PLY header has no format line")
    return fmt, elements, comments, offset


def _property(parts: list[str], line: str, lineno: int, path: Path) -> tuple[str, str]:
    if len(parts) == 5 and parts[1] == "list":
        return parts[4], "list:" + parts[2] + ":" + parts[3]
    if len(parts) == 3 and parts[1] in _PLY_TYPES:
        return parts[2], _PLY_TYPES[parts[1]]
    raise ToolkitError(f"{path}: bad property line {lineno}: {_short(line)!r} (expected 'property TYPE NAME', TYPE "
                       f"one of {sorted(set(_PLY_TYPES))})")


def _short(text: str, limit: int = 80) -> str:
    return text if len(text) <= limit else text[:limit] + "..."


def read_ply_vertices(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], list[str]]:
    """Read the ``vertex`` element of a PLY file -> ({property: float array [N]}, header comments)."""
    path = check_readable_file(path, "PLY file")
    with open(path, "rb") as f:
        fmt, elements, comments, offset = _parse_header(f.read(_MAX_HEADER_BYTES), path)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise ToolkitError(f"{path}: PLY has no 'vertex' element")
    if names[0] != "vertex":
        raise ToolkitError(f"{path}: the 'vertex' element must come first for a Gaussian PLY")
    _, n, props = elements[0]
    if any(t.startswith("list:") for _, t in props):
        raise ToolkitError(f"{path}: list properties in the vertex element are not supported")
    if not props:
        raise ToolkitError(f"{path}: the 'vertex' element declares no properties")
    # Refuse a count the file cannot hold before reading or allocating for it: a binary row is exactly its
    # bytes, an ASCII value at least one character and a separator.
    row = np.dtype([(name, t) for name, t in props]).itemsize if fmt != "ascii" else 2 * len(props)
    least = "at least " if fmt == "ascii" else ""
    check_declared_size(path, offset + n * row - (fmt == "ascii" and n > 0),
                        f"element 'vertex' (the header declares {n} vertices of {least}{row} bytes)")
    # The body's bytes (a binary vertex element's only: other elements may follow), ASCII's parse, and a
    # float64 copy per property.
    size = n * row if fmt != "ascii" else Path(path).stat().st_size - offset
    extra = Path(path).stat().st_size - offset - size
    if fmt != "ascii" and len(elements) == 1 and extra >= row > 0:  # a stray newline is no row; a whole row is
        raise ToolkitError(f"{path}: {extra} bytes follow the {n} vertices the header declares ({row} bytes each) "
                           "and no other element: the header's vertex count is wrong, or the file is damaged")
    check_allocation(size + 2 * 8 * n * len(props), f"{path}: reading {n} vertices of {len(props)} properties")
    with open(path, "rb") as f:
        f.seek(offset)
        body = f.read(size)
    cols = _ascii_rows(body, n, props, path) if fmt == "ascii" else _binary_rows(body, n, props, fmt, path)
    return cols, comments


def _ascii_rows(body: bytes, n: int, props: list[tuple[str, str]], path: Path) -> dict[str, np.ndarray]:
    if n == 0:
        return {name: np.zeros(0) for name, _ in props}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpy notes that blank lines do not count towards max_rows: we want that
        try:
            arr = np.loadtxt(io.StringIO(body.decode("ascii", errors="replace")), dtype=np.float64, comments=None,
                             ndmin=2, max_rows=n)
        except ValueError as e:
            raise ToolkitError(f"{path}: vertex rows are not {len(props)} numbers each ({e})") from None
    if arr.shape[0] < n:
        raise ToolkitError(f"{path}: truncated: header declares {n} vertices, found {arr.shape[0]} rows")
    if arr.shape[1] != len(props):
        raise ToolkitError(f"{path}: vertex rows have {arr.shape[1]} values, header declares {len(props)}")
    return {name: arr[:, i] for i, (name, _) in enumerate(props)}


def _binary_rows(body: bytes, n: int, props: list[tuple[str, str]], fmt: str, path: Path) -> dict[str, np.ndarray]:
    endian = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(name, endian + t) for name, t in props])
    need = n * dtype.itemsize
    if len(body) < need:  # the file changed since its size was checked
        raise ToolkitError(
            f"{path}: truncated: header declares {n} vertices ({need} bytes), file has {len(body)} bytes of data"
        )
    rec = np.frombuffer(body, dtype=dtype, count=n)
    with np.errstate(invalid="ignore"):  # a signalling NaN warns when widened; NaNs are refused by name later
        return {name: rec[name].astype(np.float64) for name, _ in props}


def read_gaussian_ply(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor | None], dict]:
    """Read a 3DGS PLY (graphdeco layout, this toolkit's or another tool's) -> (tensors, metadata).

    The tensors are the pre-activation fields named as in ``GaussianScene`` (means, quats, log_scales,
    opacity_logits, features, part, sh: None without SH coefficients). Checked here: the file's layout, the
    metadata comment, and finite values in every property used; the scene's own rules are
    ``GaussianScene.validate``'s.
    """
    cols, comments = read_ply_vertices(path)
    required = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [p for p in required if p not in cols]
    if missing:
        raise ToolkitError(f"{path}: not a 3DGS PLY: missing vertex properties {missing}")
    meta, ours = _metadata(comments, path)
    n = len(cols["x"])
    feat_names = _indexed(cols, "feat_", path)
    rest_names = _indexed(cols, "f_rest_", path)
    dc_names = [f"f_dc_{i}" for i in range(3)]
    has_dc = all(k in cols for k in dc_names)
    if ours and meta.get("feature_dim", len(feat_names)) != len(feat_names):
        raise ToolkitError(f"{path}: the header's metadata says feature_dim={meta['feature_dim']}, the vertex has "
                           f"{len(feat_names)} feat_* properties")
    want_sh = has_dc and (meta.get("has_sh", True) if ours else True)
    # Our files name their feature width (0 included); a file without feat_* takes the DC colour as features.
    dc_colour = not feat_names and not (ours and "feature_dim" in meta)
    if dc_colour and not has_dc:
        raise ToolkitError(f"{path}: no colour: neither f_dc_0..2 nor feat_* vertex properties")
    used = required + feat_names + (dc_names if want_sh or dc_colour else []) + (rest_names if want_sh else [])
    t = _float32_columns(cols, used, path)
    stack = lambda names: torch.stack([t[x] for x in names], 1) if names else torch.zeros(n, 0)  # noqa: E731
    sh = _sh(stack(dc_names), stack(rest_names), path) if want_sh else None
    if dc_colour:
        features = sh_dc_to_rgb(stack(dc_names)).clamp(0, 1)
        meta.setdefault("feature_kind", "rgb")
    else:
        features = stack(feat_names)
    if "part" in cols and not np.isin(cols["part"], (0.0, 1.0, 2.0)).all():
        raise ToolkitError(f"{path}: vertex property 'part' must hold 0 (face), 1 (left eye) or 2 (right eye)")
    part = torch.from_numpy(cols["part"]).to(torch.int8) if "part" in cols else torch.zeros(n, dtype=torch.int8)
    for k in _RESERVED_META:
        meta.pop(k, None)
    tensors = dict(means=stack(["x", "y", "z"]), quats=stack([f"rot_{i}" for i in range(4)]),
                   log_scales=stack([f"scale_{i}" for i in range(3)]), opacity_logits=t["opacity"],
                   features=features, part=part, sh=sh)
    return tensors, meta


def _metadata(comments: list[str], path: Path) -> tuple[dict, bool]:
    """(the ``comment ditgaze {json}`` metadata, whether there was one: a file this toolkit wrote)."""
    meta, ours = {}, False
    for c in comments:
        if c.startswith(_META_TAG + " "):
            meta = parse_json_object(c[len(_META_TAG) + 1:], f"{path}: the ditgaze metadata comment of the PLY header")
            ours = True
    if ours:
        if not isinstance(meta.get("has_sh", False), bool):
            raise ToolkitError(f"{path}: ditgaze metadata has_sh: expected true or false, got {meta['has_sh']!r}")
        dim = meta.get("feature_dim", 0)
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 0:
            raise ToolkitError(f"{path}: ditgaze metadata feature_dim: expected an integer >= 0, got {dim!r}")
    return meta, ours


def _indexed(cols: dict[str, np.ndarray], prefix: str, path: Path) -> list[str]:
    """The properties ``{prefix}0 .. {prefix}{M-1}`` in index order; another name with the prefix, or a gap, is
    refused (a column in the wrong place would scramble every Gaussian's SH or features)."""
    names = [k for k in cols if k.startswith(prefix)]
    for k in names:
        if not re.fullmatch(r"0|[1-9][0-9]{0,8}", k[len(prefix):]):
            raise ToolkitError(f"{path}: vertex property {k!r}: expected {prefix}<index>, the index a number "
                               "without leading zeros")
    names.sort(key=lambda k: int(k[len(prefix):]))
    expected = [f"{prefix}{i}" for i in range(len(names))]
    if names != expected:
        gap = next(e for e, k in zip(expected, names) if e != k)
        raise ToolkitError(f"{path}: vertex properties {prefix}*: {len(names)} of them, but {gap!r} is missing "
                           f"(expected {prefix}0 .. {prefix}{len(names) - 1})")
    return names


def _float32_columns(cols: dict[str, np.ndarray], used: list[str], path: Path) -> dict[str, torch.Tensor]:
    """The properties a scene is built from, as float32 tensors. NaN or inf in any of them (an inf scale or a NaN
    position included) is refused here, naming the property: the renderer does not handle them, and a NaN
    Gaussian would vanish or blank the frame silently. Normals and unknown properties are never used, so their
    values do not matter."""
    out = {}
    for name in dict.fromkeys(used):
        with np.errstate(over="ignore", invalid="ignore"):  # counted just below
            v = cols[name].astype(np.float32)
        bad = int((~np.isfinite(v)).sum())
        if bad:
            raise ToolkitError(f"{path}: vertex property {name!r}: {bad} of {len(v)} values are NaN or inf (or "
                               "beyond float32); expected finite numbers")
        out[name] = torch.from_numpy(v)
    return out


def _sh(dc: torch.Tensor, rest: torch.Tensor, path: Path) -> torch.Tensor:
    """[N, K, 3] SH coefficients from the DC columns [N, 3] and the channel-major f_rest columns [N, 3(K-1)]."""
    if rest.shape[1] % 3:
        raise ToolkitError(f"{path}: {rest.shape[1]} f_rest properties is not a multiple of 3")
    k = 1 + rest.shape[1] // 3
    if int(round(math.sqrt(k))) ** 2 != k:
        raise ToolkitError(f"{path}: {k} SH coefficients per channel is not a square (degree+1)^2")
    rest = rest.reshape(dc.shape[0], 3, k - 1).transpose(1, 2)
    return torch.cat([dc[:, None, :], rest], 1)
