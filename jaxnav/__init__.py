"""jaxnav: massively parallel PPO for TurtleBot 2i obstacle avoidance on MuJoCo MJX.

The public names are imported on first use, so `jaxnav.robot_side` (numpy only) imports without jax.
"""

__version__ = "0.1.0"

import importlib

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


# Ctrl-C honoured from the first instant of `python -m jaxnav.train` (and evaluate, export).
importlib.import_module("jaxnav.cli").early_interrupts()
