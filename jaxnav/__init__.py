"""jaxnav: massively parallel PPO for TurtleBot 2i obstacle avoidance on MuJoCo MJX."""

__version__ = "0.1.0"

import contextlib
import io

# mujoco.mjx prints a line on import when its optional Warp backend is absent; jaxnav uses JAX only.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx  # noqa: F401

from jaxnav.io.checkpoint import load_policy  # noqa: E402
from jaxnav.io.layouts import LayoutError, RoomLayout, load_layout  # noqa: E402
from jaxnav.tasks.registry import make_env  # noqa: E402

__all__ = [
    "LayoutError",
    "RoomLayout",
    "evaluate",
    "load_layout",
    "load_policy",
    "make_env",
    "train",
]


def __getattr__(name: str):
    # `train` and `evaluate` are also the `python -m` entry points; importing them lazily keeps
    # `python -m jaxnav.train` from finding its own module half-imported. Both modules are callable.
    if name in ("train", "evaluate"):
        import importlib

        return importlib.import_module(f"jaxnav.{name}")
    raise AttributeError(f"module 'jaxnav' has no attribute '{name}'")
