"""The packages import each other only downward, as the architecture's table says, and no module is in a circle.

Read from the source (every ``import`` and ``from ... import`` of an ``openral_*`` package, at any
depth, lazy ones included), so a new upward arrow or a new circle fails here before it confuses a reader.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

# Who may import whom (besides itself). The CLI sits on top and may import everything.
ALLOWED: dict[str, set[str]] = {
    "openral_core": set(),
    "openral_observability": {"openral_core"},
    "openral_world_state": {"openral_core", "openral_observability"},
    "openral_hal": {"openral_core", "openral_observability"},
    "openral_rskill": {"openral_core", "openral_observability", "openral_hal"},  # the leader arm reads its HAL
    "openral_remote": {"openral_core", "openral_observability", "openral_rskill"},
    "openral_perception": {"openral_core", "openral_observability", "openral_rskill", "openral_remote"},
    "openral_dataset": {"openral_core", "openral_observability"},
    "openral_console": {"openral_core", "openral_observability"},
    "openral_runner": {
        "openral_core",
        "openral_observability",
        "openral_world_state",
        "openral_hal",
        "openral_rskill",
        "openral_perception",
    },
    "openral_sim": {
        "openral_core",
        "openral_observability",
        "openral_world_state",
        "openral_hal",
        "openral_rskill",
        "openral_runner",
        "openral_dataset",
        "openral_remote",
    },
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return {name for name in found if name.startswith("openral_")}


def _graph() -> dict[str, dict[str, list[str]]]:
    """package -> imported package -> the modules that import it."""
    graph: dict[str, dict[str, list[str]]] = {}
    for package in sorted(p for p in SRC.iterdir() if p.is_dir() and p.name.startswith("openral_")):
        edges: dict[str, list[str]] = {}
        for module in sorted(package.rglob("*.py")):
            for target in _imports(module) - {package.name}:
                edges.setdefault(target, []).append(str(module.relative_to(SRC)))
        graph[package.name] = edges
    return graph


def test_every_package_imports_only_what_the_table_allows() -> None:
    upward = [
        f"{package} -> {target} ({', '.join(modules)})"
        for package, edges in _graph().items()
        if package in ALLOWED
        for target, modules in edges.items()
        if target not in ALLOWED[package]
    ]
    assert upward == []


def test_the_runner_does_not_import_the_zenoh_services() -> None:
    assert "openral_remote" not in _graph()["openral_runner"]


def test_the_package_graph_has_no_circle() -> None:
    graph = {package: set(edges) for package, edges in _graph().items()}
    done: set[str] = set()

    def visit(package: str, path: list[str]) -> None:
        assert package not in path, f"import circle: {' -> '.join([*path, package])}"
        if package in done:
            return
        for target in sorted(graph.get(package, ())):
            visit(target, [*path, package])
        done.add(package)

    for package in graph:
        visit(package, [])


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of every ``openral_*`` package (a package is its ``__init__``)."""
    modules: dict[str, Path] = {}
    for path in sorted(SRC.glob("openral_*/**/*.py")):
        parts = path.relative_to(SRC).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _module_imports(path: Path, modules: Mapping[str, Path]) -> set[str]:
    """The ``openral_*`` modules ``path`` imports, lazy ones included.

    ``from package import name`` is an import of ``package.name`` when that is a module, else of
    ``package`` (its ``__init__``).
    """
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name in modules)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in modules:
            for alias in node.names:
                submodule = f"{node.module}.{alias.name}"
                found.add(submodule if submodule in modules else node.module)
    return found


def _module_circles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected sets of more than one module (Tarjan's algorithm), each as one circle's members."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for target in sorted(graph.get(module, ())):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in on_stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            members: list[str] = []
            while not members or members[-1] != module:
                members.append(stack.pop())
                on_stack.discard(members[-1])
            if len(members) > 1:
                circles.append(sorted(members))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return circles


def test_no_module_imports_itself_back_through_others() -> None:
    modules = _modules()
    graph = {name: _module_imports(path, modules) - {name} for name, path in modules.items()}
    assert _module_circles(graph) == []


def test_the_module_scan_finds_a_lazy_circle(tmp_path: Path) -> None:
    package = tmp_path / "openral_demo"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "params.py").write_text("from openral_demo.detector import Detector\n")
    (package / "detector.py").write_text("def build():\n    from openral_demo import params\n")
    modules = {
        "openral_demo": package / "__init__.py",
        **{f"openral_demo.{p.stem}": p for p in package.glob("[!_]*.py")},
    }
    graph = {name: _module_imports(path, modules) - {name} for name, path in modules.items()}
    assert graph["openral_demo.detector"] == {"openral_demo.params"}
    assert _module_circles(graph) == [["openral_demo.detector", "openral_demo.params"]]


def test_the_scan_sees_lazy_imports_inside_functions(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from openral_dataset.writer import X\n    import openral_remote.codec\n")
    assert _imports(module) == {"openral_dataset", "openral_remote"}
