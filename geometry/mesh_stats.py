"""Mesh I/O, inspection and comparison (what ``python -m geometry inspect`` / ``compare`` print).

Watertightness and winding come from trimesh (open3d's checks flag slivers as self-intersections).
Distances for :func:`compare_meshes` are exact point-to-triangle distances from open3d's RaycastingScene
(lazily imported) on area-uniform surface samples.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import torch

from toolkit.errors import ToolkitError, one_line
from toolkit.io import atomic_write_bytes, check_readable_file
from toolkit.limits import check_allocation, check_count, check_declared_size

MESH_EXTENSIONS = (".ply", ".obj", ".stl", ".off", ".glb")
# Surface samples per mesh in compare: open3d answers ~1e6 closest-point queries a second on one core, so
# 10^7 is about a minute; each sample holds ~0.5 KiB at the peak (float64 points, normals and temporaries).
MAX_SAMPLES = 10_000_000
BYTES_PER_SAMPLE = 512


def check_mesh(verts: torch.Tensor, faces: torch.Tensor, name: str = "mesh") -> None:
    """Raise a ToolkitError for wrong shapes, an empty mesh, NaN/inf vertices or out-of-range faces."""
    if verts.dim() != 2 or verts.shape[1] != 3 or faces.dim() != 2 or faces.shape[1] != 3:
        raise ToolkitError(f"{name}: expected verts [V, 3] and faces [F, 3], got {list(verts.shape)} and {list(faces.shape)}")
    if verts.shape[0] == 0 or faces.shape[0] == 0:
        raise ToolkitError(f"{name}: empty mesh ({verts.shape[0]} vertices, {faces.shape[0]} faces)")
    bad = ~torch.isfinite(verts).all(1)
    if bool(bad.any()):
        raise ToolkitError(f"{name}: {int(bad.sum())} vertices have NaN/inf coordinates")
    if int(faces.min()) < 0 or int(faces.max()) >= verts.shape[0]:
        raise ToolkitError(f"{name}: face indices must be in [0, {verts.shape[0]}), got [{int(faces.min())}, {int(faces.max())}]")


# ---------------------------------------------------------------------------------------- readers
# OBJ, OFF and PLY are read here, strictly: trimesh accepts 0-based OBJ indices (silently shifting every face),
# headers declaring more rows than the file holds, PLY faces whose index is a float, or a vertex row read as a
# face. Every count a header declares is bounded by the file's size before anything is allocated for it, and
# every error names the file and the line (text) or row (binary). STL and GLB go through trimesh, then the same
# checks on what it returns.

_F32_MAX = float(np.finfo(np.float32).max)
_NO_TRIANGLES = "no triangles (a point cloud? a Gaussian scene reads with `python -m toolkit info`)"


def _int_token(tok: str) -> int:
    """A face index token; ValueError unless an integer that fits int64 (a forged 10^30 must not overflow)."""
    i = int(tok)
    if not -(1 << 62) <= i <= 1 << 62:
        raise ValueError(tok)
    return i


def _text_lines(data: bytes) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of the non-blank lines, ``#`` comments removed; latin-1 so that no byte fails to
    decode (a stray byte then fails as a number, on its line)."""
    out = []
    for no, line in enumerate(data.decode("latin-1").split("\n"), 1):
        tok = (line[:line.index("#")] if "#" in line else line).split()
        if tok:
            out.append((no, tok))
    return out


def _faces_from_polygons(path, polys, where, n_verts: int, base: int = 0) -> np.ndarray:
    """Fan-triangulate polygons (a list of 0-based id sequences, one [F, k] array, or (lengths, ids)) -> faces
    [T, 3] int64, after checking every polygon has >= 3 vertices and every id is in [0, n_verts); ``where(i)`` names row i
    and ``base`` is the file's first index (messages quote the index as written)."""
    if isinstance(polys, tuple):  # (lengths [F], ids [sum of lengths])
        lens, flat = polys
    elif isinstance(polys, np.ndarray):
        lens, flat = np.full(polys.shape[0], polys.shape[1], np.int64), polys.reshape(-1).astype(np.int64)
    else:
        lens = np.fromiter(map(len, polys), np.int64, len(polys))
        flat = np.fromiter((i for p in polys for i in p), np.int64, int(lens.sum()))
    short = np.flatnonzero(lens < 3)
    if short.size:
        raise ToolkitError(f"{path}: {where(int(short[0]))}: a face needs at least 3 vertices, got {lens[short[0]]}")
    bad = np.flatnonzero((flat < 0) | (flat >= n_verts))
    if bad.size:
        row = int(np.searchsorted(np.cumsum(lens), bad[0], side="right"))
        raise ToolkitError(f"{path}: {where(row)}: vertex index {flat[bad[0]] + base} is out of range "
                           f"(the file has {n_verts} vertices, numbered from {base})")
    ntri = lens - 2
    starts = np.repeat(np.cumsum(lens) - lens, ntri)
    j = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    return np.stack([flat[starts], flat[starts + j], flat[starts + j + 1]], 1)


def _obj_statements(path: Path, data: bytes):
    """The ``v`` and ``f`` statements of an OBJ -> (vertex coordinate strings [[x, y, z]], their line numbers,
    face index strings [[i, ...]], their line numbers, the vertex count before each face)."""
    verts, vert_lines, faces, face_lines, seen = [], [], [], [], []
    for no, line in enumerate(data.decode("latin-1").split("\n"), 1):
        tok = (line[:line.index("#")] if "#" in line else line).split()
        if not tok:
            continue
        if tok[0] == "v":
            if len(tok) < 4:
                raise ToolkitError(f"{path}: line {no}: expected a vertex 'v x y z', got {' '.join(tok)[:60]!r}")
            verts.append(tok[1:4])
            vert_lines.append(no)
        elif tok[0] == "f":
            faces.append([t.split("/", 1)[0] for t in tok[1:]] if "/" in line else tok[1:])
            face_lines.append(no)
            seen.append(len(verts))
    return verts, vert_lines, faces, face_lines, seen


def _read_obj(path: Path, data: bytes):
    """Wavefront OBJ: ``v x y z`` and ``f i j k ...`` (1-based; negative counts back from the last vertex so far;
    ``i/t/n`` uses the position only). Other statements (vt, vn, g, usemtl, l ...) are skipped. Numbers are
    converted in bulk; a line is looked for only once a conversion failed."""
    verts, vert_lines, faces, face_lines, seen = _obj_statements(path, data)
    try:
        v = np.array(verts, np.float64).reshape(-1, 3)
    except ValueError:
        r = next((r for r, xyz in enumerate(verts) if not all(_is_float(x) for x in xyz)), 0)
        raise ToolkitError(f"{path}: line {vert_lines[r]}: expected a vertex 'v x y z', got "
                           f"{' '.join(verts[r])[:60]!r}") from None
    lens = np.fromiter(map(len, faces), np.int64, len(faces))
    try:
        flat = np.array([_int_token(t) for p in faces for t in p], np.int64)
    except ValueError:
        r = next((r for r, p in enumerate(faces) if not all(_is_int(t) for t in p)), 0)
        raise ToolkitError(f"{path}: line {face_lines[r]}: expected face indices 'f i j k' (or i/t/n), "
                           f"got {' '.join(faces[r])[:40]!r}") from None
    before = np.repeat(np.array(seen, np.int64), lens)
    bad = np.flatnonzero((flat == 0) | (-flat > before))
    if bad.size:  # a positive index past the end is found with the other formats' checks, below
        r = int(np.searchsorted(np.cumsum(lens), bad[0], side="right"))
        raise ToolkitError(f"{path}: line {face_lines[r]}: face index {flat[bad[0]]} is out of range (OBJ indices "
                           f"start at 1; negative ones count back from the {seen[r]} vertices so far)")
    flat = np.where(flat > 0, flat - 1, before + flat)
    f = _faces_from_polygons(path, (lens, flat), lambda r: f"line {face_lines[r]}", v.shape[0], base=1)
    return v, f, lambda r: f"line {vert_lines[r]}"


def _is_float(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _is_int(text: str) -> bool:
    try:
        _int_token(text)
        return True
    except ValueError:
        return False


def _off_counts(path: Path, lines) -> tuple[int, int, int]:
    """OFF header -> (vertices, faces, index of the first vertex line); counts may follow 'OFF' on its line."""
    head = lines[0][1][0] if lines else ""
    if not (head.endswith("OFF") and set(head[:-3]) <= set("STCN")):
        raise ToolkitError(f"{path}: not an OFF file (expected 'OFF' on the first line, got {head[:20]!r})")
    rest, at = lines[0][1][1:], 1
    if not rest and len(lines) > 1:
        rest, at = lines[1][1], 2
    if rest[:1] == ["BINARY"]:
        raise ToolkitError(f"{path}: binary OFF is not supported; write an ASCII OFF, PLY or OBJ")
    try:
        nv, nf = (int(t) for t in rest[:2])
    except ValueError:
        nv = nf = -1
    if len(rest) < 2 or not (0 <= nv <= 1 << 62 and 0 <= nf <= 1 << 62):
        raise ToolkitError(f"{path}: line {lines[at - 1][0]}: expected the counts 'vertices faces edges', "
                           f"got {' '.join(rest)[:60]!r}")
    # The smallest vertex line is "0 0 0\n" (6 bytes) and the smallest face "3 0 1 2\n" (8).
    check_declared_size(path, 6 * nv + 8 * nf - 1, f"the OFF header's {nv} vertices and {nf} faces")
    return nv, nf, at


def _read_off(path: Path, data: bytes):
    """ASCII OFF (and COFF/NOFF/STOFF: extra columns skipped): counts, vertex lines, 'n i1 .. in' face lines."""
    lines = _text_lines(data)
    nv, nf, at = _off_counts(path, lines)
    if len(lines) - at != nv + nf:
        have = len(lines) - at
        raise ToolkitError(f"{path}: the header declares {nv} vertices and {nf} faces ({nv + nf} lines) but "
                           f"{have} follow (truncated, or a count in its header is wrong)")
    rows, polys = lines[at:at + nv], lines[at + nv:]
    try:
        v = np.array([tok[:3] for _, tok in rows], np.float64).reshape(nv, 3)
    except ValueError:
        no, tok = next(((no, tok) for no, tok in rows if len(tok) < 3 or not all(map(_is_float, tok[:3]))), rows[0])
        raise ToolkitError(f"{path}: line {no}: expected a vertex 'x y z', got {' '.join(tok)[:60]!r}") from None
    room = np.array([len(tok) - 1 for _, tok in polys], np.int64)  # colours may follow the ids
    try:
        lens = np.array([_int_token(tok[0]) for _, tok in polys], np.int64).reshape(-1)
        if ((lens < 0) | (lens > room)).any():
            raise ValueError
        flat = np.array([_int_token(t) for (_, tok), k in zip(polys, lens) for t in tok[1:k + 1]], np.int64)
        if len(flat) != lens.sum():
            raise ValueError
    except ValueError:
        no, tok = next(((no, tok) for no, tok in polys if not _is_off_face(tok)), polys[0])
        raise ToolkitError(f"{path}: line {no}: expected a face 'n i1 ... in', got {' '.join(tok)[:60]!r}") from None
    f = _faces_from_polygons(path, (lens, flat), lambda r: f"line {polys[r][0]}", nv)
    return v, f, lambda r: f"line {rows[r][0]}"


def _is_off_face(tok: list[str]) -> bool:
    """Whether an OFF face line reads: a count k >= 0, then k integer ids (then anything, colours)."""
    try:
        k = int(tok[0])
        return 0 <= k <= len(tok) - 1 and all(_is_int(t) for t in tok[1:k + 1])
    except ValueError:
        return False


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_END_HEADER = re.compile(rb"^end_header[ \t\r]*$", re.M)


def _ply_header(path: Path, data: bytes):
    """-> (byte order: '' for ascii, '<' or '>'; elements [(name, count, [(property, type) or (property,
    (count type, item type))])]; offset of the body; number of header lines)."""
    end = _END_HEADER.search(data, 0, 1 << 20)
    if data[:4].rstrip() != b"ply" or end is None:
        raise ToolkitError(f"{path}: not a PLY file (expected 'ply' ... 'end_header' at its start)")
    body = min(end.end() + 1, len(data))
    lines = data[:end.start()].decode("latin-1").split("\n")
    fmt, elements = None, []
    for no, line in enumerate(lines[1:-1], 2):
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format" and len(tok) == 3 and tok[1] in _PLY_FORMATS:
            fmt = _PLY_FORMATS[tok[1]]
        elif tok[0] == "element" and len(tok) == 3 and re.fullmatch("[0-9]+", tok[2]):
            if int(tok[2]) > 1 << 62 or tok[1] in (e[0] for e in elements):
                raise ToolkitError(f"{path}: line {no}: element {tok[1]!r} declared twice or with a count over 2^62")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property" and elements and len(tok) == 3 and tok[1] in _PLY_TYPES:
            elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        elif (tok[0] == "property" and elements and len(tok) == 5 and tok[1] == "list" and tok[3] in _PLY_TYPES
              and _PLY_TYPES.get(tok[2], "f")[0] in "iu"):
            elements[-1][2].append((tok[4], (_PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]])))
        else:
            raise ToolkitError(f"{path}: line {no}: unexpected PLY header line {line.strip()[:60]!r}")
    if fmt is None:
        raise ToolkitError(f"{path}: no 'format ascii|binary_little_endian|binary_big_endian 1.0' line in its header")
    empty = [name for name, _, props in elements if not props]
    if empty:
        raise ToolkitError(f"{path}: element {empty[0]!r} has no properties in its header")
    return fmt, elements, body, data[:body].count(b"\n")


def _ply_min_bytes(order: str, elements) -> int:
    """The fewest bytes a body can take for the rows the header declares (lists may be empty)."""
    total = 0
    for _, count, props in elements:
        if order:
            row = sum(np.dtype(t if isinstance(t, str) else t[0]).itemsize for _, t in props)
        else:  # a token and a separator per property
            row = 2 * len(props)
        total += count * row
    return total


def _ply_ascii_row(path: Path, no: int, tok: list[str], props) -> list:
    """One row (a line) -> a value per property: a float, or a list (ints for integer items)."""
    vals, i = [], 0
    try:
        for _, t in props:
            if isinstance(t, str):
                vals.append(float(tok[i]))
                i += 1
                continue
            k = int(tok[i])
            item = _int_token if t[1][0] in "iu" else float
            vals.append([item(x) for x in tok[i + 1:i + 1 + k]])
            if k < 0 or len(vals[-1]) != k:
                raise ValueError
            i += 1 + k
        if i != len(tok):
            raise ValueError
    except (ValueError, IndexError):
        names = ", ".join(p if isinstance(t, str) else f"{p} (a count, then the items)" for p, t in props)
        raise ToolkitError(f"{path}: line {no}: expected the values of {names} as its header declares, "
                           f"got {' '.join(tok)[:60]!r}") from None
    return vals


def _ply_ascii(path: Path, data: bytes, body: int, header_lines: int, elements):
    """An ASCII body (one row per line) -> ({element: {property: values}}, where(element, row))."""
    rows = [(no + header_lines, tok) for no, tok in _text_lines(data[body:])]
    out, at, first = {}, 0, {}
    for name, count, props in elements:
        chunk = rows[at:at + count]
        if len(chunk) < count:
            raise ToolkitError(f"{path}: the header declares {count} {name} rows but the file ends after "
                               f"{len(chunk)} (truncated, or a count in its header is wrong)")
        vals = [_ply_ascii_row(path, no, tok, props) for no, tok in chunk]
        out[name] = {p: [v[j] for v in vals] for j, (p, _) in enumerate(props)}
        first[name] = at
        at += count
    if at < len(rows):
        raise ToolkitError(f"{path}: line {rows[at][0]}: more rows than the header declares")
    return out, lambda name, r: f"line {rows[first[name] + r][0]}"


def _ply_truncated(path: Path, name: str, row: int, count: int) -> ToolkitError:
    return ToolkitError(f"{path}: the file ends in {name} row {row} of the {count} its header declares "
                        f"(truncated, or a count in its header is wrong)")


def _ply_first_row_counts(path: Path, data: bytes, off: int, order: str, name: str, count: int, props) -> list[int]:
    """The lengths of the first row's lists (rows are read in one go when every row has the same)."""
    counts = []
    for _, t in props:
        size = np.dtype(t if isinstance(t, str) else t[0]).itemsize
        if off + size > len(data):
            raise _ply_truncated(path, name, 0, count)
        if not isinstance(t, str):
            counts.append(max(0, int(np.frombuffer(data, order + t[0], 1, off)[0])))
            size += counts[-1] * np.dtype(t[1]).itemsize
        off += size
        if off > len(data):  # before a row dtype of that size is built
            raise _ply_truncated(path, name, 0, count)
    return counts


def _ply_binary_element(path: Path, data: bytes, off: int, order: str, name: str, count: int, props):
    """One binary element -> ({property: [N] array, or [N, k] array / list of lists for a list}, next offset)."""
    lists_n = sum(not isinstance(t, str) for _, t in props)
    counts = _ply_first_row_counts(path, data, off, order, name, count, props) if count else [0] * lists_n
    fields, lists, k = [], [], iter(counts)
    for j, (_, t) in enumerate(props):
        if isinstance(t, str):
            fields.append((f"p{j}", order + t))
        else:
            n = next(k)
            fields += [(f"n{j}", order + t[0]), (f"p{j}", order + t[1], (n,))]
            lists.append((f"n{j}", n))
    dt = np.dtype(fields)
    if off + count * dt.itemsize <= len(data):
        arr = np.frombuffer(data, dt, count, off)
        if all(bool((arr[f] == n).all()) for f, n in lists):
            return {p: arr[f"p{j}"] for j, (p, _) in enumerate(props)}, off + count * dt.itemsize
    return _ply_binary_rows(path, data, off, order, name, count, props)


def _ply_binary_rows(path: Path, data: bytes, off: int, order: str, name: str, count: int, props):
    """Row-by-row reading, for lists of varying lengths (and to name the row where a file ends early)."""
    out: dict = {p: [] for p, _ in props}
    for r in range(count):
        for p, t in props:
            head = t if isinstance(t, str) else t[0]
            size = np.dtype(head).itemsize
            if off + size > len(data):
                raise _ply_truncated(path, name, r, count)
            v = np.frombuffer(data, order + head, 1, off)[0]
            off += size
            if not isinstance(t, str):
                n, size = int(v), np.dtype(t[1]).itemsize
                if n < 0:
                    raise ToolkitError(f"{path}: {name} row {r}: a list of {n} items")
                if off + n * size > len(data):
                    raise _ply_truncated(path, name, r, count)
                v = np.frombuffer(data, order + t[1], n, off).tolist()
                off += n * size
            out[p].append(v)
    return out, off


def _ply_binary(path: Path, data: bytes, body: int, order: str, elements):
    """A binary body -> ({element: {property: values}}, where(element, row))."""
    out, off = {}, body
    for name, count, props in elements:
        out[name], off = _ply_binary_element(path, data, off, order, name, count, props)
    if data[off:].strip():
        raise ToolkitError(f"{path}: {len(data) - off} bytes follow the rows its header declares "
                           f"(a count in its header is wrong)")
    return out, lambda name, r: f"{name} row {r}"


def _read_ply(path: Path, data: bytes):
    """PLY (ASCII or binary): the vertex element's x, y, z and the face element's vertex_indices lists."""
    order, elements, body, header_lines = _ply_header(path, data)
    types = {name: dict(props) for name, _, props in elements}
    if not all(isinstance(types.get("vertex", {}).get(c), str) for c in "xyz"):
        raise ToolkitError(f"{path}: no vertex element with scalar x, y, z properties in its header")
    face_t = types.get("face", {})
    key = next((k for k in ("vertex_indices", "vertex_index") if k in face_t), None)
    if key is not None and (isinstance(face_t[key], str) or face_t[key][1][0] not in "iu"):
        raise ToolkitError(f"{path}: the face element's {key} must be a list of integers in its header")
    counts = ", ".join(f"{count} {name}" for name, count, _ in elements)
    check_declared_size(path, body + _ply_min_bytes(order, elements), f"the PLY header's rows ({counts})")
    els, where = _ply_binary(path, data, body, order, elements) if order else _ply_ascii(
        path, data, body, header_lines, elements)
    with np.errstate(invalid="ignore"):  # a signalling NaN warns as it widens; it is refused as non-finite after
        v = np.stack([np.asarray(els["vertex"][c], np.float64).reshape(-1) for c in "xyz"], 1)
    polys = els["face"][key] if key is not None else []
    f = _faces_from_polygons(path, polys, lambda r: where("face", r), v.shape[0])
    return v, f, lambda r: where("vertex", r)


def _read_with_trimesh(path: Path, data: bytes):
    """STL and GLB through trimesh (their counts are checked against the data by trimesh itself)."""
    import trimesh

    try:
        m = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for garbled files
        raise ToolkitError(f"{path}: not a readable mesh ({type(e).__name__}: {one_line(e, 120)})") from None
    if not isinstance(m, trimesh.Trimesh):
        raise ToolkitError(f"{path}: not a triangle mesh (got {type(m).__name__})")
    v, f = np.asarray(m.vertices, np.float64).reshape(-1, 3), np.asarray(m.faces, np.int64).reshape(-1, 3)
    return v, _faces_from_polygons(path, f, lambda r: f"face {r}", v.shape[0]), lambda r: f"vertex {r}"


_READERS = {".obj": _read_obj, ".off": _read_off, ".ply": _read_ply}


def load_mesh(path: str | os.PathLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a triangle mesh file -> (verts [V, 3] float32, faces [F, 3] int64), validated: finite vertices in
    float32's range, every face index in range, at least one triangle (polygons are fan-triangulated)."""
    path = check_readable_file(path, "mesh file")
    ext = path.suffix.lower()
    if ext not in MESH_EXTENSIONS:
        raise ToolkitError(f"{path}: unknown mesh extension {ext!r}; expected one of {MESH_EXTENSIONS}")
    data = path.read_bytes()
    v, f, where = _READERS.get(ext, _read_with_trimesh)(path, data)
    if f.shape[0] == 0:  # a point cloud, or a header with no faces
        raise ToolkitError(f"{path}: {_NO_TRIANGLES}")
    bad = np.flatnonzero(~np.isfinite(v).all(1))
    if bad.size:
        raise ToolkitError(f"{path}: {where(int(bad[0]))}: vertex coordinates must be finite, got "
                           f"{v[bad[0]].tolist()} ({bad.size} NaN/inf vertices)")
    big = np.flatnonzero((np.abs(v) > _F32_MAX).any(1))
    if big.size:  # meshes are float32 from here on: such a vertex would become inf
        raise ToolkitError(f"{path}: {where(int(big[0]))}: vertex coordinate {np.abs(v[big[0]]).max():.3g} is "
                           f"outside float32's range (|x| <= {_F32_MAX:.3g})")
    verts, faces = torch.from_numpy(v).float(), torch.from_numpy(np.ascontiguousarray(f, np.int64))
    check_mesh(verts, faces, str(path))
    return verts, faces


def check_mesh_extension(path: str | os.PathLike) -> None:
    """Raise a ToolkitError unless ``path``'s extension is a mesh format :func:`save_mesh` writes."""
    ext = Path(path).suffix.lower()
    if ext not in MESH_EXTENSIONS:
        raise ToolkitError(f"{path}: unknown mesh extension {ext!r}; expected one of {MESH_EXTENSIONS}")


def save_mesh(path: str | os.PathLike, verts: torch.Tensor, faces: torch.Tensor) -> None:
    """Write a mesh atomically; the format follows the extension (.ply binary, .obj, .stl, .off, .glb)."""
    import trimesh

    path = Path(path)
    check_mesh_extension(path)
    check_mesh(verts, faces, str(path))
    m = trimesh.Trimesh(verts.detach().cpu().double().numpy(), faces.cpu().numpy(), process=False)
    data = m.export(file_type=path.suffix.lower()[1:])
    atomic_write_bytes(path, data.encode() if isinstance(data, str) else data)


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges [E, 2] and how many faces use each [E] (int64 keys, no row-unique)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    e.sort(1)
    n = int(faces.max()) + 1
    keys, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)
    return np.stack([keys // n, keys % n], 1), counts


def inspect_mesh(verts: torch.Tensor, faces: torch.Tensor) -> dict:
    """Topology and geometry statistics of a triangle mesh, as a JSON-able dict."""
    import trimesh

    check_mesh(verts, faces)
    v = verts.detach().cpu().double().numpy()
    f = faces.cpu().numpy().astype(np.int64)
    m = trimesh.Trimesh(v, f, process=False)
    edges, counts = _edges(f)
    lengths = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    lo, hi = v.min(0), v.max(0)
    diag = float(np.linalg.norm(hi - lo))
    area = m.area_faces
    used = np.unique(f)
    n_comp = len(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(f)), min_len=1))
    watertight = bool(m.is_watertight)
    euler = int(len(used) - len(edges) + len(f))
    stats = {
        "vertices": int(v.shape[0]),
        "unreferenced_vertices": int(v.shape[0] - len(used)),
        "faces": int(f.shape[0]),
        "edges": int(len(edges)),
        "components": n_comp,
        "watertight": watertight,
        "winding_consistent": bool(m.is_winding_consistent),
        "boundary_edges": int((counts == 1).sum()),
        "non_manifold_edges": int((counts > 2).sum()),
        "euler_characteristic": euler,
        "genus": int((2 * n_comp - euler) // 2) if watertight else None,
        "area": float(area.sum()),
        "volume": float(m.volume) if watertight else None,
        "orientation": ("outward" if m.volume > 0 else "inward") if watertight and m.is_winding_consistent else None,
        "bbox_min": lo.tolist(),
        "bbox_max": hi.tolist(),
        "bbox_diagonal": diag,
        "edge_length": {"min": float(lengths.min()), "mean": float(lengths.mean()), "max": float(lengths.max())},
        # Relative to the diagonal with no absolute floor: a floor would call every face of a tiny mesh degenerate.
        "degenerate_faces": int((area <= 1e-12 * diag**2).sum()),
    }
    return stats


def format_stats(stats: dict) -> str:
    """Human-readable lines for :func:`inspect_mesh` output."""
    lines = []
    for k, v in stats.items():
        if isinstance(v, dict):
            v = ", ".join(f"{a} {b:.4g}" for a, b in v.items())
        elif isinstance(v, list):
            v = "[" + ", ".join(f"{x:.4g}" for x in v) + "]"
        elif isinstance(v, float):
            v = f"{v:.6g}"
        lines.append(f"{k:<22} {v}")
    return "\n".join(lines)


def sample_surface(verts: torch.Tensor, faces: torch.Tensor, n: int, seed: int = 0, name: str = "mesh"
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Area-uniform surface samples -> (points [n, 3] float64, unit face normals [n, 3])."""
    n = check_count(n, "samples", 1, MAX_SAMPLES, "a number of surface samples")
    a, b, c = (verts[faces[:, i]].double() for i in range(3))
    cr = torch.linalg.cross(b - a, c - a)
    area = cr.norm(dim=-1)
    if not bool(area.sum() > 0):
        raise ToolkitError(f"{name}: zero surface area (every triangle is degenerate)")
    g = torch.Generator().manual_seed(seed)
    if area.shape[0] <= 1 << 24:  # torch.multinomial's limit on categories
        idx = torch.multinomial(area, n, replacement=True, generator=g)
    else:
        cdf = area.cumsum(0)
        idx = torch.searchsorted(cdf, torch.rand(n, generator=g, dtype=torch.float64) * cdf[-1]).clamp_max(len(area) - 1)
    u, w = torch.rand(n, 1, generator=g, dtype=torch.float64), torch.rand(n, 1, generator=g, dtype=torch.float64)
    flip = (u + w) > 1
    u, w = torch.where(flip, 1 - u, u), torch.where(flip, 1 - w, w)
    p = a[idx] + u * (b[idx] - a[idx]) + w * (c[idx] - a[idx])
    # Divided by the area itself, not a floor: at a 1e-30 scale every area is below any fixed floor.
    nrm = cr[idx] / torch.where(area[idx] > 0, area[idx], 1.0)[:, None]
    return p, nrm


def _closest(verts: torch.Tensor, faces: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact distances from q [P, 3] to the mesh surface and the unit normal of the closest triangle."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(verts.detach().cpu().numpy().astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(faces.cpu().numpy().astype(np.int32))
    scene.add_triangles(mesh)
    res = scene.compute_closest_points(o3d.core.Tensor(q.cpu().numpy().astype(np.float32)))
    pts = torch.from_numpy(res["points"].numpy()).double()
    fid = torch.from_numpy(res["primitive_ids"].numpy().astype(np.int64))
    a, b, c = (verts[faces[:, i]].double() for i in range(3))
    fn = torch.nn.functional.normalize(torch.linalg.cross(b - a, c - a), dim=-1)
    return (pts - q.double()).norm(dim=-1), fn[fid]


def _normalized(va: torch.Tensor, vb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Both meshes' vertices moved by the centre of their joint bounding box and divided by its diagonal
    (float64) -> (A, B, the diagonal). open3d measures in float32: in this frame its ~1e-7 relative precision
    holds at any scale (at 1e-30 the raw squared distances underflow, at 1e30 they overflow)."""
    va, vb = va.detach().double(), vb.detach().double()
    lo = torch.minimum(va.min(0).values, vb.min(0).values)
    hi = torch.maximum(va.max(0).values, vb.max(0).values)
    c, s = (lo + hi) / 2, float((hi - lo).norm())
    s = s if s > 0 else 1.0
    return (va - c) / s, (vb - c) / s, s


def compare_meshes(va: torch.Tensor, fa: torch.Tensor, vb: torch.Tensor, fb: torch.Tensor, n_samples: int = 20000,
                   seed: int = 0, names: tuple[str, str] = ("mesh A", "mesh B")) -> dict:
    """Symmetric surface distances between meshes A and B (``names`` name them in errors).

    Returns chamfer (mean of the two mean point-to-surface distances), hausdorff (max of both maxima),
    the same relative to A's bbox diagonal, and normal_consistency (mean |n_A . n_B| at closest points,
    1 = identical orientation field, ignoring the sign so inward/outward winding does not matter).
    """
    check_mesh(va, fa, names[0])
    check_mesh(vb, fb, names[1])
    n_samples = check_count(n_samples, "samples", 1, MAX_SAMPLES, "a number of surface samples")
    check_allocation(2 * n_samples * BYTES_PER_SAMPLE, f"comparing meshes on {n_samples} samples", "lower --samples")
    na_v, nb_v, scale = _normalized(va, vb)
    pa, na = sample_surface(na_v, fa, n_samples, seed, names[0])
    pb, nb = sample_surface(nb_v, fb, n_samples, seed + 1, names[1])
    d_ab, n_ab = _closest(nb_v, fb, pa)
    d_ba, n_ba = _closest(na_v, fa, pb)
    d_ab, d_ba = d_ab * scale, d_ba * scale
    diag = float((va.double().max(0).values - va.double().min(0).values).norm())
    chamfer = 0.5 * (float(d_ab.mean()) + float(d_ba.mean()))
    haus = max(float(d_ab.max()), float(d_ba.max()))
    nc = 0.5 * (float((na * n_ab).sum(-1).abs().mean()) + float((nb * n_ba).sum(-1).abs().mean()))
    rel = diag if diag > 0 else math.nan  # A has area, so a zero diagonal cannot happen
    return {"chamfer": chamfer, "hausdorff": haus, "chamfer_rel_diag": chamfer / rel,
            "hausdorff_rel_diag": haus / rel, "normal_consistency": nc,
            "mean_a_to_b": float(d_ab.mean()), "mean_b_to_a": float(d_ba.mean()), "bbox_diagonal_a": diag,
            "samples": n_samples}
