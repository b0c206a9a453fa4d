"""The package's import graph, read statically from the source (``ast``, nothing imported): no
import cycle anywhere in ``frslam_graph`` (``frslam_graph.datasets`` and ``frslam_graph.factors``
included, wherever pyproject.toml maps them), no module outside ``frslam_graph.cli`` importing the
CLI, and no ``print(`` in the library (only ``cli/`` talks to the terminal).

Every import counts wherever it is written: at module level, inside a function or a method
(``from . import x`` and other relative imports resolved), and ``importlib.import_module("...")``
with a literal name; imports under ``if TYPE_CHECKING:`` count too (a module that names another's
types for its annotations depends on it as much as one that calls it). ``from package import name`` depends on ``package.name`` when that is
a module, else on ``package`` (its ``__init__``); importing a submodule is not counted as
depending on its parent package's ``__init__`` (Python runs that first, whoever imports).
"""

from __future__ import annotations

import ast
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOT = "frslam_graph"


@dataclass(frozen=True)
class Module:
    name: str
    path: Path
    is_package: bool


def package_dirs() -> dict[str, Path]:
    """Package name -> folder: ``frslam_graph`` and the folders pyproject.toml maps into it."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    mapped = config.get("tool", {}).get("setuptools", {}).get("package-dir", {})
    dirs = {ROOT: REPO / ROOT}
    dirs.update({name: REPO / folder for name, folder in mapped.items() if name.startswith(ROOT + ".")})
    return dirs


def find_modules() -> dict[str, Module]:
    """Every module of the package, by dotted name (a folder mapped elsewhere is read from there)."""
    dirs = package_dirs()
    modules: dict[str, Module] = {}
    for package, folder in dirs.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([package, *parts])
            deeper = [o for o in dirs if o.startswith(package + ".")]
            if any(name == o or name.startswith(o + ".") for o in deeper):
                continue  # a subfolder pyproject maps elsewhere (read from its own folder)
            if any(p in (".venv", "__pycache__") for p in rel.parts):
                continue
            modules[name] = Module(name, path, path.name == "__init__.py")
    return modules


def _resolve(name: str, modules: dict[str, Module]) -> str | None:
    """The package module ``name`` or its longest prefix that is one (None outside the package)."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def imports_of(module: Module, modules: dict[str, Module]) -> Iterator[tuple[str, int]]:
    """(imported package module, line) for every import the module runs."""
    tree = ast.parse(module.path.read_text(encoding="utf-8"), filename=str(module.path))
    package = module.name if module.is_package else module.name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = _resolve(alias.name, modules)
                if target:
                    yield target, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join([*base_parts, *([node.module] if node.module else [])])
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                target = sub if sub in modules else _resolve(base, modules)
                if target:
                    yield target, node.lineno
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            fname = (
                func.attr
                if isinstance(func, ast.Attribute)
                else func.id
                if isinstance(func, ast.Name)
                else ""
            )
            if fname in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                target = _resolve(node.args[0].value, modules)
                if target:
                    yield target, node.lineno


def import_graph() -> tuple[dict[str, Module], dict[str, dict[str, int]]]:
    """Modules and, per module, the package modules it imports (-> first line importing it)."""
    modules = find_modules()
    graph: dict[str, dict[str, int]] = {}
    for name, module in modules.items():
        edges: dict[str, int] = {}
        for target, line in imports_of(module, modules):
            if target != name:
                edges.setdefault(target, line)
        graph[name] = edges
    return modules, graph


def strongly_connected(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module, each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
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
    return out


def one_cycle(component: list[str], graph: dict[str, dict[str, int]]) -> list[str]:
    """A shortest cycle through the component's first module (breadth-first), closed."""
    members = set(component)
    start = component[0]
    parent: dict[str, str] = {}
    queue = [start]
    while queue:
        node = queue.pop(0)
        for child in sorted(graph[node]):
            if child not in members:
                continue
            if child == start:
                path = [node]
                while path[-1] != start:
                    path.append(parent[path[-1]])
                return [*reversed(path), start]
            if child not in parent:
                parent[child] = node
                queue.append(child)
    return [start, start]  # not reached: a component of > 1 module holds a cycle


def describe(cycle: list[str], graph: dict[str, dict[str, int]]) -> str:
    return " -> ".join(
        f"{a} (line {graph[a][b]})" if i < len(cycle) - 1 else a
        for i, (a, b) in enumerate(zip(cycle, [*cycle[1:], cycle[-1]], strict=True))
    )


def subpackage_graph(
    modules: dict[str, Module], graph: dict[str, dict[str, int]]
) -> dict[str, dict[str, int]]:
    """The graph with each subpackage of ``frslam_graph`` (``datasets``, ``floorplan``, ...) as one
    node: a subpackage and a module (or another subpackage) must not import each other either."""

    def unit(name: str) -> str:
        top = ".".join(name.split(".")[:2])
        return top if top in modules and modules[top].is_package and top != ROOT else name

    out: dict[str, dict[str, int]] = {unit(m): {} for m in graph}
    for name, targets in graph.items():
        for target, line in targets.items():
            if unit(target) != unit(name):
                out[unit(name)].setdefault(unit(target), line)
    return out


@pytest.fixture(scope="module")
def graph() -> tuple[dict[str, Module], dict[str, dict[str, int]]]:
    return import_graph()


def test_the_graph_sees_the_whole_package(graph):
    modules, edges = graph
    assert "frslam_graph.floorplan.model" in modules
    assert "frslam_graph.datasets.recording" in modules  # mapped from datasets/
    assert "frslam_graph.factors" in modules  # mapped from factors/
    assert "frslam_graph.registration.mfr.register" in modules
    # function-level and relative imports count
    assert "frslam_graph.registration.mfr.coarse" in edges["frslam_graph.registration.mfr.register"]
    assert "frslam_graph.evaluation.trajectory_io" in edges["frslam_graph.datasets.rosbag"]


def test_cycle_finder_names_cycles_through_function_level_relative_and_type_only_imports(tmp_path):
    pkg = tmp_path / ROOT
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from frslam_graph.sub import b\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "b.py").write_text("from .. import c\n")
    (pkg / "c.py").write_text("import importlib\nimportlib.import_module('frslam_graph.a')\n")
    # a type-only import counts: d names e's types, e calls d
    (pkg / "d.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from frslam_graph.e import E\n"
    )
    (pkg / "e.py").write_text("from frslam_graph import d\n")
    names = ["a", "sub.b", "c", "d", "e"]
    modules = {f"{ROOT}.{v}": Module(f"{ROOT}.{v}", pkg / f"{v.replace('.', '/')}.py", False) for v in names}
    modules[ROOT] = Module(ROOT, pkg / "__init__.py", True)
    modules[f"{ROOT}.sub"] = Module(f"{ROOT}.sub", pkg / "sub" / "__init__.py", True)
    edges = {m: {t: line for t, line in imports_of(mod, modules)} for m, mod in modules.items()}
    components = sorted(strongly_connected(edges))
    assert components == [[f"{ROOT}.a", f"{ROOT}.c", f"{ROOT}.sub.b"], [f"{ROOT}.d", f"{ROOT}.e"]]
    text = describe(one_cycle(components[0], edges), edges)
    assert (
        text
        == "frslam_graph.a (line 2) -> frslam_graph.sub.b (line 1) -> frslam_graph.c (line 2) -> frslam_graph.a"
    )


def test_subpackage_graph_finds_a_module_and_a_subpackage_importing_each_other():
    """As metrics.py and datasets/ did: no module cycle (metrics -> datasets.recording,
    datasets.rosbag -> metrics), but the subpackage and the module depend on each other."""
    names = {ROOT: True, f"{ROOT}.metrics": False, f"{ROOT}.datasets": True}
    names |= {f"{ROOT}.datasets.recording": False, f"{ROOT}.datasets.rosbag": False}
    modules = {n: Module(n, Path(n), pkg) for n, pkg in names.items()}
    edges = {n: {} for n in names}
    edges[f"{ROOT}.metrics"] = {f"{ROOT}.datasets.recording": 3}
    edges[f"{ROOT}.datasets.rosbag"] = {f"{ROOT}.metrics": 7}
    assert strongly_connected(edges) == []
    assert strongly_connected(subpackage_graph(modules, edges)) == [[f"{ROOT}.datasets", f"{ROOT}.metrics"]]


def test_no_import_cycle(graph):
    _, edges = graph
    cycles = []
    for comp in strongly_connected(edges):
        cycle = one_cycle(comp, edges)
        others = [m for m in comp if m not in cycle]
        cycles.append(
            describe(cycle, edges) + (f" (and in cycles with them: {', '.join(others)})" if others else "")
        )
    assert not cycles, "import cycles (module (line of the import) -> ...):\n" + "\n".join(cycles)


def test_no_import_cycle_between_subpackages(graph):
    modules, edges = graph
    packed = subpackage_graph(modules, edges)
    cycles = [" <-> ".join(comp) for comp in strongly_connected(packed)]
    assert not cycles, "subpackages / modules importing each other:\n" + "\n".join(cycles)


def test_only_the_cli_imports_the_cli(graph):
    modules, edges = graph
    cli = f"{ROOT}.cli"
    offenders = [
        f"{name} (line {line}) imports {target}"
        for name, targets in sorted(edges.items())
        if not (name == cli or name.startswith(cli + "."))
        for target, line in sorted(targets.items())
        if target == cli or target.startswith(cli + ".")
    ]
    assert not offenders, "modules outside frslam_graph.cli importing it:\n" + "\n".join(offenders)


def test_the_library_does_not_print(graph):
    modules, _ = graph
    cli = f"{ROOT}.cli"
    offenders = []
    for name, module in sorted(modules.items()):
        if name == cli or name.startswith(cli + "."):
            continue
        tree = ast.parse(module.path.read_text(encoding="utf-8"))
        offenders += [
            f"{module.path.relative_to(REPO)}:{node.lineno}"
            for node in ast.walk(tree)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print"
        ]
    assert not offenders, (
        "print( outside frslam_graph/cli (the library returns or logs, the CLI prints):\n"
        + "\n".join(offenders)
    )
