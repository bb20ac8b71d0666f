"""``python -m geometry``: every subcommand, and bad input -> one line ``error: ...``, exit status 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from geometry.__main__ import main
from geometry.mesh_files import save_mesh
from geometry.sdf import SDFNet, SDFNetConfig, SphereInit, pretrain_sphere
from tests.gl import skip_without_gl
from toolkit.errors import run_cli

ROOT = Path(__file__).resolve().parents[2]


def _run(*args) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "geometry", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=300)


@pytest.fixture
def sphere_ply(tmp_path):
    m = trimesh.creation.icosphere(2)
    p = tmp_path / "sphere.ply"
    save_mesh(p, torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces))
    return p


def _ascii_ply(path, verts, faces):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(verts)}", "property float x", "property float y",
             "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(str(c) for c in v) for v in verts] + ["3 " + " ".join(map(str, f)) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_bad_inputs_one_line_exit_2(tmp_path):
    (tmp_path / "notamesh.ply").write_text("hello, I am text\n")
    cases = [
        ("inspect", tmp_path / "missing.ply"),
        ("inspect", tmp_path / "notamesh.ply"),
        ("inspect", _ascii_ply(tmp_path / "empty.ply", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [])),
        ("inspect", _ascii_ply(tmp_path / "nan.ply", [[0, 0, 0], ["nan", 0, 0], [0, 1, 0]], [[0, 1, 2]])),
    ]
    for cmd, path in cases:
        r = _run(cmd, path)
        assert r.returncode == 2, (path, r.stderr)
        err = r.stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in r.stderr, r.stderr
    assert "NaN" in _run("inspect", tmp_path / "nan.ply").stderr
    assert "no triangles (a point cloud?" in _run("inspect", tmp_path / "empty.ply").stderr


def test_bad_inputs_in_process(tmp_path, capsys, sphere_ply):
    assert run_cli(main, ["compare", str(sphere_ply), str(tmp_path / "nope.obj")]) == 2
    assert run_cli(main, ["extract", str(sphere_ply), str(tmp_path / "o.ply")]) == 2  # a mesh is no checkpoint
    assert run_cli(main, ["fit", str(sphere_ply), str(tmp_path / "fit")]) == 2  # a mesh is no HDF5 file
    assert run_cli(main, ["clean", str(sphere_ply), str(tmp_path / "o.xyz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(e.startswith("error: ") for e in err)
    assert not (tmp_path / "o.xyz").exists()
    # Flags and output names are checked before the work, each error naming what was wrong.
    for args, expect in ((["clean", str(sphere_ply), str(tmp_path / "o.ply"), "--target-faces", "0"], "--target-faces"),
                         (["extract", str(tmp_path / "none.safetensors"), str(tmp_path / "o.txt")], "o.txt: unknown mesh"),
                         (["render", str(sphere_ply), str(tmp_path / "s.jpgg")], "s.jpgg: the contact sheet is a PNG"),
                         (["render", str(sphere_ply), str(tmp_path / "s.png"), "--views", "0"], "--views must be >= 1"),
                         (["fit", str(sphere_ply), str(tmp_path / "fit"), "--threads", "-1"], "--threads must be >= 0")):
        assert run_cli(main, args) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and expect in err and err.count("\n") == 1, err
    assert not list(tmp_path.glob("o.*")) and not list(tmp_path.glob("s.*"))


def test_fit_runs_on_the_threads_it_is_given(tmp_path, monkeypatch):
    import torch

    import geometry.fit_dataset as fd

    seen = []
    monkeypatch.setattr(fd, "fit_dataset", lambda *a, **k: seen.append(torch.get_num_threads()) or {})
    before = torch.get_num_threads()
    try:
        assert run_cli(main, ["fit", str(tmp_path / "d.h5"), str(tmp_path / "fit"), "--threads", "1"]) == 0
        torch.set_num_threads(2)
        assert run_cli(main, ["fit", str(tmp_path / "d.h5"), str(tmp_path / "fit"), "--threads", "0"]) == 0
    finally:
        torch.set_num_threads(before)
    assert seen == [1, 2]


def test_inspect_json_compare_clean(tmp_path, sphere_ply):
    r = _run("inspect", sphere_ply, "--json")
    assert r.returncode == 0, r.stderr
    stats = json.loads(r.stdout)
    assert stats["watertight"] and stats["genus"] == 0 and stats["faces"] == 320
    assert _run("inspect", sphere_ply).stdout.count("\n") > 10
    r = _run("compare", sphere_ply, sphere_ply, "--json", "--samples", 2000)
    assert r.returncode == 0 and json.loads(r.stdout)["chamfer"] < 1e-5
    out = tmp_path / "clean.ply"
    assert run_cli(main, ["clean", str(sphere_ply), str(out), "--target-faces", "100"]) == 0
    assert trimesh.load(out).faces.shape[0] <= 100


def test_extract_and_render(tmp_path):
    net = SDFNet(SDFNetConfig(hidden=32, feature_dim=4, box_min=(-1, -1, -1), box_max=(1, 1, 1)))
    pretrain_sphere(net, SphereInit((0.1, 0, 0), 0.5, steps=150, batch=1024, lr=3e-3))
    ckpt = tmp_path / "sdf.safetensors"
    net.save(ckpt)
    out = tmp_path / "m.ply"
    assert run_cli(main, ["extract", str(ckpt), str(out), "--res", "24"]) == 0
    m = trimesh.load(out)
    assert m.is_watertight and m.volume > 0
    assert np.linalg.norm(m.vertices - [0.1, 0, 0], axis=1).mean() == pytest.approx(0.5, abs=0.05)
    png = tmp_path / "sheet.png"
    r = _run("render", out, png, "--views", 3, "--size", 64)
    if r.returncode == 2 and "cannot create a headless OpenGL" in r.stderr:
        skip_without_gl(f"no headless GL here: {r.stderr.strip()}")
    assert r.returncode == 0, r.stderr
    import imageio.v3 as iio

    img = iio.imread(png)
    assert img.shape == (64, 3 * 64, 3) and (img < 250).any()


@pytest.mark.parametrize("key, bad", [("w2c_Tvec", np.zeros((12, 3))), ("scale", np.ones(5)), ("cam_index", np.zeros((6, 2)))])
def test_fit_rejects_rows_of_the_wrong_shape(tmp_path, capsys, key, bad):
    import h5py

    n = 6
    good = {"head_mask": np.zeros((n, 8, 8), np.uint8), "inmat": np.tile(np.eye(3), (n, 1, 1)),
            "w2c_Rmat": np.tile(np.eye(3), (n, 1, 1)), "w2c_Tvec": np.zeros((n, 3)), "pose": np.zeros((n, 6)),
            "facial_landmarks_3d": np.zeros((n, 68, 3)), "scale": np.ones((n, 1)), "cam_index": np.arange(n)}
    path = tmp_path / "subject.h5"
    with h5py.File(path, "w") as f:
        for k, v in {**good, key: bad}.items():
            f[k] = v
    assert run_cli(main, ["fit", str(path), str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {path}: {key} has shape {list(bad.shape)}, expected [{n}")


def test_a_holdout_camera_the_file_lacks_is_refused_and_the_default_takes_those_it_has(tmp_path, capsys):
    """A camera the file lacks holds nothing out: the fit would run unscored (no held-out IoU), unseen."""
    import h5py
    import torch

    from geometry.fit_dataset import split_views

    n = 6
    path = tmp_path / "subject.h5"
    with h5py.File(path, "w") as f:
        for k, v in {"head_mask": np.zeros((n, 8, 8), np.uint8), "inmat": np.tile(np.eye(3), (n, 1, 1)),
                     "w2c_Rmat": np.tile(np.eye(3), (n, 1, 1)), "w2c_Tvec": np.zeros((n, 3)), "pose": np.zeros((n, 6)),
                     "facial_landmarks_3d": np.zeros((n, 68, 3)), "scale": np.ones((n, 1)),
                     "cam_index": np.arange(n)}.items():
            f[k] = v
    assert run_cli(main, ["fit", str(path), str(tmp_path / "fit"), "--holdout", "2,99"]) == 2
    assert capsys.readouterr().err == ("error: fit: --holdout camera(s) [99] not in the file, whose cameras are "
                                       "[0, 1, 2, 3, 4, 5]\n")
    assert not (tmp_path / "fit").exists()
    views = {"masks": torch.zeros(n, 8, 8), "Ks": torch.zeros(n, 3, 3), "viewmats": torch.zeros(n, 4, 4),
             "cam_index": torch.arange(n)}
    train, test = split_views(views)  # 2, 7, 10, 15 by default: camera 2 is the one this file has
    assert len(train) == 5 and len(test) == 1
    assert split_views(views, [])[1] is None
