"""The import graph of `recon/` is the architecture: no cycles, and each layer imports only what sits below it.

The graph is read with `ast`, never by importing: every `import` / `from ... import` in a module counts, at module
level, inside functions (lazy imports) and under `if TYPE_CHECKING:` alike, because each one is a dependency someone
reading or moving the code has to respect. `from package import name` is an edge to `package.name` when that is a
module, else to `package`. Importing `a.b.c` also runs `a/__init__` and `a/b/__init__`; those implicit edges are left
out (every module would otherwise depend on `recon/__init__`, which loads the API lazily).

The rules:

* no import cycle;
* the library layer (`recon.capture`, `recon.nerf`, `recon.evaluation`, `recon.meshing`, `recon.geometry` and the
  shared modules beside them) imports nothing above it (`recon.plans`, `recon.stages`, `recon.runner`, `recon.app`);
* no stage imports another stage (they meet through the scene folder's files, wired by `recon.stages`);
* only the train stage and the profiler import the training loop (`recon.nerf.trainer`): rendering and scoring a
  trained field live in `recon.nerf.evaluate`;
* the camera math (`recon.camera`) imports nothing of recon but its errors: everything that projects or casts rays
  builds on it, so it sits at the bottom.

The tests follow one rule of their own: no test module imports another (shared helpers live in helper modules such as
`tests/ball_scene.py`), so running, editing or moving one test file never drags another one's tests along.
"""
from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "recon"

LIBRARY_PACKAGES = ("recon.capture", "recon.nerf", "recon.evaluation", "recon.meshing", "recon.geometry")
"""The library: photos and the scene contract in; fields, renders and meshes out. Tensors, arrays and files."""
LIBRARY_MODULES = ("recon.camera", "recon.config", "recon.atomic", "recon.errors", "recon.field", "recon.plots")
"""Shared by the whole library: camera math, the typed options (each layer reads its slice), careful file writes,
user-facing errors, a field on disk, PNG plots."""
RUNNERS = ("recon.plans", "recon.stages", "recon.runner", "recon.app")
"""Above the library: what each stage decides (plans), the stages, the runner and the faces (CLI, API, batch, bench,
profiling, viewer). A library module importing one of these would make the layers a circle."""
STAGES = "recon.stages"
TRAINER = "recon.nerf.trainer"
TRAINER_IMPORTERS = frozenset({"recon.stages.train", "recon.app.profiling"})
"""Who may import the training loop: the stage that trains and the profiler that times training steps."""
CAMERA = "recon.camera"
CAMERA_IMPORTS = frozenset({"recon.errors"})
"""All of recon that the camera math may import."""
TESTS = "tests"

Graph = dict[str, dict[str, int]]
"""module -> {imported recon module: line of its first import}."""


def module_files(root: Path, package: str) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of `package` under `root` (packages by their __init__)."""
    files = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        files[".".join(parts)] = path
    return files


def _imported_names(node: ast.Import | ast.ImportFrom, module: str, is_package: bool, known: set[str]) -> list[str]:
    """The modules one import statement names (relative imports resolved against `module`)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        source = ".".join(base + ([node.module] if node.module else []))
    else:
        source = node.module or ""
    return [f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else source for alias in node.names]


def import_graph(files: Mapping[str, Path], package: str = PACKAGE) -> Graph:
    """Every module's imports of other modules of `package`, from the source text (nothing is imported)."""
    known = set(files)
    graph: Graph = {}
    for module, path in files.items():
        edges: dict[str, int] = {}
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            for name in _imported_names(node, module, is_package, known):
                if name != package and not name.startswith(package + "."):
                    continue
                while name not in known and "." in name:  # `import recon.x.Y` where Y is not a module
                    name = name.rpartition(".")[0]
                if name != module:
                    edges[name] = min(edges.get(name, node.lineno), node.lineno)
        graph[module] = edges
    return graph


def find_cycles(graph: Mapping[str, Mapping[str, int]]) -> list[list[str]]:
    """One cycle (first module repeated at the end) per strongly connected group of modules that import each other."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[set[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm; the graph is a few dozen modules deep at most
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.add(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_cycle_in(graph, group) for group in groups]


def _cycle_in(graph: Mapping[str, Mapping[str, int]], group: set[str]) -> list[str]:
    """A shortest import cycle through the alphabetically first module of a strongly connected group."""
    start = min(group)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v]):
                if w == start:
                    return paths[v] + [start]
                if w in group and w not in paths:
                    paths[w] = paths[v] + [w]
                    nxt.append(w)
        frontier = nxt
    raise AssertionError(f"{sorted(group)} is not strongly connected")


def _within(module: str, prefixes: Iterable[str]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def is_library(module: str) -> bool:
    return _within(module, LIBRARY_PACKAGES) or module in LIBRARY_MODULES


def layering_violations(graph: Mapping[str, Mapping[str, int]]) -> list[str]:
    """Every import that breaks a layering rule, as 'module:line imports target (rule)'."""
    found = []
    for module, edges in sorted(graph.items()):
        for target, line in sorted(edges.items()):
            where = f"{module}:{line} imports {target}"
            if is_library(module) and _within(target, RUNNERS):
                found.append(f"{where} (the library layer imports no stage, runner or CLI)")
            if module.startswith(STAGES + ".") and _within(target, [STAGES]):
                found.append(f"{where} (a stage imports no other stage)")
            if target == TRAINER and module not in TRAINER_IMPORTERS:
                found.append(f"{where} (only {', '.join(sorted(TRAINER_IMPORTERS))} import the training loop; "
                             f"render and score with recon.nerf.evaluate)")
            if module == CAMERA and target not in CAMERA_IMPORTS:
                found.append(f"{where} (the camera math imports nothing of recon but {', '.join(sorted(CAMERA_IMPORTS))})")
    return found


def is_test_module(module: str) -> bool:
    return module.rpartition(".")[2].startswith("test_")


def imports_between_tests(graph: Mapping[str, Mapping[str, int]]) -> list[str]:
    """Every import of a test module by another test module, as 'module:line imports target'."""
    return [f"{module}:{line} imports {target}" for module, edges in sorted(graph.items()) if is_test_module(module)
            for target, line in sorted(edges.items()) if is_test_module(target)]


def _describe(graph: Mapping[str, Mapping[str, int]], cycle: list[str]) -> str:
    return " -> ".join(f"{a} (line {graph[a][b]})" for a, b in zip(cycle, cycle[1:])) + f" -> {cycle[-1]}"


@pytest.fixture(scope="module")
def graph() -> Graph:
    return import_graph(module_files(ROOT, PACKAGE))


# ----------------------------------------------------------------------------- the checker itself
def _write_package(root: Path, sources: dict[str, str]) -> dict[str, Path]:
    for rel, text in sources.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return module_files(root, "pkg")


def test_graph_counts_lazy_relative_and_submodule_imports(tmp_path: Path) -> None:
    files = _write_package(tmp_path, {
        "pkg/__init__.py": "from pkg import a\n",
        "pkg/a.py": "import os\nfrom .sub import b\n",
        "pkg/sub/__init__.py": "",
        "pkg/sub/b.py": "def f():\n    from ..c import thing\n    return thing\n",
        "pkg/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.sub.b.Klass\nthing = 1\n",
    })
    graph = import_graph(files, "pkg")
    assert graph == {"pkg": {"pkg.a": 1}, "pkg.a": {"pkg.sub.b": 2}, "pkg.sub": {},
                     "pkg.sub.b": {"pkg.c": 2}, "pkg.c": {"pkg.sub.b": 3}}
    cycles = find_cycles(graph)
    assert cycles == [["pkg.c", "pkg.sub.b", "pkg.c"]]
    assert _describe(graph, cycles[0]) == "pkg.c (line 3) -> pkg.sub.b (line 2) -> pkg.c"


def test_layering_rules_catch_each_kind_of_violation() -> None:
    bad = {
        "recon.nerf.fast": {"recon.runner.pipeline": 3},
        "recon.capture.scene": {"recon.stages.poses": 9},
        "recon.meshing.photos": {"recon.plans.mesh": 2, "recon.geometry.raster": 1},
        "recon.stages.mesh": {"recon.stages.train": 5, "recon.nerf.trainer": 6},
        "recon.stages.train": {"recon.nerf.trainer": 7, "recon.runner.pipeline": 1},
        "recon.app.cli": {"recon.stages": 2, "recon.runner.pipeline": 2},
        "recon.camera": {"recon.errors": 1, "recon.capture.scene": 4},
    }
    found = layering_violations(bad)
    assert [v.split(" (")[0] for v in found] == [
        "recon.camera:4 imports recon.capture.scene",
        "recon.capture.scene:9 imports recon.stages.poses",
        "recon.meshing.photos:2 imports recon.plans.mesh",
        "recon.nerf.fast:3 imports recon.runner.pipeline",
        "recon.stages.mesh:6 imports recon.nerf.trainer",
        "recon.stages.mesh:5 imports recon.stages.train",
    ]


def test_test_import_rule_catches_a_test_importing_a_test(tmp_path: Path) -> None:
    files = _write_package(tmp_path, {
        "pkg/helpers.py": "",
        "pkg/test_a.py": "from pkg.helpers import x\nfrom pkg import test_b\n",
        "pkg/test_b.py": "def f():\n    from pkg.test_a import thing\n",
        "pkg/test_c.py": "import pkg.helpers\n",
    })
    graph = import_graph(files, "pkg")
    assert imports_between_tests(graph) == ["pkg.test_a:2 imports pkg.test_b", "pkg.test_b:2 imports pkg.test_a"]


# ----------------------------------------------------------------------------- recon itself
def test_graph_sees_recon(graph: Graph) -> None:
    """The walk reaches the whole package and its lazy imports (else the rules below would pass on nothing)."""
    assert {"recon", "recon.nerf.trainer", "recon.nerf.evaluate", "recon.stages.train", "recon.capture.colmap"} <= set(graph)
    assert TRAINER in graph["recon.stages.train"]  # imported inside the stage's run function
    assert len(graph) >= 60 and sum(map(len, graph.values())) >= 200


def test_no_import_cycles(graph: Graph) -> None:
    cycles = find_cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(_describe(graph, c) for c in cycles)


def test_layering(graph: Graph) -> None:
    found = layering_violations(graph)
    assert not found, "layering broken:\n" + "\n".join(found)


# ----------------------------------------------------------------------------- the tests themselves
def test_no_test_module_imports_another() -> None:
    graph = import_graph(module_files(ROOT, TESTS), TESTS)
    assert "tests.test_architecture" in graph and "tests.ball_scene" in graph  # the walk reached the tests
    found = imports_between_tests(graph)
    assert not found, "test modules importing test modules (move the shared helpers to a helper module):\n" + "\n".join(found)
