"""No command writes over one of its inputs: each CLI, given an output that is (or links to) an input, exits 2 with
one `error:` line and leaves the input's bytes as they were."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from toolkit.errors import ToolkitError
from toolkit.io import check_not_an_input

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


def _refused(r: subprocess.CompletedProcess, *unchanged: tuple[Path, bytes]) -> None:
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    for path, before in unchanged:
        assert path.read_bytes() == before, f"{path} changed"


def test_the_check_compares_resolved_paths(tmp_path):
    src = tmp_path / "a.ply"
    src.write_bytes(b"x")
    (tmp_path / "link.ply").symlink_to(src)
    for same in (src, tmp_path / "link.ply", tmp_path / "sub" / ".." / "a.ply"):
        with pytest.raises(ToolkitError, match="is the input file"):
            check_not_an_input(same, [src])
    check_not_an_input(tmp_path / "b.ply", [src, tmp_path])  # a new file beside the input is fine


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scene") / "head.ply"
    from toolkit.procedural import demo_head_scene

    demo_head_scene(200).to_ply(path)
    return path


def test_toolkit_convert(scene_file, tmp_path):
    link = tmp_path / "same.ply"
    link.symlink_to(scene_file)
    before = scene_file.read_bytes()
    _refused(_run("-m", "toolkit", "convert", str(scene_file), str(scene_file)), (scene_file, before))
    _refused(_run("-m", "toolkit", "convert", str(scene_file), str(link)), (scene_file, before))


def test_geometry_clean(tmp_path):
    mesh = tmp_path / "m.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    before = mesh.read_bytes()
    _refused(_run("-m", "geometry", "clean", str(mesh), str(mesh)), (mesh, before))


def test_data_inspect_sheet(tmp_path):
    data = tmp_path / "data"
    r = _run("-m", "train.data", "synth", "--subjects", "1", "--frames", "1", "--res", "32", "--out", str(data))
    assert r.returncode == 0, r.stderr
    subject = next(data.glob("*.h5"))
    before = subject.read_bytes()
    _refused(_run("-m", "train.data", "inspect", str(subject), "--sheet", str(subject)), (subject, before))
    _refused(_run("-m", "train.data", "inspect", str(data), "--sheet", str(tmp_path / "sheet.h5")), (subject, before))
    png = tmp_path / "subject.png"
    png.symlink_to(subject)
    _refused(_run("-m", "train.data", "inspect", str(data), "--sheet", str(png)), (subject, before))


def test_preview_sweep(scene_file):
    before = scene_file.read_bytes()
    _refused(_run("apps/preview.py", str(scene_file), "--headless", "--sweep", str(scene_file)), (scene_file, before))


def test_geometry_extract(tmp_path):
    from geometry.sdf import SDFNet, SDFNetConfig

    ckpt = tmp_path / "sdf.safetensors"
    SDFNet(SDFNetConfig(grid_res=8)).save(ckpt)
    before = ckpt.read_bytes()
    link = tmp_path / "mesh.ply"
    link.symlink_to(ckpt)  # a mesh name that is the checkpoint
    _refused(_run("-m", "geometry", "extract", str(ckpt), str(link)), (ckpt, before))
