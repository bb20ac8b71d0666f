"""The bad-input corpus of ``python -m geometry``: every subcommand, each way its input can be wrong.

Each case must be refused before any work: exit 2, one ``error:`` line naming the file or flag and what was
expected, no traceback, inputs and the output folder untouched, within a second or two.
"""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
import torch
import trimesh

from geometry.mesh_files import save_mesh
from tests.fuzz.cli import assert_refused

TRI = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
PLY_HEAD = ("ply\nformat {fmt} 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n"
            "element face {nf}\nproperty list uchar int vertex_indices\nend_header\n")


def _files(d: Path) -> dict[str, Path]:
    """Every input the corpus names, written into ``d``."""
    from geometry.sdf import SDFNet, SDFNetConfig
    from toolkit.io import load_checkpoint, save_checkpoint

    m = trimesh.creation.icosphere(1)
    save_mesh(d / "sphere.ply", torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces))
    text = {
        "zero.obj": TRI + "f 0 1 2\n",
        "oor.obj": TRI + "f 1 2 5\n",
        "back.obj": TRI + "f -1 -2 -4\n",
        "two.obj": TRI + "f 1 2\n",
        "big.off": "OFF\n3 99999999 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
        "short.off": "OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
        "nan.ply": PLY_HEAD.format(fmt="ascii", nv=3, nf=1) + "0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n",
        "huge.ply": PLY_HEAD.format(fmt="ascii", nv=3, nf=1) + "0 0 0\n1e39 0 0\n0 1 0\n3 0 1 2\n",
        "noface.ply": PLY_HEAD.format(fmt="ascii", nv=3, nf=0) + "0 0 0\n1 0 0\n0 1 0\n",
        "floatidx.ply": PLY_HEAD.format(fmt="ascii", nv=3, nf=1) + "0 0 0\n1 0 0\n0 1 0\n3 0 1.5 2\n",
        "point.obj": "v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n",
        "mesh.xyz": "0 0 0\n",
    }
    for name, body in text.items():
        (d / name).write_text(body)
    head = PLY_HEAD.format(fmt="binary_little_endian", nv=3, nf=2).encode()
    (d / "cut.ply").write_bytes(head + struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack("<B3i", 3, 0, 1, 2))
    net = SDFNet(SDFNetConfig(hidden=16, feature_dim=4))
    net.save(d / "sdf.safetensors")
    state, info = load_checkpoint(d / "sdf.safetensors")
    save_checkpoint(d / "wide.safetensors", state, {**info, "config": {**info["config"], "hidden": 32}})
    save_checkpoint(d / "fine.safetensors", state, {**info, "config": {**info["config"], "grid_res": 100_000}})
    (d / "out").mkdir()
    return {p.name: p for p in d.iterdir()}


# (id, argv with {file} placeholders, regex the error line must match, environment)
CASES = [
    # inspect: every reader's refusals, naming the file and the line or row
    ("inspect-obj-zero-index", ["inspect", "{zero.obj}"], r"zero\.obj: line 4: face index 0 is out of range \(OBJ indices start at 1", {}),
    ("inspect-obj-index-past-end", ["inspect", "{oor.obj}"], r"oor\.obj: line 4: vertex index 5 is out of range", {}),
    ("inspect-obj-relative-before-first", ["inspect", "{back.obj}"], r"back\.obj: line 4: face index -4 is out of range", {}),
    ("inspect-obj-two-vertex-face", ["inspect", "{two.obj}"], r"two\.obj: line 4: a face needs at least 3 vertices, got 2", {}),
    ("inspect-off-forged-face-count", ["inspect", "{big.off}"], r"big\.off: the OFF header's 3 vertices and 99999999 faces needs", {}),
    ("inspect-off-missing-line", ["inspect", "{short.off}"], r"short\.off: the header declares 4 vertices and 1 faces", {}),
    ("inspect-ply-nan-vertex", ["inspect", "{nan.ply}"], r"nan\.ply: line 11: vertex coordinates must be finite", {}),
    ("inspect-ply-beyond-float32", ["inspect", "{huge.ply}"], r"huge\.ply: line 11: .* outside float32's range", {}),
    ("inspect-ply-no-faces", ["inspect", "{noface.ply}"], r"noface\.ply: no triangles", {}),
    ("inspect-ply-float-index", ["inspect", "{floatidx.ply}"], r"floatidx\.ply: line 13: expected the values of vertex_indices", {}),
    ("inspect-ply-binary-truncated", ["inspect", "{cut.ply}"], r"cut\.ply: the file ends in face row 1 of the 2 its header declares", {}),
    ("inspect-unknown-extension", ["inspect", "{mesh.xyz}"], r"mesh\.xyz: unknown mesh extension '\.xyz'", {}),
    ("inspect-missing-file", ["inspect", "{out}/none.ply"], r"none\.ply: no such mesh file", {}),
    # compare: the sample count, before either mesh is read
    ("compare-samples-1e11", ["compare", "{sphere.ply}", "{sphere.ply}", "--samples", "1e11"], r"--samples: expected a number of surface samples per mesh in \[1, 10000000\]", {}),
    ("compare-samples-zero", ["compare", "{sphere.ply}", "{sphere.ply}", "--samples", "0"], r"--samples: expected .* in \[1, 10000000\], got 0", {}),
    ("compare-samples-nan", ["compare", "{sphere.ply}", "{sphere.ply}", "--samples", "nan"], r"--samples: .* got nan", {}),
    ("compare-samples-fraction", ["compare", "{sphere.ply}", "{sphere.ply}", "--samples", "2.5"], r"--samples: .* got 2\.5", {}),
    ("compare-samples-not-a-number", ["compare", "{sphere.ply}", "{sphere.ply}", "--samples", "lots"], r"--samples: invalid number value: 'lots'", {}),
    ("compare-samples-over-memory", ["compare", "{sphere.ply}", "{sphere.ply}", "--samples", "1e7"], r"--samples 10000000 would allocate .* memory budget", {"DITGAZE_MEMORY_GB": "0.5"}),
    ("compare-bad-second-mesh", ["compare", "{sphere.ply}", "{zero.obj}"], r"zero\.obj: line 4: face index 0", {}),
    ("compare-flat-mesh", ["compare", "{point.obj}", "{sphere.ply}", "--samples", "10"], r"point\.obj: zero surface area", {}),
    # clean: tolerances and counts, and the remeshing edge against the mesh's area
    ("clean-remesh-edge-1e-6", ["clean", "{sphere.ply}", "{out}/o.ply", "--remesh-edge", "1e-6"], r"--remesh-edge: an edge of 1e-06 x the diagonal would remesh this mesh into ~.* faces, more than 2000000; expected an edge fraction >= ", {}),
    ("clean-remesh-edge-negative", ["clean", "{sphere.ply}", "{out}/o.ply", "--remesh-edge", "-0.1"], r"--remesh-edge: expected an edge length .* in \[0, 1\], got -0\.1", {}),
    ("clean-remesh-edge-nan", ["clean", "{sphere.ply}", "{out}/o.ply", "--remesh-edge", "nan"], r"--remesh-edge: .* got nan", {}),
    ("clean-taubin-steps-1e9", ["clean", "{sphere.ply}", "{out}/o.ply", "--taubin-steps", "1e9"], r"--taubin-steps: expected a number of smoothing steps in \[0, 1000\]", {}),
    ("clean-taubin-steps-negative", ["clean", "{sphere.ply}", "{out}/o.ply", "--taubin-steps", "-1"], r"--taubin-steps: .* got -1", {}),
    ("clean-weld-tolerance-nan", ["clean", "{sphere.ply}", "{out}/o.ply", "--weld-tolerance", "nan"], r"--weld-tolerance: expected a fraction of the bounding-box diagonal in \[0, 0\.1\], got nan", {}),
    ("clean-weld-tolerance-negative", ["clean", "{sphere.ply}", "{out}/o.ply", "--weld-tolerance=-1e-3"], r"--weld-tolerance: .* got -0\.001", {}),
    ("clean-component-fraction-2", ["clean", "{sphere.ply}", "{out}/o.ply", "--min-component-fraction", "2"], r"--min-component-fraction: expected a fraction of the faces in \[0, 1\], got 2", {}),
    ("clean-hole-edges-negative", ["clean", "{sphere.ply}", "{out}/o.ply", "--max-hole-edges", "-5"], r"--max-hole-edges: expected a number of edges in \[0, 100000\], got -5", {}),
    ("clean-target-faces-zero", ["clean", "{sphere.ply}", "{out}/o.ply", "--target-faces", "0"], r"--target-faces: expected a number of faces in \[4, ", {}),
    ("clean-target-faces-inf", ["clean", "{sphere.ply}", "{out}/o.ply", "--target-faces", "inf"], r"--target-faces: .* got inf", {}),
    ("clean-bad-input", ["clean", "{big.off}", "{out}/o.ply"], r"big\.off: the OFF header's", {}),
    ("clean-output-is-input", ["clean", "{sphere.ply}", "{sphere.ply}"], r"is the input file", {}),
    # extract: the grid, before and after the checkpoint is read; a mismatched checkpoint on one line
    ("extract-res-100000", ["extract", "{sdf.safetensors}", "{out}/m.ply", "--res", "100000"], r"--res: expected a grid resolution \(cubes per axis; 0: the checkpoint's\) in \[2, 512\], got 100000", {}),
    ("extract-res-one", ["extract", "{sdf.safetensors}", "{out}/m.ply", "--res", "1"], r"--res: .* got 1$", {}),
    ("extract-res-over-memory", ["extract", "{sdf.safetensors}", "{out}/m.ply", "--res", "256"], r"--res 256: a kuhn tet grid and its mesh would allocate .* lower --res", {"DITGAZE_MEMORY_GB": "0.5"}),
    ("extract-weight-mismatch", ["extract", "{wide.safetensors}", "{out}/m.ply"], r"wide\.safetensors: SDF checkpoint does not match the network \(Error\(s\) in loading state_dict for SDFNet: size mismatch", {}),
    ("extract-checkpoint-grid-res", ["extract", "{fine.safetensors}", "{out}/m.ply"], r"fine\.safetensors: grid_res \(--res 0\): expected a grid resolution .* got 100000", {}),
    ("extract-mesh-as-checkpoint", ["extract", "{sphere.ply}", "{out}/m.ply"], r"sphere\.ply", {}),
    # fit: every flag, before the dataset is read
    ("fit-steps-1e9", ["fit", "{out}/d.h5", "{out}/fit", "--steps", "1e9"], r"--steps: expected a number of optimiser steps in \[1, 100000\]", {}),
    ("fit-steps-zero", ["fit", "{out}/d.h5", "{out}/fit", "--steps", "0"], r"--steps: .* got 0", {}),
    ("fit-res-100000", ["fit", "{out}/d.h5", "{out}/fit", "--res", "100000"], r"--res: expected a grid resolution \(cubes per axis\) in \[4, 512\]", {}),
    ("fit-res-over-memory", ["fit", "{out}/d.h5", "{out}/fit", "--res", "256"], r"--res 256: .* would allocate", {"DITGAZE_MEMORY_GB": "0.5"}),
    ("fit-seed-negative", ["fit", "{out}/d.h5", "{out}/fit", "--seed", "-1"], r"--seed: expected a seed in \[0, ", {}),
    ("fit-threads-1e6", ["fit", "{out}/d.h5", "{out}/fit", "--threads", "1e6"], r"--threads: expected a number of threads .* in \[0, 1024\]", {}),
    ("fit-threads-negative", ["fit", "{out}/d.h5", "{out}/fit", "--threads", "-1"], r"--threads must be >= 0", {}),
    ("fit-holdout-negative", ["fit", "{out}/d.h5", "{out}/fit", "--holdout", "2,-7"], r"--holdout: expected camera indices in \[0, ", {}),
    ("fit-holdout-words", ["fit", "{out}/d.h5", "{out}/fit", "--holdout", "left,right"], r"--holdout: expected comma-separated camera indices", {}),
    # render: the sheet's size, before GL or the mesh
    ("render-views-1e8", ["render", "{sphere.ply}", "{out}/s.png", "--views", "1e8"], r"--views: expected a number of views in \[1, 256\]", {}),
    ("render-size-100000", ["render", "{sphere.ply}", "{out}/s.png", "--size", "100000"], r"--size: expected a view size in pixels in \[8, 4096\]", {}),
    ("render-views-nan", ["render", "{sphere.ply}", "{out}/s.png", "--views", "nan"], r"--views: .* got nan", {}),
    ("render-over-memory", ["render", "{sphere.ply}", "{out}/s.png", "--views", "256", "--size", "4096"], r"a sheet of 256 views of 4096 px would allocate .* lower --views or --size", {"DITGAZE_MEMORY_GB": "4"}),
    ("render-views-zero", ["render", "{sphere.ply}", "{out}/s.png", "--views", "0"], r"--views must be >= 1", {}),
    ("render-flat-mesh", ["render", "{point.obj}", "{out}/s.png"], r"the mesh's bounding box has no extent", {}),
    ("render-bad-mesh", ["render", "{two.obj}", "{out}/s.png"], r"two\.obj: line 4: a face needs at least 3 vertices", {}),
]


@pytest.mark.parametrize("argv, match, env", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_geometry_refuses(tmp_path, monkeypatch, argv, match, env):
    files = _files(tmp_path)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    args, used = [], []
    for a in argv:
        for name, path in files.items():
            if f"{{{name}}}" in a:
                a = a.replace(f"{{{name}}}", str(path))
                used += [path] if name != "out" else []
        args.append(a)
    assert_refused("geometry", args, match, inputs=used, out_dir=files["out"], seconds=20)
