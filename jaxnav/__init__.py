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

# Public name -> the module that defines it. `train` and `evaluate` are functions of the library
# (`jaxnav.training`, `jaxnav.evaluation`); the modules `jaxnav/train.py` and `jaxnav/evaluate.py`
# only run their command lines (`python -m jaxnav.train`, `jaxnav.cli.train`) and refuse to be
# imported, so `jaxnav.train` is never rebound to a module.
_SOURCES = {
    "LayoutError": "jaxnav.io.layouts",
    "RoomLayout": "jaxnav.io.layouts",
    "load_layout": "jaxnav.io.layouts",
    "load_policy": "jaxnav.runs",
    "make_brax_env": "jaxnav.brax_env",  # imports brax, only when asked for
    "make_env": "jaxnav.tasks.registry",
    "train": "jaxnav.training",
    "evaluate": "jaxnav.evaluation",
}


def __getattr__(name: str):
    if name not in _SOURCES:
        raise AttributeError(f"module 'jaxnav' has no attribute '{name}'")
    return getattr(importlib.import_module(_SOURCES[name]), name)


# Ctrl-C honoured from the first instant of `python -m jaxnav.train` (and evaluate, export).
importlib.import_module("jaxnav.process").early_interrupts()
