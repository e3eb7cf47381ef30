"""Tests of the room rules of DESIGN.md: who imports what, no import cycle, small files saying what they own.

Imports are read from the source with :mod:`ast`, function-level imports included, so an import hidden inside
a function still counts (it is still a dependency, only a late one).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROOMS = {
    "vio": "viotb.vio",
    "envs": "viotb.envs",
    "controllers": "viotb.controllers",
    "models": "viotb.models",
}
MAX_LINES = 500


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT)
    room, rest = rel.parts[0], rel.with_suffix("").parts[1:]
    parts = [ROOMS[room], *rest]
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    out = {}
    for room in ROOMS:
        for path in sorted((ROOT / room).rglob("*.py")):
            out[_module_name(path)] = path
    return out


SOURCES = _sources()


def _imports(path: Path) -> set[str]:
    """Every module named by an import anywhere in the file (top level or inside functions)."""
    tree = ast.parse(path.read_text(), str(path))
    names: set[str] = set()
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            names.add(target)
            # ``from pkg import module`` names a module too.
            names.update(f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in SOURCES)
    return names


def _internal(name: str) -> str | None:
    """The project module an import resolves to (the longest known prefix), or None for third parties."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        cand = ".".join(parts[:k])
        if cand in SOURCES:
            return cand
    return None


GRAPH = {
    mod: {t for t in (_internal(n) for n in _imports(p)) if t and t != mod} for mod, p in SOURCES.items()
}


def test_the_scan_sees_the_project():
    assert "viotb.vio.msckf" in SOURCES and "viotb.envs.run.closed_loop" in SOURCES
    assert "viotb.vio.types" in GRAPH["viotb.vio.msckf"]


@pytest.mark.parametrize(
    "forbidden", ["mujoco", "gymnasium", "rerun", "ray", "viotb.envs", "viotb.controllers"]
)
def test_vio_runs_on_any_dataset_without_the_simulator(forbidden):
    bad = sorted(
        f"{mod}: {name}"
        for mod, path in SOURCES.items()
        if mod.startswith("viotb.vio")
        for name in _imports(path)
        if name == forbidden or name.startswith(forbidden + ".")
    )
    assert not bad, f"vio/ must not import {forbidden}: {bad}"


def test_controllers_use_numpy_and_only_vio_lie_and_types():
    allowed_vio = {"viotb.vio.lie", "viotb.vio.types"}
    bad = []
    for mod, path in SOURCES.items():
        if not mod.startswith("viotb.controllers"):
            continue
        for name in _imports(path):
            if (
                name.startswith("viotb.")
                and not name.startswith("viotb.controllers")
                and name not in allowed_vio
            ):
                bad.append(f"{mod}: {name}")
            if name.split(".")[0] in {"mujoco", "gymnasium", "rerun", "scipy", "cv2"}:
                bad.append(f"{mod}: {name}")
    assert not bad, bad


def test_models_import_no_other_room():
    bad = [
        f"{mod}: {n}"
        for mod, p in SOURCES.items()
        if mod.startswith("viotb.models")
        for n in _imports(p)
        if n.startswith("viotb.") and not n.startswith("viotb.models")
    ]
    assert not bad, bad


def test_no_import_cycle_among_the_project_modules():
    """Tarjan's strongly connected components over the import graph: every component is one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_the_cycle_check_finds_a_planted_cycle():
    """The checker itself: a graph with a -> b -> a is reported (guards against a check that sees nothing)."""
    saved = dict(GRAPH)
    try:
        GRAPH["viotb.vio.types"] = set(GRAPH["viotb.vio.types"]) | {"viotb.vio.msckf"}
        with pytest.raises(AssertionError, match="import cycles"):
            test_no_import_cycle_among_the_project_modules()
    finally:
        GRAPH.clear()
        GRAPH.update(saved)


def test_envs_is_in_wings():
    loose = sorted(p.name for p in (ROOT / "envs").glob("*.py") if p.name != "__init__.py")
    assert not loose, f"envs/ holds only its wings (sim, scenarios, run, gym, data, tools): {loose}"


def test_no_source_file_over_500_lines_and_each_says_what_it_owns():
    long_files, undocumented = [], []
    for mod, path in SOURCES.items():
        n = len(path.read_text().splitlines())
        if n > MAX_LINES:
            long_files.append(f"{path.relative_to(ROOT)}: {n}")
        doc = ast.get_docstring(ast.parse(path.read_text()))
        if not doc or not doc.strip():
            undocumented.append(mod)
    assert not long_files, long_files
    assert not undocumented, undocumented


def test_no_merge_conflict_markers_left_in_the_tree():
    markers = ("<<<<<<< ", ">>>>>>> ")
    bad = []
    for pattern in ("*.py", "*.md", "*.toml", "*.yaml", "*.yml", "*.sh"):
        for path in ROOT.rglob(pattern):
            if any(
                part.startswith(".") or part in {"build", "dist"} for part in path.relative_to(ROOT).parts
            ):
                continue
            for k, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
                if line.startswith(markers):
                    bad.append(f"{path.relative_to(ROOT)}:{k}")
    assert not bad, bad
