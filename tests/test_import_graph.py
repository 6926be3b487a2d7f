"""The package's import graph: no circles, and no import that runs back up the layers of
:data:`LAYERS` (imports inside functions included); the core imports neither a simulator nor
torch."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "twin"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> list[tuple[str, list[str]]]:
    """Every import statement of ``path`` (inside functions too): the module it names, made
    absolute, and the names it takes from it."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.append((base, [alias.name for alias in node.names]))
    return found


def imported_modules(path: Path, modules: set[str]) -> set[str]:
    """The twin modules ``path`` imports (``from twin.x import y`` names twin.x.y when y is a
    module, else twin.x); package faces (``__init__``) are seen through."""
    found = set()
    for base, names in imports(path):
        for target in [f"{base}.{n}" for n in names] + [base]:
            if target in modules:
                found.add(target)
                break
    return found - {module_name(path)}


def import_graph() -> dict[str, set[str]]:
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(p) for p in paths}
    return {module_name(p): imported_modules(p, modules) for p in paths}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph[node]:
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_import_graph_sees_the_packages_modules():
    graph = import_graph()
    assert "twin.experiment" in graph and "twin.sumo.source" in graph
    assert "twin.grid" in graph["twin.scores"]


def test_a_circle_is_found():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_circles_in_twin():
    assert circles(import_graph()) == []


#: The layers of twin, lowest first: a module imports only from its own layer or lower ones. An
#: entry names a module and, with a trailing dot, every module under a package. The learned
#: swarms sit below the registry that names them (it imports them when one is built, so torch
#: loads only then); pretraining runs experiments, so it sits above the runner.
LAYERS: list[tuple[str, list[str]]] = [
    (
        "foundation: errors, notices, files, processes, clocks, resources, executors, the user boundary",
        [
            "twin",
            "twin.errors",
            "twin.notices",
            "twin.files",
            "twin.processes",
            "twin.timing",
            "twin.clock",
            "twin.seeds",
            "twin.cache_place",
            "twin.outputs",
            "twin.resources",
            "twin.executors",
            "twin.readback",
            "twin.boundary",
        ],
    ),
    (
        "core: grid, scores, idleness maps, swarm step, policies, planners, coordinator",
        [
            "twin.grid",
            "twin.mfd",
            "twin.paths",
            "twin.scores",
            "twin.states",
            "twin.coordinator",
            "twin.swarm",
            "twin.monitoring",
            "twin.idleness_maps",
            "twin.policies",
            "twin.planners",
            "twin.tours",
            "twin.belief",
            "twin.nowcast_gain",
            "twin.faults",
        ],
    ),
    ("traffic sources", ["twin.traffic", "twin.traffic."]),
    ("the patrol loop", ["twin.patrol"]),
    (
        "learned swarms (torch)",
        [
            "twin.learning",
            "twin.learning.qnet",
            "twin.learning.replay",
            "twin.learning.dqn",
            "twin.learning.online",
            "twin.learning.checkpoint",
            "twin.learning.data",
            "twin.learning.policies",
        ],
    ),
    ("the swarm registry", ["twin.swarms"]),
    ("scenario config, metrics, ceilings", ["twin.config", "twin.metrics", "twin.ceilings"]),
    ("SUMO", ["twin.sumo", "twin.sumo."]),
    ("traffic kinds", ["twin.traffic_kinds"]),
    ("the experiment runner", ["twin.experiment"]),
    ("the run folder", ["twin.runs"]),
    ("training", ["twin.env", "twin.training", "twin.training."]),
    ("report", ["twin.report", "twin.report."]),
    ("sweep", ["twin.sweep", "twin.sweep."]),
    ("transfer experiments", ["twin.transfer", "twin.transfer."]),
    ("command line", ["twin.cli", "twin.cli.", "twin.__main__"]),
]

#: The simulator's packages, imported only under twin/sumo/, and torch, only under twin/learning/
#: and twin/training/.
SIMULATOR = {"libsumo", "sumolib", "traci"}
HEAVY = {"twin.sumo.": SIMULATOR, "twin.learning.": {"torch"}, "twin.training.": {"torch"}}


def layer_of(module: str, layers=LAYERS) -> int | None:
    """The index of the layer that lists ``module`` (an exact entry wins over a package)."""
    for n, (_, entries) in enumerate(layers):
        if module in entries:
            return n
    for n, (_, entries) in enumerate(layers):
        if any(e.endswith(".") and module.startswith(e) for e in entries):
            return n
    return None


def upward_imports(graph: dict[str, set[str]], layers=LAYERS) -> list[str]:
    """Every import from a module to a module of a higher layer, as readable lines."""
    found = []
    for module, targets in sorted(graph.items()):
        for target in sorted(targets):
            if layer_of(target, layers) > layer_of(module, layers):
                found.append(
                    f"{module} ({layers[layer_of(module, layers)][0]}) imports {target} "
                    f"({layers[layer_of(target, layers)][0]})"
                )
    return found


def test_every_module_is_in_a_layer():
    assert [m for m in import_graph() if layer_of(m) is None] == []


def test_an_upward_import_is_found():
    layers = [("low", ["a", "b"]), ("high", ["c", "pkg."])]
    graph = {"a": {"b"}, "b": set(), "c": {"a"}, "pkg.x": {"c"}}
    assert upward_imports(graph, layers) == []
    graph["b"] = {"pkg.x"}
    assert upward_imports(graph, layers) == ["b (low) imports pkg.x (high)"]


def test_no_import_runs_back_up_the_layers():
    assert upward_imports(import_graph()) == []


def test_only_sumo_imports_the_simulator_and_only_learning_torch():
    found = {
        module_name(path): {base.partition(".")[0] for base, _ in imports(path)}
        & (SIMULATOR | {"torch"})
        for path in sorted(PACKAGE.rglob("*.py"))
    }
    allowed = {
        m: next((ok for prefix, ok in HEAVY.items() if m.startswith(prefix)), set()) for m in found
    }
    assert {m: heavy - allowed[m] for m, heavy in found.items() if heavy - allowed[m]} == {}
    assert found["twin.learning.qnet"] == {"torch"} and found["twin.sumo.session"]
