"""The simulation core: the env contract, the robot, the batched MJX scene, the depth sensor, the
signed distance, the layout model, domain randomisation, room families and goals.

MuJoCo MJX is imported here once (`jaxnav.core.mjx`), with the two lines its optional Warp backend prints on stdout
when absent kept off it (jaxnav uses MJX's JAX implementation): scoped to that import, so nothing
else's output is touched.
"""

import contextlib as _contextlib
import io as _io

with _contextlib.redirect_stdout(_io.StringIO()):
    from mujoco import mjx  # jaxnav's modules outside core take it from here

__all__ = ["mjx"]
