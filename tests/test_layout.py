"""Package hygiene: light imports, layering rules, docstrings, CLIs and the demo."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["toolkit", "render", "geometry", "train", "apps"]
ALLOWED = {
    "toolkit": set(),
    "render": {"toolkit"},
    "geometry": {"toolkit", "render"},
    "train": {"toolkit", "render", "geometry"},
    "apps": {"toolkit", "render", "geometry", "train"},
}


def test_import_render_and_toolkit_stays_light():
    code = (
        "import sys, render, toolkit, toolkit.scene, toolkit.ply, toolkit.cameras, toolkit.rotations, toolkit.io;"
        "heavy = [m for m in ('open3d', 'pymeshlab', 'moderngl') if m in sys.modules];"
        "print(heavy); sys.exit(1 if heavy else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_every_library_module_imports_without_heavy_dependencies():
    """open3d, pymeshlab, moderngl and tensorboard are imported inside the functions that need them."""
    modules = sorted(".".join(p.relative_to(ROOT).with_suffix("").parts) for pkg in ("toolkit", "render", "geometry", "train")
                     for p in (ROOT / pkg).rglob("*.py") if p.name != "__main__.py")
    modules = [m.removesuffix(".__init__") for m in modules]
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        "heavy = [m for m in ('open3d', 'pymeshlab', 'moderngl', 'tensorboard') if m in sys.modules]\n"
        "print(heavy); sys.exit(1 if heavy else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def _imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


@pytest.mark.parametrize("pkg", PACKAGES)
def test_layering(pkg):
    for path in (ROOT / pkg).rglob("*.py"):
        ours = _imports_of(path) & set(PACKAGES)
        bad = ours - ALLOWED[pkg] - {pkg}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}; {pkg} may import {sorted(ALLOWED[pkg])}"


def _private_train_names(path: Path) -> list[str]:
    """``from train... import _x`` and ``name._x`` where ``name`` was imported from ``train``, in ``path``."""
    tree = ast.parse(path.read_text())
    private = lambda name: name.startswith("_") and not name.startswith("__")  # noqa: E731
    bound, found = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bound |= {(a.asname or a.name.split(".")[0]) for a in node.names if a.name.split(".")[0] == "train"}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "train":
            found += [f"line {node.lineno}: from {node.module} import {a.name}" for a in node.names if private(a.name)]
            bound |= {a.asname or a.name for a in node.names}
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and private(node.attr):
            root = node.value
            while isinstance(root, ast.Attribute):
                root = root.value
            if isinstance(root, ast.Name) and root.id in bound:
                found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


@pytest.mark.parametrize("folder", ["apps", "benchmarks"])
def test_apps_and_benchmarks_use_only_the_public_names_of_train(folder):
    """A finished run is opened with ``train.trained_run.TrainedRun``; nothing outside train reaches into its
    private names."""
    bad = {str(p.relative_to(ROOT)): found for p in sorted((ROOT / folder).rglob("*.py"))
           if (found := _private_train_names(p))}
    assert not bad, bad


@pytest.mark.parametrize("pkg", PACKAGES)
def test_package_docstring_states_ownership_and_imports(pkg):
    doc = ast.get_docstring(ast.parse((ROOT / pkg / "__init__.py").read_text()))
    assert doc and "May import" in doc


def _run(*args):
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True)


def test_toolkit_cli_errors_are_one_line(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    for args in (["info", str(tmp_path / "missing.ply")], ["info", str(bad)], ["info", str(tmp_path)],
                 ["convert", str(bad), str(tmp_path / "o.ply")]):
        r = _run("-m", "toolkit", *args)
        assert r.returncode == 2, r.stderr
        assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
        assert "Traceback" not in r.stderr


def test_demo_writes_scene_files(tmp_path):
    r = _run("-m", "apps.demo", "--out", str(tmp_path), "--gaussians", "2000", "--skip-training")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "demo_head.safetensors").exists() and (tmp_path / "demo_head.ply").exists()
    r = _run("-m", "toolkit", "convert", str(tmp_path / "demo_head.ply"), str(tmp_path / "again.safetensors"))
    assert r.returncode == 0 and (tmp_path / "again.safetensors").exists()
    r = _run("-m", "apps.demo", "--out", str(tmp_path), "--gaussians", "3")
    assert r.returncode == 2 and r.stderr.startswith("error: --gaussians")


def test_install_disk_check_names_the_folder_and_the_shortfall(tmp_path):
    script = ROOT / "scripts" / "check_disk.sh"
    missing = tmp_path / "not" / "yet" / ".venv"  # checked at its nearest existing parent
    ok = subprocess.run(["bash", str(script), "1", str(missing)], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    short = subprocess.run(["bash", str(script), str(10**12), str(missing)], capture_output=True, text=True)
    assert short.returncode == 1
    lines = short.stderr.strip().splitlines()
    assert len(lines) == 1 and str(missing) in lines[0] and f"{tmp_path} has" in lines[0], short.stderr
