"""The layers hold (docs/architecture.md): the import contract, and light imports of the lower layers."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_import_contract_is_kept():
    """`lint-imports` checks the contracts in pyproject.toml: layers that point one way, and
    no torch, gymnasium or matplotlib below downwash and envs."""
    proc = subprocess.run(["lint-imports"], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


@pytest.mark.parametrize(
    "module, banned",
    [
        ("downwash_core.geometry", ("torch", "gymnasium", "matplotlib")),
        ("downwash_core.validate", ("torch", "gymnasium", "matplotlib")),
        ("downwash_trajectories", ("torch", "gymnasium", "matplotlib")),
        # python-control itself imports matplotlib, so the controller and the loop load it
        ("controllers.lqr", ("torch", "gymnasium")),
        ("sim.flight", ("torch", "gymnasium")),
        ("sim", ("torch", "gymnasium")),
    ],
)
def test_lower_layers_import_no_learning_or_rl_library(module, banned):
    """Importing a module of the simulation stack loads neither torch nor gymnasium (`import sim`
    included: the envs moved out of it); the foundation and the trajectories not even matplotlib."""
    code = (f"import sys, {module}; heavy = sorted(m for m in {banned!r} if m in sys.modules);"
            "print(heavy); sys.exit(1 if heavy else 0)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, f"{module} imported {proc.stdout.strip()} {proc.stderr[-2000:]}"


def test_no_experiment_imports_another():
    """Experiments share only `experiments.common` (with the option checks of `experiments.options` and the flights'
    components of `experiments.components`, the printing of `experiments.console`) and the
    tracking table (lemniscate and transect are its entries); an experiment that is a package
    (`experiments.report`) imports its own modules besides."""
    shared = {"common", "components", "console", "options", "tracking"}
    for path in (ROOT / "experiments").rglob("*.py"):
        parts = path.relative_to(ROOT / "experiments").parts
        own = {parts[0]} if len(parts) > 1 else set()  # the experiment's package, for a module inside one
        text = path.read_text()
        for line in text.splitlines():
            if line.startswith(("from experiments", "import experiments")):
                target = line.split()[1].split(".")[1] if "." in line.split()[1] else ""
                assert target in shared | own, f"{path.relative_to(ROOT)}: {line}"


MAX_MODULE_LINES = 600
# modules still over the limit, each at most as long as now (a ratchet: they may only shrink;
# each is to be split as the simulator was)
OVER_THE_LIMIT = {
}


def test_no_module_grows_past_the_limit():
    """A module reads in one sitting: at most 600 lines (sim/simulator.py was 1470)."""
    long = {}
    for pkg in ("downwash_core", "downwash_trajectories", "controllers", "sim", "downwash", "downwash_envs",
                "experiments"):
        for path in (ROOT / pkg).rglob("*.py"):
            n = len(path.read_text().splitlines())
            if n > MAX_MODULE_LINES:
                long[path.relative_to(ROOT).as_posix()] = n
    grown = {k: n for k, n in long.items() if n > OVER_THE_LIMIT.get(k, MAX_MODULE_LINES)}
    assert not grown, f"over {MAX_MODULE_LINES} lines (or longer than its recorded cap): {grown}; split it"
    shrunk = sorted(set(OVER_THE_LIMIT) - set(long))
    assert not shrunk, f"{shrunk}: now within {MAX_MODULE_LINES} lines; remove from OVER_THE_LIMIT"


PACKAGES = ("downwash_core", "downwash_trajectories", "controllers", "sim", "downwash", "downwash_envs", "experiments")
# public names defined in more than one module on purpose, each with why
DEFINED_TWICE = {
    "VEHICLE_NAMES": "experiments.vehicles lists the kinds without importing the stack (tests/test_vehicles.py ties it)",
    "make_vec_env": "each SB3 adapter module's own factory (downwash_envs.sb3 the follower's, swarm_sb3 the swarm's)",
}


def _exported_definitions(path: Path) -> set[str]:
    """The names of `__all__` that the module itself defines (a def, a class or an assignment), not imports."""
    tree = ast.parse(path.read_text())
    exported: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            # a literal list; a lazy package's (['ENV_IDS', *_LAZY]): its literal names, the rest it imports
            items = node.value.elts if isinstance(node.value, ast.List) else []
            exported = {ast.literal_eval(e) for e in items if isinstance(e, ast.Constant)}
    defined = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            defined.add(node.name)
        elif isinstance(node, ast.Assign):
            defined.update(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            defined.add(node.target.id)
    return defined & exported


def test_one_public_name_has_one_definition():
    """A public name means one thing: no two modules define it, except the static copies of
    experiments.options (tests/test_cli.py ties each to its source), an experiment's own commands
    (no experiment imports another) and the few in DEFINED_TWICE."""
    where: dict[str, list[str]] = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for name in _exported_definitions(path):
                where.setdefault(name, []).append(path.relative_to(ROOT).as_posix())
    commands = set(where.get("main", []))  # the experiments' commands
    twice = {
        name: paths for name, paths in where.items()
        if len(paths) > 1 and name not in DEFINED_TWICE
        and not (len(paths) == 2 and "experiments/options.py" in paths)
        and not all(p in commands for p in paths)
    }
    assert not twice, f"defined in more than one module: {twice}; rename one, or import it from the other"


def _nesting(node, depth=0):
    """The deepest nesting of blocks (for, while, if, with, try) inside `node`."""
    blocks = (ast.For, ast.While, ast.If, ast.With, ast.Try)
    inner = [_nesting(child, depth + isinstance(child, blocks)) for child in ast.iter_child_nodes(node)]
    return max([depth, *inner])


def test_the_fused_tick_body_fits_on_one_screen():
    """The fused kernel is a short composition of stages (sim.tick_stages): its body, docstring aside, at
    most 80 lines and four nested blocks; and no stage reads the address table (only the bundle makers do)."""
    tree = ast.parse((ROOT / "sim" / "fused.py").read_text())
    kernel = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == "_fused_kernel")
    body = kernel.body[1:] if isinstance(kernel.body[0], ast.Expr) else kernel.body  # the docstring aside
    lines = body[-1].end_lineno - body[0].lineno + 1
    assert lines <= 80, f"the fused tick's body is {lines} lines"
    depth = max(_nesting(stmt, isinstance(stmt, (ast.For, ast.While, ast.If, ast.With, ast.Try))) for stmt in body)
    assert depth <= 4, f"the fused tick nests {depth} blocks deep"
    stages = ast.parse((ROOT / "sim" / "tick_stages.py").read_text())
    readers = {f.name for f in stages.body if isinstance(f, ast.FunctionDef)
               and any(isinstance(n, ast.Name) and n.id == "tab" for n in ast.walk(f))}
    assert readers and all(name.endswith("_bundle") for name in readers), readers


def test_docs_architecture_table_lists_every_module():
    """The module table of docs/architecture.md names exactly the modules of the seven packages
    (deprecated shims aside)."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text[text.index("\n## Modules\n"):]
    section = section[: section.index("\n## ", 1)] if "\n## " in section[1:] else section
    listed = set()
    for line in section.splitlines():
        if line.startswith("| `"):
            listed.add(line.split("`")[1])
    packages = ("downwash_core", "downwash_trajectories", "controllers", "sim", "downwash", "downwash_envs")
    modules = set()
    for pkg in packages:
        for path in (ROOT / pkg).rglob("*.py"):  # subpackages too (sim.fields.momentum)
            text = path.read_text()
            if path.name == "__init__.py" or text.lstrip('"').startswith("Deprecated"):
                continue
            modules.add(".".join(path.relative_to(ROOT).with_suffix("").parts))
    modules |= {"experiments.common", "experiments.components", "experiments.config_file", "experiments.console",
                "experiments.options", "experiments.tracking"}
    assert listed == modules, (f"missing from docs/architecture.md: {sorted(modules - listed)}; "
                               f"stale: {sorted(listed - modules)}")


def test_docs_observation_table_is_the_generated_one():
    """docs/envs.md holds `downwash_envs.observation.observation_table()` verbatim (paste its output there)."""
    from downwash_envs.observation import observation_table

    assert observation_table() in (ROOT / "docs" / "envs.md").read_text()


def test_docs_swarm_observation_table_is_the_generated_one():
    """docs/envs.md holds `downwash_envs.swarm.swarm_observation_table()` verbatim (paste its output there)."""
    from downwash_envs.swarm import swarm_observation_table

    assert swarm_observation_table() in (ROOT / "docs" / "envs.md").read_text()
