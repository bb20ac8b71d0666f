"""3DGS PLY files in the graphdeco layout (the format of the original 3D Gaussian Splatting code).

One ``vertex`` element, every property float32, values **pre-activation**::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3

``f_rest`` is channel-major (all R coefficients, then G, then B); ``rot`` is wxyz; ``scale`` is log-scale;
``opacity`` is the logit. This toolkit adds ``feat_0..feat_{D-1}`` (the scene's features, so non-RGB
features and exact RGB round-trip) and ``part``, plus a ``comment ditgaze {json}`` header line with the
scene metadata. Files from other tools load too: features become the SH DC colour
``clamp(0.5 + C0 · f_dc, 0, 1)`` and all SH coefficients are kept.

The reader accepts ``binary_little_endian``, ``binary_big_endian`` and ``ascii`` PLY with any scalar types.

This module speaks plain tensors (the pre-activation fields of ``toolkit.scene.GaussianScene``, by name) and
knows nothing of the scene class: ``GaussianScene.to_ply`` / ``from_ply`` call it, never the other way round.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.io import atomic_write, check_readable_file

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi)), the degree-0 SH basis constant
_META_TAG = "ditgaze"
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_MAX_HEADER_BYTES = 1 << 20


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return dc * SH_C0 + 0.5


def write_gaussian_ply(path: str | os.PathLike, tensors: dict[str, torch.Tensor], metadata: dict) -> None:
    """Write Gaussians to ``path`` as a binary little-endian 3DGS PLY, atomically.

    ``tensors``: the pre-activation fields, checked by the caller (``GaussianScene.tensors()``): means [N, 3],
    quats [N, 4] wxyz, log_scales [N, 3], opacity_logits [N], features [N, D], part [N] int, optional
    sh [N, K, 3]. ``metadata``: JSON-able, written to the header (``feature_kind`` "rgb", the default, makes
    the first three features the SH DC colour when there is no ``sh``).
    """
    sh_coeffs = tensors.get("sh")
    n = tensors["means"].shape[0]
    d = tensors["features"].shape[1]
    cols: list[tuple[str, torch.Tensor]] = []
    f32 = lambda t: t.detach().to("cpu", torch.float32)  # noqa: E731
    means = f32(tensors["means"])
    cols += [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
    cols += [(f"n{a}", torch.zeros(n)) for a in "xyz"]
    if sh_coeffs is not None:
        sh = f32(sh_coeffs)
        dc, rest = sh[:, 0, :], sh[:, 1:, :].transpose(1, 2).reshape(n, -1)  # channel-major
    else:
        feats = f32(tensors["features"])
        dc = rgb_to_sh_dc(feats[:, :3]) if (d >= 3 and metadata.get("feature_kind", "rgb") == "rgb") else torch.zeros(n, 3)
        if dc.shape[1] < 3:
            dc = torch.cat([dc, torch.zeros(n, 3 - dc.shape[1])], 1)
        rest = torch.zeros(n, 0)
    cols += [(f"f_dc_{i}", dc[:, i]) for i in range(3)]
    cols += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    cols += [("opacity", f32(tensors["opacity_logits"]))]
    ls = f32(tensors["log_scales"])
    cols += [(f"scale_{i}", ls[:, i]) for i in range(3)]
    q = f32(tensors["quats"])
    cols += [(f"rot_{i}", q[:, i]) for i in range(4)]
    feats = f32(tensors["features"])
    cols += [(f"feat_{i}", feats[:, i]) for i in range(d)]
    cols += [("part", tensors["part"].to("cpu", torch.float32))]

    meta = dict(metadata)
    meta["has_sh"] = sh_coeffs is not None
    meta["feature_dim"] = d
    meta_json = json.dumps(meta, sort_keys=True, separators=(",", ":"))
    if "\n" in meta_json or "\r" in meta_json:
        raise ToolkitError("scene metadata cannot be written to a PLY header (contains a newline)")
    if len(meta_json) > _MAX_HEADER_BYTES // 2:  # readers read a bounded header
        raise ToolkitError(f"scene metadata cannot be written to a PLY header: {len(meta_json)} bytes of JSON, "
                           f"expected at most {_MAX_HEADER_BYTES // 2}")
    header = ["ply", "format binary_little_endian 1.0", f"comment {_META_TAG} {meta_json}", f"element vertex {n}"]
    header += [f"property float {name}" for name, _ in cols]
    header += ["end_header"]
    data = np.stack([c.numpy() for _, c in cols], axis=1).astype("<f4") if n else np.zeros((0, len(cols)), "<f4")
    with atomic_write(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(data).tobytes())


def _parse_header(raw: bytes, path: Path) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]], list[str], int]:
    # The header ends at the first *line* "end_header": a comment may contain the word.
    m = re.search(rb"\nend_header[ \t]*\r?(\n|$)", raw)
    if not raw.startswith(b"ply") or m is None:
        raise ToolkitError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header' within the first "
                           f"{len(raw)} bytes)")
    nl = m.end(1) - 1
    if not m.group(1):
        raise ToolkitError(f"{path}: truncated PLY header")
    try:
        text = raw[:nl].decode("ascii")
    except UnicodeDecodeError:
        raise ToolkitError(f"{path}: PLY header is not ASCII text") from None
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    comments: list[str] = []
    for lineno, line in enumerate(text.replace("\r", "").split("\n")[1:], start=2):
        parts = line.split()
        if not parts or parts[0] in ("end_header", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise ToolkitError(f"{path}: unsupported PLY format line {line!r}")
            fmt = parts[1]
        elif parts[0] == "comment":
            comments.append(line[len("comment "):])
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise ToolkitError(f"{path}: bad element line {lineno}: {line!r}")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ToolkitError(f"{path}: property before any element on line {lineno}")
            if len(parts) == 5 and parts[1] == "list":
                elements[-1][2].append((parts[4], "list:" + parts[2] + ":" + parts[3]))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
            else:
                raise ToolkitError(f"{path}: bad property line {lineno}: {line!r}")
            if [name for name, _ in elements[-1][2]].count(elements[-1][2][-1][0]) > 1:
                raise ToolkitError(f"{path}: property {elements[-1][2][-1][0]!r} of element {elements[-1][0]!r} "
                                   f"is declared twice (line {lineno})")
        else:
            raise ToolkitError(f"{path}: unexpected PLY header line {lineno}: {line!r}")
    if fmt is None:
        raise ToolkitError(f"{path}: PLY header has no format line")
    return fmt, elements, comments, nl + 1


def read_ply_vertices(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], list[str]]:
    """Read the ``vertex`` element of a PLY file -> ({property: float array [N]}, header comments)."""
    path = check_readable_file(path, "PLY file")
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER_BYTES)
        fmt, elements, comments, offset = _parse_header(head, path)
        f.seek(offset)
        body = f.read()
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise ToolkitError(f"{path}: PLY has no 'vertex' element")
    if names[0] != "vertex":
        raise ToolkitError(f"{path}: the 'vertex' element must come first for a Gaussian PLY")
    _, n, props = elements[0]
    if any(t.startswith("list:") for _, t in props):
        raise ToolkitError(f"{path}: list properties in the vertex element are not supported")
    if fmt == "ascii":
        rows = body.decode("ascii", errors="replace").split("\n")
        rows = [r for r in rows if r.strip()][:n]
        if len(rows) < n:
            raise ToolkitError(f"{path}: truncated: header declares {n} vertices, found {len(rows)} rows")
        try:
            arr = np.array([[float(v) for v in r.split()] for r in rows], dtype=np.float64).reshape(n, -1) if n \
                else np.zeros((0, len(props)))
        except ValueError:
            raise ToolkitError(f"{path}: vertex rows are not {len(props)} numbers each") from None
        if arr.shape[1] != len(props):
            raise ToolkitError(f"{path}: vertex rows have {arr.shape[1]} values, header declares {len(props)}")
        cols = {name: arr[:, i] for i, (name, _) in enumerate(props)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, endian + t) for name, t in props])
        need = n * dtype.itemsize
        if len(body) < need:
            raise ToolkitError(
                f"{path}: truncated: header declares {n} vertices ({need} bytes), file has {len(body)} bytes of data"
            )
        rec = np.frombuffer(body[:need], dtype=dtype, count=n)
        cols = {name: rec[name].astype(np.float64) for name, _ in props}
    return cols, comments


def read_gaussian_ply(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor | None], dict]:
    """Read a 3DGS PLY (graphdeco layout, this toolkit's or another tool's) -> (tensors, metadata).

    The tensors are the pre-activation fields named as in ``GaussianScene`` (means, quats, log_scales,
    opacity_logits, features, part, sh: None without SH coefficients), unchecked beyond the file's layout.
    """
    cols, comments = read_ply_vertices(path)
    required = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [p for p in required if p not in cols]
    if missing:
        raise ToolkitError(f"{path}: not a 3DGS PLY: missing vertex properties {missing}")
    meta: dict = {}
    ours = False
    for c in comments:
        if c.startswith(_META_TAG + " "):
            try:
                meta = json.loads(c[len(_META_TAG) + 1:])
                ours = True
            except json.JSONDecodeError:
                raise ToolkitError(f"{path}: corrupt ditgaze metadata comment in the PLY header") from None
    t = lambda name: torch.from_numpy(cols[name].astype(np.float32))  # noqa: E731
    stack = lambda names: torch.stack([t(x) for x in names], 1) if names else None  # noqa: E731
    n = len(cols["x"])
    means = stack(["x", "y", "z"])
    quats = stack([f"rot_{i}" for i in range(4)])
    log_scales = stack([f"scale_{i}" for i in range(3)])
    opacity = t("opacity")
    feat_names = sorted((k for k in cols if k.startswith("feat_")), key=lambda k: int(k[5:]) if k[5:].isdigit() else -1)
    dc_names = [f"f_dc_{i}" for i in range(3)]
    has_dc = all(k in cols for k in dc_names)
    rest_names = sorted((k for k in cols if k.startswith("f_rest_")), key=lambda k: int(k[7:]))
    sh = None
    want_sh = meta.get("has_sh", True) if ours else True
    if has_dc and want_sh:
        if len(rest_names) % 3:
            raise ToolkitError(f"{path}: {len(rest_names)} f_rest properties is not a multiple of 3")
        k = 1 + len(rest_names) // 3
        if int(round(math.sqrt(k))) ** 2 != k:
            raise ToolkitError(f"{path}: {k} SH coefficients per channel is not a square (degree+1)^2")
        dc = stack(dc_names)
        rest = stack(rest_names).reshape(n, 3, k - 1).transpose(1, 2) if rest_names else torch.zeros(n, 0, 3)
        sh = torch.cat([dc[:, None, :], rest], 1)
    if feat_names:
        features = stack(feat_names)
    elif has_dc:
        features = sh_dc_to_rgb(stack(dc_names)).clamp(0, 1)
        meta.setdefault("feature_kind", "rgb")
    else:
        raise ToolkitError(f"{path}: no colour: neither f_dc_0..2 nor feat_* vertex properties")
    if "part" in cols and not np.isin(cols["part"], (0.0, 1.0, 2.0)).all():
        raise ToolkitError(f"{path}: vertex property 'part' must hold 0 (face), 1 (left eye) or 2 (right eye)")
    part = t("part").to(torch.int8) if "part" in cols else torch.zeros(n, dtype=torch.int8)
    for k in ("has_sh", "feature_dim", "format", "format_version"):
        meta.pop(k, None)
    tensors = dict(means=means, quats=quats, log_scales=log_scales, opacity_logits=opacity, features=features,
                   part=part, sh=sh)
    return tensors, meta
