"""The packages import each other only downward, as the architecture's table says, and never in a circle.

Read from the source (every ``import`` and ``from ... import`` of an ``openral_*`` package, at any
depth, lazy ones included), so a new upward arrow fails here before it confuses a reader.
"""

from __future__ import annotations

import ast
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


def test_the_scan_sees_lazy_imports_inside_functions(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from openral_dataset.writer import X\n    import openral_remote.codec\n")
    assert _imports(module) == {"openral_dataset", "openral_remote"}
