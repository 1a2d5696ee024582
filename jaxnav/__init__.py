"""jaxnav: massively parallel PPO for TurtleBot 2i obstacle avoidance on MuJoCo MJX."""

import contextlib
import io

# mujoco.mjx prints a line on import when its optional Warp backend is absent; jaxnav uses JAX only.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx  # noqa: F401

from jaxnav.envs import make_env  # noqa: E402
from jaxnav.layouts import LayoutError, RoomLayout, load_layout  # noqa: E402

__all__ = ["LayoutError", "RoomLayout", "load_layout", "make_env"]
__version__ = "0.1.0"
