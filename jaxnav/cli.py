"""`jaxnav.train` and `jaxnav.evaluate` are both modules (`python -m ...`) and functions."""

from __future__ import annotations

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
