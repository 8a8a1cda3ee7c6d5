"""The import graph follows ../shared/DESIGN.md's arrows: read from every module's source (imports inside
functions and under ``TYPE_CHECKING`` count: a lazy import hides a cycle, it does not remove it), the
packages import only those below them, no two modules import each other through any path, and no module
reaches for another module's private (``_name``) members."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from tests.conftest import REPO

#: What each package may import (besides itself): the table of DESIGN.md, core at the bottom.
ALLOWED = {
    "core": set(),
    "registration": {"core"},
    "mapping": {"core", "registration"},
    "evaluation": {"core", "registration", "mapping"},
    "slam": {"core", "registration", "mapping", "evaluation"},
}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in ALLOWED:
        for p in (REPO / pkg).rglob("*.py"):
            parts = p.relative_to(REPO).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


MODULES = _modules()


def _owner(name: str) -> str | None:
    """The project module *name* lives in (a module, or the module holding the attribute *name*)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _imports(mod: str) -> list[tuple[str, str | None, int]]:
    """(imported module, imported name or None, line) of every import statement in *mod*, anywhere."""
    path = MODULES[mod]
    package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((sub, None, node.lineno) if sub in MODULES else (base, a.name, node.lineno))
    return out


def _edges() -> dict[str, set[str]]:
    edges: dict[str, set[str]] = defaultdict(set)
    for mod in MODULES:
        for target, _, _ in _imports(mod):
            owner = _owner(target)
            if owner is not None and owner != mod:
                edges[mod].add(owner)
    return edges


def test_the_walk_sees_the_project():
    """The walk finds the packages' modules and their imports (a walk that saw nothing would pass the rest)."""
    assert {m.split(".")[0] for m in MODULES} == set(ALLOWED)
    assert len(MODULES) > 100
    edges = _edges()
    assert "core.errors" in edges["core.geometry"] and "registration.icp" in edges["slam.loops.verify"]
    # imports inside functions count: the pipeline imports its mapping process inside run_slam's helper
    assert "slam.pipeline.mapping_process" in edges["slam.pipeline.run"]


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_a_package_imports_only_the_packages_below_it(package):
    bad = sorted(f"{mod}:{line} imports {target}" for mod in MODULES if mod.split(".")[0] == package
                 for target, _, line in _imports(mod)
                 if (owner := _owner(target)) is not None and owner.split(".")[0] not in ALLOWED[package] | {package})
    assert not bad, "\n".join(bad)


def test_no_two_modules_import_each_other_through_any_path():
    """Strongly connected components of the module graph (Tarjan's, as scipy computes them) are all single modules."""
    names = sorted(MODULES)
    index = {m: k for k, m in enumerate(names)}
    edges = _edges()
    rows = [index[a] for a in edges for _ in edges[a]]
    cols = [index[b] for a in edges for b in edges[a]]
    graph = csr_matrix(([1] * len(rows), (rows, cols)), shape=(len(names), len(names)))
    n, labels = connected_components(graph, directed=True, connection="strong")
    cycles = [sorted(names[k] for k in range(len(names)) if labels[k] == c) for c in range(n)]
    cycles = [c for c in cycles if len(c) > 1]
    assert not cycles, cycles


def test_no_module_imports_another_modules_private_names():
    """Neither ``from m import _name`` nor ``m._name`` on a project module imported under a name."""
    bad = []
    for mod, path in MODULES.items():
        aliases = {}
        for target, name, line in _imports(mod):
            owner = _owner(target)
            if owner is None or owner == mod:
                continue
            if name is not None and name.startswith("_") and not name.startswith("__"):
                bad.append(f"{mod}:{line} imports {owner}.{name}")
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                aliases.update({a.asname: a.name for a in node.names if a.asname and a.name in MODULES})
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                aliases.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names
                                if f"{node.module}.{a.name}" in MODULES})
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                bad.append(f"{mod}:{node.lineno} uses {aliases[node.value.id]}.{node.attr}")
    assert not bad, "\n".join(bad)


def test_no_source_file_is_over_400_lines():
    """Small modules with one job: a file past 400 lines is doing more than one."""
    long = sorted(f"{mod}: {n} lines" for mod, path in MODULES.items()
                  if (n := len(path.read_text(encoding="utf-8").splitlines())) > 400)
    assert not long, long


def test_no_function_of_the_pipeline_or_the_loop_closure_stages_is_over_80_lines():
    """The frame loop and the loop-closure stages read a screen at a time."""
    long = []
    for mod, path in MODULES.items():
        if not mod.startswith(("slam.pipeline", "slam.loops")):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 80:
                long.append(f"{mod}.{node.name}: {node.end_lineno - node.lineno + 1} lines")
    assert not long, long
