"""jaxnav: massively parallel PPO for TurtleBot 2i obstacle avoidance on MuJoCo MJX.

The public names are imported on first use, so `jaxnav.robot_side` (numpy only) imports without jax.
"""

__version__ = "0.1.0"

import contextlib
import importlib
import sys
from importlib.abc import Loader, MetaPathFinder
from importlib.machinery import PathFinder
from io import StringIO  # `import io` would be shadowed by the subpackage jaxnav.io

__all__ = [
    "LayoutError",
    "RoomLayout",
    "evaluate",
    "load_layout",
    "load_policy",
    "make_brax_env",
    "make_env",
    "train",
]

# Public name -> the module that defines it. `train` and `evaluate` are the modules themselves (both
# callable, and the `python -m` entry points: importing them lazily keeps `python -m jaxnav.train`
# from finding its own module half-imported).
_SOURCES = {
    "LayoutError": "jaxnav.io.layouts",
    "RoomLayout": "jaxnav.io.layouts",
    "load_layout": "jaxnav.io.layouts",
    "load_policy": "jaxnav.runs",
    "make_brax_env": "jaxnav.brax_env",  # imports brax, only when asked for
    "make_env": "jaxnav.tasks.registry",
    "train": None,
    "evaluate": None,
}


def __getattr__(name: str):
    if name not in _SOURCES:
        raise AttributeError(f"module 'jaxnav' has no attribute '{name}'")
    if _SOURCES[name] is None:
        return importlib.import_module(f"jaxnav.{name}")
    return getattr(importlib.import_module(_SOURCES[name]), name)


class _QuietLoader(Loader):
    """Runs a module with stdout discarded (its `print`s only)."""

    def __init__(self, loader: Loader):
        self.loader = loader

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module):
        with contextlib.redirect_stdout(StringIO()):
            self.loader.exec_module(module)


class _QuietWarpProbe(MetaPathFinder):
    """mujoco.mjx.warp prints two lines on stdout when its optional Warp backend is absent; jaxnav
    uses MJX's JAX implementation only. Whichever jaxnav module imports mjx first, this silences it."""

    NAME = "mujoco.mjx.warp"

    def find_spec(self, name, path=None, target=None):
        if name != self.NAME:
            return None
        sys.meta_path.remove(self)  # once is enough
        spec = PathFinder.find_spec(name, path, target)
        if spec is not None and spec.loader is not None:
            spec.loader = _QuietLoader(spec.loader)
        return spec


if _QuietWarpProbe.NAME not in sys.modules:
    sys.meta_path.insert(0, _QuietWarpProbe())

# Ctrl-C honoured from the first instant of `python -m jaxnav.train` (and evaluate, export).
importlib.import_module("jaxnav.cli").early_interrupts()
