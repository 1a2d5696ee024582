"""The suite's own rules (docs/development.md): a test marked slow says in its docstring (or its
module's, for a module marked whole) why it cannot be fast. Read from the source: an AST walk."""

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def marked_slow(node) -> bool:
    return any("mark.slow" in ast.unparse(d) for d in getattr(node, "decorator_list", ()))


def module_marked_slow(tree: ast.Module) -> bool:
    return any(
        isinstance(n, ast.Assign)
        and any(getattr(t, "id", "") == "pytestmark" for t in n.targets)
        and "slow" in ast.unparse(n.value)
        for n in tree.body
    )


def says_why(node) -> bool:
    return "slow" in (ast.get_docstring(node) or "").lower()


def test_every_slow_test_says_why():
    silent = []
    for path in sorted(TESTS.glob("test_*.py")):
        tree = ast.parse(path.read_text())
        if module_marked_slow(tree) and not says_why(tree):
            silent.append(f"{path.name} (the module)")
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef) and marked_slow(node) and not says_why(node):
                silent.append(f"{path.name}::{node.name}")
    assert not silent, "slow without a reason in the docstring:\n" + "\n".join(silent)


def test_the_rule_sees_a_silent_slow_test():
    tree = ast.parse("import pytest\n@pytest.mark.slow\ndef test_x():\n    '''Quick.'''\n")
    node = tree.body[1]
    assert marked_slow(node) and not says_why(node)
