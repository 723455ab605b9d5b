"""The packages' module-level imports form no cycle, and no module reads another's private names.

Both are read from the source with `ast`, so they hold for every module whether or not a test
imports it. An import runs when its module is imported: at module level (inside ``if``/``try``
and class bodies too), not inside a function and not under ``if TYPE_CHECKING:``. Importing
``a.b.c`` runs the packages ``a`` and ``a.b`` first, so those count as imported too (but not the
importer's own packages, which are running already). A function-level import that exists only to
dodge a cycle is a cycle all the same; the ones left are named in `FUNCTION_LEVEL_CYCLES`.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("downwash_core", "downwash_trajectories", "controllers", "sim", "downwash", "downwash_envs", "experiments")

# Cycles that close only through an import inside a function, each to be broken where it is
# (modules this check may not fix: a registry under rework, an experiment's command line).
FUNCTION_LEVEL_CYCLES = {
    # resolve_field_spec imports the fitted-field reader, which looks its base field up in FIELDS
    frozenset({"sim.fields.registry", "sim.fields.fitted"}),
    # the command line reads a config file through config_file, which builds on common's options and writes the
    # tables in force through components, which applies them
    frozenset({"experiments.common", "experiments.components", "experiments.config_file"}),
}


def _modules() -> dict[str, Path]:
    """{dotted name: path} of every module of the packages (a package by its __init__)."""
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = _modules()


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.Module, functions: bool) -> list[ast.Import | ast.ImportFrom]:
    """The import statements that run when the module is imported (with `functions`: all of them)."""
    found, todo = [], list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append(node)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)) and not functions:
            continue
        elif isinstance(node, ast.If) and _is_type_checking(node) and not functions:
            todo.extend(node.orelse)
            continue
        todo.extend(child for child in ast.iter_child_nodes(node) if isinstance(child, ast.stmt))
    return found


def _targets(module: str, node: ast.Import | ast.ImportFrom) -> set[str]:
    """The modules of the packages that one import statement of `module` runs."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        if node.level:
            base = module.split(".") if MODULES[module].name == "__init__.py" else module.split(".")[:-1]
            base = base[:len(base) - (node.level - 1)]
            source = ".".join(base + ([node.module] if node.module else []))
        else:
            source = node.module or ""
        # `from package import submodule` imports the submodule; `from module import name` the module
        names = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in MODULES else source for alias in node.names]
    out = set()
    for name in names:
        parts = name.split(".")
        for i in range(1, len(parts) + 1):  # the packages above it run first
            prefix = ".".join(parts[:i])
            if prefix in MODULES:
                out.add(prefix)
    return {t for t in out if t != module and not module.startswith(t + ".")}  # not its own packages


def import_graph(functions: bool = False) -> dict[str, set[str]]:
    """{module: the modules of the packages it imports}, at module level (with `functions`: anywhere)."""
    graph = {}
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text(), str(path))
        graph[module] = set().union(*(_targets(module, n) for n in _import_nodes(tree, functions)))
    return graph


def cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan): every module of one lies on a
    cycle through every other."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []

    def visit(v: str) -> None:  # recursion depth: the longest import chain, a few dozen
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(component)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return components


def _one_cycle(graph: dict[str, set[str]], component: set[str]) -> list[str]:
    """A closed path through the component's smallest module: a -> b -> ... -> a (breadth first)."""
    start = min(component)
    paths = {start: [start]}
    todo = [start]
    while todo:
        v = todo.pop(0)
        for w in sorted(graph[v] & component):
            if w == start:
                return paths[v] + [start]
            if w not in paths:
                paths[w] = paths[v] + [w]
                todo.append(w)
    raise AssertionError(f"no cycle through {start}")


def _shown(graph: dict[str, set[str]], found: list[set[str]]) -> str:
    return "\n".join(f"{' -> '.join(_one_cycle(graph, c))} (of {sorted(c)})" for c in found)


def test_the_scan_finds_every_package_and_resolves_relative_and_package_imports():
    graph = import_graph()
    assert {"sim.simulator", "sim.fields", "sim.fields.registry", "experiments.report"} <= set(graph)
    assert "sim.plan" in graph["sim.simulator"] and "controllers.lqr" in graph["sim.plan"]
    assert "sim.fields" in graph["downwash.field_fit"]  # importing sim.fields.registry runs sim.fields first
    assert "sim.fields" not in graph["sim.fields.shed"]  # (its own package is running already)
    toy = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(toy) == [{"a", "b", "c"}] and _one_cycle(toy, {"a", "b", "c"}) == ["a", "b", "c", "a"]


def test_module_level_imports_form_no_cycle():
    graph = import_graph()
    found = cycles(graph)
    assert not found, "import cycles (module level):\n" + _shown(graph, found)


def test_function_level_imports_close_only_the_known_cycles():
    """A cycle through an import inside a function is one waiting to happen; `sim` has none of its own."""
    graph = import_graph(functions=True)
    found = cycles(graph)
    unknown = [c for c in found if frozenset(c) not in FUNCTION_LEVEL_CYCLES]
    assert not unknown, "import cycles through function-level imports:\n" + _shown(graph, unknown)
    gone = FUNCTION_LEVEL_CYCLES - {frozenset(c) for c in found}
    assert not gone, f"no longer cycles, remove from FUNCTION_LEVEL_CYCLES: {sorted(map(sorted, gone))}"


# ----------------------------------------------------------------------------- private names

# A NamedTuple's public API starts with an underscore.
NAMEDTUPLE_API = frozenset({"_asdict", "_replace", "_fields", "_field_defaults", "_make"})


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__")) and name not in NAMEDTUPLE_API


def _own(node: ast.expr) -> bool:
    """`self`, `cls` or `super()`: the object's own attributes."""
    return (isinstance(node, ast.Name) and node.id in ("self", "cls")) or (
        isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "super")


def private_reads(module: str, tree: ast.Module) -> set[tuple[str, str]]:
    """(module, name) for each private name `module` takes from another object or module: `x._name`,
    `getattr(x, "_name")` (and hasattr, setattr) for x not its own, and `from m import _name`."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr) and not _own(node.value):
            out.add((module, node.attr))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
              and node.func.id in ("getattr", "hasattr", "setattr") and len(node.args) >= 2
              and isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str)
              and _private(node.args[1].value) and not _own(node.args[0])):
            out.add((module, node.args[1].value))
        elif isinstance(node, ast.ImportFrom):
            out.update((module, alias.name) for alias in node.names if _private(alias.name))
    return out


def all_private_reads() -> set[tuple[str, str]]:
    found = set()
    for module, path in MODULES.items():
        found |= private_reads(module, ast.parse(path.read_text(), str(path)))
    return found


# Private names of other libraries that this project reads, each where and why: none of them has a public
# way to the same thing. The project's own modules read no private name of one another (the test below).
THIRD_PARTY_PRIVATE_READS = {
    ("sim.plan", ("_address",)): "MuJoCo's MjData._address: the scratch data the fused tick steps by address",
    ("sim.physics", ("_address", "_models")): "MuJoCo's MjModel/MjData._address and Batch._models",
    ("downwash_core.jit", ("_locator_classes",)): "numba's cache locators, extended in place",
    ("downwash.ensemble_network", ("_u", "_v")): "torch's spectral-norm vectors",
    ("downwash.ensemble_settle", ("_u", "_v")): "torch's spectral-norm vectors",
    ("downwash.models", ("_u", "_v")): "torch's spectral-norm vectors (its power iteration, settled in place)",
    ("downwash.numpy_mlp", ("_u", "_v")): "torch's spectral-norm vectors",
    ("downwash_envs.evaluation", ("_setup_learn",)): "stable-baselines3's callback set-up",
    ("downwash_envs.rendering", ("_MUJOCO_GL",)): "MuJoCo's chosen GL back end",
    ("downwash_envs.viewer", ("_MJPYTHON",)): "MuJoCo's viewer: whether it runs under mjpython",
}


def test_the_private_scan_sees_attributes_getattr_and_imports_but_not_own_names():
    code = ("from m import _a, b\nx._c\ngetattr(y, '_d')\nself._e\ncls._f\nsuper()._g\nz.__dict__\n"
            "t._asdict()\nhasattr(w, '_h')\n")
    assert private_reads("p", ast.parse(code)) == {("p", n) for n in ("_a", "_c", "_d", "_h")}


def test_no_module_reads_another_modules_private_names():
    found = all_private_reads()
    known = {(module, name) for (module, names) in THIRD_PARTY_PRIVATE_READS for name in names}
    new = sorted(found - known)
    assert not new, ("private names read across modules (make them public, or give the owner a public way): "
                     + ", ".join(f"{m}: {n}" for m, n in new))
    gone = sorted(known - found)
    assert not gone, "no longer read, remove from THIRD_PARTY_PRIVATE_READS: " + ", ".join(f"{m}: {n}" for m, n in gone)


def test_sim_plan_reads_no_private_attribute_of_the_simulator():
    """The plan reads the simulator's public attributes and the bound state it hands over (`PlanInputs`)."""
    tree = ast.parse(MODULES["sim.plan"].read_text())
    reads = {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute) and _private(node.attr)
             and isinstance(node.value, ast.Name) and node.value.id == "sim"}
    assert not reads, sorted(reads)
