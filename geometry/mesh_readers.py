"""The mesh file readers behind :func:`geometry.mesh_files.load_mesh`: OBJ, OFF and PLY read strictly here,
STL and GLB through trimesh; each returns (vertices [V, 3] float64, faces [F, 3] int64, where) with ``where(r)``
naming vertex ``r``'s line or row for error messages."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from toolkit.errors import ToolkitError, one_line
from toolkit.limits import check_declared_size

# ---------------------------------------------------------------------------------------- readers
# OBJ, OFF and PLY are read here, strictly: trimesh accepts 0-based OBJ indices (silently shifting every face),
# headers declaring more rows than the file holds, PLY faces whose index is a float, or a vertex row read as a
# face. Every count a header declares is bounded by the file's size before anything is allocated for it, and
# every error names the file and the line (text) or row (binary). STL and GLB go through trimesh, then the same
# checks on what it returns.

NO_TRIANGLES = "no triangles (a point cloud? a Gaussian scene reads with `python -m toolkit info`)"


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


def read_with_trimesh(path: Path, data: bytes):
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


READERS = {".obj": _read_obj, ".off": _read_off, ".ply": _read_ply}
