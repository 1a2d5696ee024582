"""The package's layers point one way (docs/development.md): each module imports only from its own
layer or those below it, `ppo` and `tasks` not from each other, and no two modules import each
other, directly or round a cycle. Read from the source (an AST walk): no module is imported.

    robot_side  <  core  <  io, wrappers  <  ppo, tasks, viz  <  the top-level modules  <  cli

The command lines (`jaxnav.cli`, and `jaxnav.train`, `jaxnav.evaluate`: modules that only run one)
are the top layer: no library module imports them. `jaxnav.export`, `replay` and `twin` are library
modules that `python -m` also runs: the command line they import under `if __name__ == "__main__":`
is no arrow, since that code runs only when the module is the program, never for an importer.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "jaxnav"
RANK = {"robot_side": 0, "core": 1, "io": 2, "wrappers": 2, "ppo": 3, "tasks": 3, "viz": 3}
TOP = 4  # jaxnav/*.py: the library's top (what composes a run, training, evaluation)
CLI = 5  # jaxnav/cli/ and the modules `python -m jaxnav.<command>` runs
# Modules that only run a command line (`python -m` entry points).
COMMANDS = {"train", "evaluate"}
APART = {("ppo", "tasks"), ("tasks", "ppo")}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 1 and (parts[1] == "cli" or parts[1] in COMMANDS):
        return "cli"
    return parts[1] if len(parts) > 1 and parts[1] in RANK else "top"


def rank(name: str) -> int:
    return CLI if name == "cli" else RANK.get(name, TOP)


def is_main_block(node: ast.AST) -> bool:
    """`if __name__ == "__main__":`, what runs only when the module is the program."""
    test = getattr(node, "test", None)
    return (
        isinstance(node, ast.If)
        and isinstance(test, ast.Compare)
        and isinstance(test.left, ast.Name)
        and test.left.id == "__name__"
        and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in test.comparators)
    )


def imports(path: Path) -> set[str]:
    """The jaxnav modules `path` imports, anywhere in the file (inside functions too), but for
    its `if __name__ == "__main__":` block."""
    tree = ast.parse(path.read_text())
    tree.body = [node for node in tree.body if not is_main_block(node)]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("jaxnav")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith("jaxnav"):
                found.add(node.module)
                found |= {f"{node.module}.{a.name}" for a in node.names}
    return found


def graph() -> dict[str, set[str]]:
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {m: {t for t in imports(p) if t in modules and t != m} for m, p in modules.items()}


def test_layers_point_one_way():
    wrong = []
    for module, targets in graph().items():
        here = layer(module)
        for target in targets:
            there = layer(target)
            if rank(there) > rank(here) or (here, there) in APART:
                wrong.append(f"{module} -> {target}")
    assert not wrong, "imports against the layers:\n" + "\n".join(sorted(wrong))


def test_no_import_cycles():
    g = graph()
    packages = {m for m in g if (PACKAGE / Path(*m.split(".")[1:]) / "__init__.py").exists()}
    g = {m: {t for t in ts if t not in packages} for m, ts in g.items() if m not in packages}
    seen, stack, cycles = set(), [], []

    def visit(m):
        if m in stack:
            cycles.append(" -> ".join([*stack[stack.index(m) :], m]))
            return
        if m in seen:
            return
        seen.add(m)
        stack.append(m)
        for t in sorted(g.get(m, ())):
            visit(t)
        stack.pop()

    for m in sorted(g):
        visit(m)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_importing_jaxnav_changes_no_global_state():
    """`import jaxnav` (and its submodules) installs no signal handler and no import hook, and
    MJX's import prints nothing (its absent Warp backend's lines are kept off stdout)."""
    import subprocess
    import sys

    code = (
        "import signal, sys\n"
        "ours = lambda: [f for f in sys.meta_path if 'jaxnav' in type(f).__module__]\n"
        "state = lambda: (ours(), signal.getsignal(signal.SIGINT), sys.stdout, sys.excepthook)\n"
        "before = state()\n"
        "import jaxnav\n"
        "print(before == state())\n"
        "import jaxnav.tasks.base, jaxnav.evaluation, jaxnav.cli.evaluate\n"
        "print(before == state())\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "True\nTrue\n"  # and nothing else printed


def test_train_and_evaluate_are_plain_functions():
    """`jaxnav.train` and `jaxnav.evaluate` are the library's functions, whatever was imported
    before: the `python -m` modules of the same names refuse to be imported (which would rebind
    the package's attribute to a module), naming where the command line lives."""
    import importlib
    import inspect

    import pytest

    import jaxnav
    from jaxnav import evaluation, training

    for name, library in (("train", training), ("evaluate", evaluation)):
        with pytest.raises(ImportError, match=f"jaxnav.cli.{name}"):
            importlib.import_module(f"jaxnav.{name}")
        assert inspect.isfunction(getattr(jaxnav, name))
        assert getattr(jaxnav, name) is getattr(library, name)
    from jaxnav import evaluate, train

    assert (train, evaluate) == (training.train, evaluation.evaluate)
