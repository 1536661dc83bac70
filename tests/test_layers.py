"""The package's layers, read from its imports: every import of every module (function-level and TYPE_CHECKING ones
included, as tools/hooks count them) runs from a higher layer to a lower one or within a layer, and no import cycle
holds more than 3 modules. The few conveniences that reach up (Trajectory.show() into the viewers) are named below
and in docs/architecture.md; a new module must be given a layer here.

The graph is read from the source files (ast), not from sys.modules: nothing is imported, so a lazy import counts
as much as one at the top of a module.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src"

# From the bottom up. A module may import from its own layer and the layers below it.
LAYERS: list[tuple[str, list[str]]] = [
    ("foundation", ["text", "exceptions", "ordered", "metadata", "progress", "step_control", "native", "noise"]),
    ("files", ["safety", "files"]),
    ("maths", ["state", "integrators", "integrators.*", "robot"]),
    ("argument checks", ["validation"]),
    ("robots, controllers, results", ["catalog", "catalog.*", "controllers", "trajectory"]),
    ("scenes", ["scenes", "scenes.*", "sensors", "readings"]),
    ("stepping", ["recording", "kernels", "kernels.*", "core", "monitor", "torques", "driver"]),
    ("entry points", ["simulation", "rollout", "stepper", "gym"]),
    ("studies", ["derivatives", "stability", "analysis", "bench", "bench.*"]),
    ("results read back", ["recorded", "tables"]),
    ("viewers", ["viz", "viz.*"]),
    ("command line", ["", "__main__", "cli", "cli.*"]),
]

# The one kind of import allowed to reach up: a convenience on a lower layer's object that hands over to a higher
# one (docs/architecture.md lists them). (importer, imported): the convenience.
NAMED_EXCEPTIONS: dict[tuple[str, str], str] = {
    ("trajectory", "viz.notebook"): "Trajectory.show()",
    ("trajectory", "tables"): "Trajectory.to_dataframe()",
    ("scenes.scene", "simulation"): "Scene.run()",
}

MAX_CYCLE = 3


def module_name(path: Path, root: Path) -> str:
    """'multibody_sim.scenes.scene' for src/multibody_sim/scenes/scene.py (a package: its folder's name)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path, package: str = "multibody_sim") -> dict[str, dict[str, int]]:
    """{module: {imported module: line}} over the package's modules (names relative to the package, "" for the
    package itself), from every import statement anywhere in each file."""
    files = {module_name(p, root): p for p in sorted((root / package).rglob("*.py"))}
    graph: dict[str, dict[str, int]] = {}
    for name, path in files.items():
        found: dict[str, int] = {}
        base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.ImportFrom):
                where = base[: len(base) - node.level + 1] if node.level else []
                module = ".".join(where + ([node.module] if node.module else []))
                submodules = [f"{module}.{alias.name}" for alias in node.names if f"{module}.{alias.name}" in files]
                # `from . import sub` imports the submodule only; `from .m import name` imports m
                targets = submodules if len(submodules) == len(node.names) else [module, *submodules]
            elif isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                continue
            for target in targets:
                while target and target not in files:  # `from .m import name`: the module m
                    target = target.rpartition(".")[0]
                if target and target != name:
                    found.setdefault(target, node.lineno)
        graph[name] = found

    def short(module: str) -> str:
        return "" if module == package else module.removeprefix(package + ".")

    return {short(m): {short(t): line for t, line in targets.items()} for m, targets in graph.items()}


def layer_of(module: str, layers: list[tuple[str, list[str]]]) -> int | None:
    """The index of the layer whose patterns match the module ("x.*": x's submodules), or None."""
    for index, (_, patterns) in enumerate(layers):
        for pattern in patterns:
            if module == pattern or (pattern.endswith(".*") and module.startswith(pattern[:-1])):
                return index
    return None


def upward_imports(graph: dict[str, dict[str, int]], layers: list[tuple[str, list[str]]]) -> list[tuple[str, str, int]]:
    """(importer, imported, line) of every import into a higher layer."""
    found = []
    for module, targets in graph.items():
        low = layer_of(module, layers)
        for target, line in targets.items():
            high = layer_of(target, layers)
            if low is not None and high is not None and high > low:
                found.append((module, target, line))
    return sorted(found)


def cycles(graph: dict[str, dict[str, int]], ignored: set[tuple[str, str]]) -> list[list[str]]:
    """The import cycles (strongly connected components of more than one module), largest first, without the
    `ignored` edges (Tarjan's algorithm, iterative)."""
    edges = {m: [t for t in targets if t in graph and (m, t) not in ignored] for m, targets in graph.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, 0)]
        while work:
            node, i = work.pop()
            if i == 0:
                index[node] = low[node] = len(index)
                stack.append(node)
                on_stack.add(node)
            if i < len(edges[node]):
                work.append((node, i + 1))
                nxt = edges[node][i]
                if nxt not in index:
                    work.append((nxt, 0))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
    return sorted(found, key=len, reverse=True)


def problems(
    root: Path,
    layers: list[tuple[str, list[str]]] = LAYERS,
    exceptions: dict[tuple[str, str], str] = NAMED_EXCEPTIONS,
    package: str = "multibody_sim",
) -> list[str]:
    """Everything wrong with the package's layering, one line each (empty when the layers hold)."""
    graph = import_graph(root, package)
    unplaced = [m for m in graph if layer_of(m, layers) is None]
    said = [f"module {m or package!r} has no layer in tests/test_layers.py" for m in unplaced]
    for module, target, line in upward_imports(graph, layers):
        if (module, target) not in exceptions:
            said.append(f"{module or package} (line {line}) imports {target}, a higher layer")
    for module, target in exceptions:
        if target not in graph.get(module, {}):
            said.append(f"named exception {module} -> {target} is gone: remove it from NAMED_EXCEPTIONS")
    for cycle in cycles(graph, set(exceptions)):
        if len(cycle) > MAX_CYCLE:
            said.append(f"import cycle of {len(cycle)} modules: {', '.join(cycle)}")
    return said


def test_the_package_keeps_its_layers() -> None:
    assert problems(SRC) == []


def test_the_named_exceptions_are_named_in_the_architecture() -> None:
    """Each convenience that reaches up is one docs/architecture.md names."""
    text = (SRC.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert [name for name in NAMED_EXCEPTIONS.values() if f"`{name}`" not in text] == []


def test_the_layer_patterns_cover_each_module_once() -> None:
    graph = import_graph(SRC)
    twice = [m for m in graph if sum(layer_of(m, [layer]) is not None for layer in LAYERS) > 1]
    assert twice == []


@pytest.fixture
def package(tmp_path: Path) -> Path:
    """A small package whose lower module reaches up inside a function, and whose three modules form a cycle
    through a TYPE_CHECKING import."""
    root = tmp_path / "src"
    (root / "pkg" / "sub").mkdir(parents=True)
    files = {
        "pkg/__init__.py": "",
        "pkg/low.py": "def f():\n    from .high import g\n    return g\n",
        "pkg/mid.py": "from . import low\n",
        "pkg/high.py": (
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .sub import deep\nfrom .mid import low\n"
        ),
        "pkg/sub/__init__.py": "",
        "pkg/sub/deep.py": "from ..low import f\nimport pkg.mid\n",
    }
    for name, text in files.items():
        (root / name).write_text(text)
    return root


def test_the_checks_see_lazy_imports_and_can_fail(package: Path) -> None:
    """The checks find a function-level upward import, and cycles through function-level and TYPE_CHECKING
    imports: this test fails if the graph missed either kind."""
    layers = [("bottom", ["", "low", "sub", "sub.*"]), ("middle", ["mid"]), ("top", ["high"])]
    graph = import_graph(package, "pkg")
    assert graph["low"] == {"high": 2}
    assert graph["mid"] == {"low": 1} and graph["sub.deep"] == {"low": 1, "mid": 2}
    assert cycles(graph, set()) == [["high", "low", "mid", "sub.deep"]]
    found = problems(package, layers, {}, "pkg")
    assert found == [
        "low (line 2) imports high, a higher layer",
        "sub.deep (line 2) imports mid, a higher layer",
        "import cycle of 4 modules: high, low, mid, sub.deep",
    ]
    allowed = {("low", "high"): "f()", ("sub.deep", "mid"): "x"}
    assert problems(package, layers, allowed, "pkg") == []  # the cycle was made of the two named edges
