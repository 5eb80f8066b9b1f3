"""No import circles in ``qpctl/``, and one direction of dependence (issue 23, docs/tick.md).

The test reads every import statement of every module with :mod:`ast` — at module level, inside
functions and methods, and under ``if TYPE_CHECKING:`` alike: an import deferred into a function is
still a dependence, and none may close a circle. An edge ``a → b`` means "a imports b"; importing
``qpctl.x.y`` also runs the package ``qpctl.x``'s ``__init__`` first, so it adds ``a → qpctl.x``
(except from inside ``qpctl.x`` itself, which that ``__init__`` may import: Python's packages work
so). The root package ``qpctl`` is the front door: it imports the public API from every layer and
nothing inside ``qpctl/`` imports it. Imports by string (the registries' ``"module:Class"`` entries,
``importlib.import_module``) are not statements and are not read: they name a class to build on
first use, in the registry's own layer or above.

Layers, lowest first (:data:`LAYERS`): a module may import modules of its own layer or below,
never above. A new module must be given a layer here (the test fails on a module without one).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import qpctl

ROOT = Path(qpctl.__file__).resolve().parent

#: (layer, module-name prefixes), lowest first: the direction of dependence of issue 23 — the world,
#: the state and kernels, the law (then the tick's workspace on both), tasks and constraints, the
#: formulation and solvers, the controllers, simulation, adapters, scenario, run, applications.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("foundation", ("qpctl.errors", "qpctl.config", "qpctl.linalg", "qpctl.qp")),
    ("world", ("qpctl.robot", "qpctl.geometry", "qpctl.paths", "qpctl.orientation")),
    ("state and kernels", ("qpctl.kernels", "qpctl.state", "qpctl.native")),  # native: Pinocchio's C++ brake loop
    ("law", ("qpctl.law", "qpctl.barrier_design")),
    ("tick", ("qpctl.tick", "qpctl.dynamics")),
    ("tasks and constraints", ("qpctl.tasks", "qpctl.constraints")),
    ("perception", ("qpctl.perception",)),  # the depth map: frames → kernels → snapshot → the field's rows
    ("formulation and solvers", ("qpctl.formulation", "qpctl.solvers", "qpctl.outcome", "qpctl.fallbacks",
                                 "qpctl.warmup")),
    ("controllers", ("qpctl.controllers",)),
    ("simulation", ("qpctl.simulation", "qpctl.scenes", "qpctl.safety")),  # safety: brakes rolled out in the simulator
    ("adapters", ("qpctl.adapters",)),
    ("scenario", ("qpctl.scenario", "qpctl.scenario_orientation")),
    ("replay", ("qpctl.replay",)),
    ("run", ("qpctl.run", "qpctl.plots")),
    ("applications", ("qpctl.cli", "qpctl.bench", "qpctl.sweep")),
)


def module_names(root: Path = ROOT) -> dict[str, Path]:
    """Dotted name → file of every module and package ``__init__`` under ``root``."""
    out: dict[str, Path] = {}
    for path in sorted(root.rglob("*.py")):
        parts = ("qpctl", *path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _package_of(name: str, path: Path) -> str:
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def imports_of(name: str, path: Path, modules: set[str]) -> set[str]:
    """The qpctl modules ``name`` imports anywhere in its file (see module docstring)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = _package_of(name, path)
    targets: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            targets.add(source)
            targets.update(f"{source}.{alias.name}" for alias in node.names)
    out = {t for t in targets if t in modules and t != name}
    for target in list(out):  # the packages whose __init__ runs first
        parts = target.split(".")
        for k in range(2, len(parts)):
            parent = ".".join(parts[:k])
            if not (name == parent or name.startswith(parent + ".")):
                out.add(parent)
    return out


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    files = module_names(root)
    names = set(files)
    return {name: imports_of(name, path, names) for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
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
                    work.append((child, iter(sorted(graph.get(child, ())))))
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


def layer_of(name: str) -> int | None:
    best: tuple[int, int] | None = None  # (prefix length, layer)
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (name == prefix or name.startswith(prefix + ".")) and (best is None or len(prefix) > best[0]):
                best = (len(prefix), i)
    return None if best is None else best[1]


GRAPH = import_graph()


def test_the_reader_sees_imports_of_every_kind():
    """The graph holds edges of each kind the docstring lists, so the tests below cannot pass on an
    empty graph: module-level, relative, and the implicit ``__init__`` of a package."""
    assert "qpctl.kernels.codes" in GRAPH["qpctl.kernels.tick"]  # module level, from-import of names
    assert "qpctl.tick" in GRAPH["qpctl.controllers.base"]
    assert "qpctl.controllers.qp" in GRAPH["qpctl.controllers.config"]  # inside a function
    assert "qpctl.simulation" in GRAPH["qpctl.scenario"]  # the package whose __init__ runs first
    assert sum(len(v) for v in GRAPH.values()) > 300


def test_the_cycle_finder_finds_circles():
    toy = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a", "e"}, "e": {"d"}, "f": set()}
    assert sorted(cycles(toy)) == [["a", "b", "c"], ["d", "e"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles():
    found = cycles(GRAPH)
    assert not found, "import circles in qpctl/ (each a set of modules that import one another):\n" + "\n".join(
        " ↔ ".join(c) for c in found)


def test_nothing_inside_the_package_imports_its_front_door():
    assert not [name for name, deps in GRAPH.items() if "qpctl" in deps and name != "qpctl"]


def test_every_module_has_a_layer():
    assert not [name for name in GRAPH if name != "qpctl" and layer_of(name) is None]


@pytest.mark.parametrize("layer", [name for name, _ in LAYERS])
def test_imports_go_down_the_layers(layer):
    """No module of this layer imports a module of a layer above it."""
    i = [name for name, _ in LAYERS].index(layer)
    upward = sorted(f"{name} → {dep} ({LAYERS[layer_of(dep)][0]})"  # type: ignore[index]
                    for name, deps in GRAPH.items() if name != "qpctl" and layer_of(name) == i
                    for dep in deps if (layer_of(dep) or 0) > i)
    assert not upward, f"imports from {layer!r} up the layers:\n" + "\n".join(upward)
