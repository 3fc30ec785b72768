"""The package's structure: imports go down the layers, never up, and form no cycle (``docs/architecture.md``).

Imports are read from the source (every ``import``, also inside functions and under ``TYPE_CHECKING``), so a lazy
import cannot hide an upward dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "lcreg",
        "lcreg.types",
        "lcreg.checks",
        "lcreg.config",
        "lcreg.checkpoints",
        "lcreg.figures",
        "lcreg.reference",
        "lcreg.methods",
    ),
    ("lcreg.geometry",),
    ("lcreg.metrics", "lcreg.nn", "lcreg.data"),
    ("lcreg.models",),
    ("lcreg.baselines",),
    ("lcreg.weights", "lcreg.resume", "lcreg.callbacks", "lcreg.viz", "lcreg.registration", "lcreg.deploy"),
    ("lcreg.cli",),
    ("lcreg.experiments",),
    ("lcreg.__main__",),
)
"""The layers, bottom first: a module imports only its own layer and the ones below (``lcreg`` itself is the lazy
table of public names and imports nothing when imported). The library is everything below ``lcreg.experiments``."""


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in SRC.joinpath("lcreg").rglob("*.py")}


def imported(name: str) -> set[str]:
    """The lcreg modules that module ``name`` imports (a ``from X import y`` of a submodule ``y`` counts as ``X.y``)."""
    path, found = MODULES[name], set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target.split(".")[0] == "lcreg" and target != name:
                found.add(target)
    return found


GRAPH = {name: imported(name) for name in MODULES}


def layer(name: str) -> int:
    """Index in :data:`LAYERS` of the longest prefix that names ``name``'s group."""
    best = max(
        (prefix for group in LAYERS for prefix in group if name == prefix or name.startswith(prefix + ".")), key=len
    )
    return next(i for i, group in enumerate(LAYERS) if best in group)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in graph[node]:
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                other = stack.pop()
                component.append(other)
                if other == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def test_every_module_has_a_layer() -> None:
    for name in MODULES:
        assert layer(name) >= 0, name


def test_no_import_goes_up_a_layer() -> None:
    upward = sorted(
        f"{name} (layer {layer(name)}) imports {other} (layer {layer(other)})"
        for name, others in GRAPH.items()
        for other in others
        if layer(other) > layer(name)
    )
    assert upward == []


def test_no_import_cycle() -> None:
    assert cycles(GRAPH) == []


def test_the_library_never_imports_the_experiments() -> None:
    library = [name for name in MODULES if layer(name) < layer("lcreg.experiments")]
    assert not [name for name in library if any(o.startswith("lcreg.experiments") for o in GRAPH[name])]


@pytest.mark.parametrize(
    ("graph", "expected"),
    [
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}, [["a", "b", "c"]]),
        ({"a": {"b"}, "b": set()}, []),
    ],
)
def test_the_cycle_finder_finds_cycles(graph: dict[str, set[str]], expected: list[list[str]]) -> None:
    assert cycles(graph) == expected


def test_the_import_reader_sees_lazy_and_relative_imports() -> None:
    assert "lcreg.experiments.reproduce.command" in GRAPH["lcreg.__main__"]  # inside a function
    assert "lcreg.cli" in GRAPH["lcreg.experiments.benchmarking.building"]  # under TYPE_CHECKING and in a function
