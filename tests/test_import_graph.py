"""The import graph of the library: no cycles (function-level imports included), and train/'s subpackages in layers."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("toolkit", "render", "geometry", "train", "apps")

TRAIN_LAYERS = (
    ("train.config",),
    ("train.losses",),
    ("train.data", "train.model", "train.estimator"),
    ("train.run_config",),
    ("train.presets",),
    ("train.training", "train.evaluation"),
    ("train.stages",),
    ("train.trained_run",),
    ("train.augment",),
    ("train.ablate",),
    ("train.run",),
)
"""train/'s parts from the bottom up: a part imports only parts of lower layers (and itself). The configs sit
above the components whose configs they nest; the stages above everything they run; the
finished-run API, the benchmarks on finished runs, and the CLI on top."""


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def _imports(path: Path, known: dict[str, Path]) -> set[str]:
    """Our modules that ``path`` imports anywhere in its body (function-level imports too)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in known}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module in known:
            # `from pkg import sub` imports the module pkg.sub when it is one, else a name of pkg
            subs = {f"{node.module}.{a.name}" for a in node.names} & set(known)
            out |= subs or {node.module}
            if len(subs) < len(node.names):
                out.add(node.module)
    return out


def _graph() -> dict[str, set[str]]:
    known = _modules()
    return {m: _imports(p, known) - {m} for m, p in known.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, stack, on_stack, out, counter = {}, {}, [], set(), [], [0]

    def visit(root: str) -> None:
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        top = stack.pop()
                        on_stack.discard(top)
                        comp.append(top)
                        if top == node:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
            elif child not in index:
                index[child] = low[child] = counter[0]
                counter[0] += 1
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(sorted(graph[child]))))
            elif child in on_stack:
                low[node] = min(low[node], index[child])

    for m in sorted(graph):
        if m not in index:
            visit(m)
    return out


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _part(module: str) -> str | None:
    for layer in TRAIN_LAYERS:
        for part in layer:
            if module == part or module.startswith(part + "."):
                return part
    return None


@pytest.mark.parametrize("layer", range(len(TRAIN_LAYERS)))
def test_train_parts_import_only_lower_layers(layer):
    rank = {part: i for i, parts in enumerate(TRAIN_LAYERS) for part in parts}
    graph = _graph()
    bad = []
    for module, deps in graph.items():
        part = _part(module)
        if part is None or rank[part] != layer:
            continue
        for dep in deps:
            dep_part = _part(dep)
            if dep_part is not None and dep_part != part and rank[dep_part] >= layer:
                bad.append(f"{module} imports {dep}")
    assert not bad, "; ".join(sorted(bad))


def test_every_train_module_belongs_to_a_layer():
    loose = [m for m in _modules() if m.startswith("train.") and _part(m) is None and m != "train"]
    assert not loose, f"add these to TRAIN_LAYERS: {loose}"
