"""What the command-line modules share: one-line user errors, and modules that are also functions.

`jaxnav.train` and `jaxnav.evaluate` are both modules (`python -m ...`) and functions.
"""

from __future__ import annotations

import argparse
import sys
import types
from collections.abc import Callable


def make_callable(module_name: str, fn: Callable) -> None:
    """Makes module `module_name` callable as `fn`, so that `jaxnav.train(...)` works whether
    `jaxnav.train` names the module (once imported as a submodule) or the function."""

    class _CallableModule(types.ModuleType):
        def __call__(self, *args, **kwargs):
            return fn(*args, **kwargs)

    sys.modules[module_name].__class__ = _CallableModule


class UsageError(ValueError):
    """A user mistake (flag, file, field); printed as one `error: ...` line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """argparse that raises `UsageError` instead of printing usage and exiting."""

    def error(self, message):
        raise UsageError(message)


def print_error(err: BaseException) -> None:
    """`error: <message>` on stderr, folded onto one line whatever the message held."""
    print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
