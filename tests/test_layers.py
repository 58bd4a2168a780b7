"""Imports point one way: ``cluster`` -> ``population`` -> ``ocv2``, and no module imports itself back.

Every ``.py`` file of the three packages is read with ``ast`` (nothing is imported), and every import in it
counts, wherever it stands: at the top, inside a function (the lazy imports that keep ``import ocv2`` or
``ocv2 validate`` light) or under ``if TYPE_CHECKING``, plus ``importlib.import_module("...")`` with a
literal name. A lazy import hides a cycle from Python but not from a reader, so the test treats it like any
other; so does a ``"package.module:function"`` string (how ``cluster.cli.main.COMMANDS`` names a command
module it imports when that command runs). ``from a.b import c`` is an arrow to the module ``a.b.c`` when
that is a module, else to ``a.b``.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Lowest first: a module may import from its own layer and the ones before it.
LAYERS = ("ocv2", "population", "cluster")
#: ``"cluster.cli.train:run_train"``: a function named by string, its module imported when it is called.
NAMED = re.compile(r"(?:ocv2|population|cluster)(?:\.\w+)*:\w+")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(path): path for layer in LAYERS for path in sorted((ROOT / layer).rglob("*.py"))}


def imported(path: Path, name: str, known: set[str] | None) -> set[str]:
    """The project modules that the file at ``path`` (module ``name``) imports anywhere in its body; with
    ``known=None``, every module name it imports, third-party ones included."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            for alias in node.names:
                found.add(f"{source}.{alias.name}" if f"{source}.{alias.name}" in (known or ()) else source)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            found.add(node.args[0].value)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and NAMED.fullmatch(node.value):
            found.add(node.value.partition(":")[0])
    if known is None:
        return found
    return {module for module in found if module in known and module != name}


def import_graph() -> dict[str, set[str]]:
    found = modules()
    return {name: imported(path, name, set(found)) for name, path in found.items()}


def layer(module: str) -> int:
    return LAYERS.index(module.split(".")[0])


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan), each as a sorted list."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def one_cycle(graph: dict[str, set[str]], component: list[str]) -> list[str]:
    """A shortest path from the component's first module back to itself, for the failure message."""
    start, members = component[0], set(component)
    paths, frontier = {start: [start]}, [start]
    while frontier:
        following = []
        for node in frontier:
            for target in sorted(graph[node] & members):
                if target == start:
                    return paths[node] + [start]
                if target not in paths:
                    paths[target] = paths[node] + [target]
                    following.append(target)
        frontier = following
    raise AssertionError(f"{component} is not a cycle")


def test_the_graph_sees_lazy_and_relative_imports():
    graph = import_graph()
    assert "population.config.schema" in graph["population.config"]  # top-level, from the package
    assert "cluster.api" in graph["cluster"]  # importlib.import_module("cluster.api") inside __getattr__
    assert "population.networks" in graph["population.memory"]  # inside a function
    assert "cluster.cli.train" in graph["cluster.cli.main"]  # COMMANDS' "cluster.cli.train:add_train"
    assert len(graph) > 60


def test_no_import_cycles():
    graph = import_graph()
    found = [" -> ".join(one_cycle(graph, component)) for component in cycles(graph)]
    assert not found, "import cycles:\n" + "\n".join(found)


def test_imports_point_down():
    upward = [
        f"{module} imports {target}"
        for module, targets in sorted(import_graph().items())
        for target in sorted(targets)
        if layer(target) > layer(module)
    ]
    assert not upward, "imports from a lower layer to a higher one (ocv2 <- population <- cluster):\n" + "\n".join(
        upward
    )


def test_the_jax_layers_import_neither_ray_nor_mcap_nor_the_reference():
    """docs/design: ``ocv2/`` and ``population/`` run under jit unchanged, so Ray and MCAP stay in ``cluster/``;
    jaxmarl is the tests' behavioural reference only."""
    found = [
        f"{name} imports {module}"
        for name, path in sorted(modules().items())
        if layer(name) < LAYERS.index("cluster")
        for module in sorted(imported(path, name, None))
        if module.split(".")[0] in ("ray", "mcap", "jaxmarl")
    ]
    assert not found, "\n".join(found)


def test_the_checks_fail_on_a_cycle_and_an_upward_import():
    graph = {"ocv2.a": {"population.b"}, "population.b": {"population.c"}, "population.c": {"population.b"}}
    assert cycles(graph) == [["population.b", "population.c"]]
    assert one_cycle(graph, ["population.b", "population.c"]) == ["population.b", "population.c", "population.b"]
    assert layer("population.b") > layer("ocv2.a")
