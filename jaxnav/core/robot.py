"""Robot specs: the MJCF, footprint, speed limits and camera mount of a robot, as data.

A robot is a frozen `RobotSpec` passed to `make_env`; `ROBOTS` names the ones that ship. The
TurtleBot 2i (Kobuki base, Orbbec Astra) is the default. Figures are the manufacturers' public ones
(Kobuki user guide, Astra datasheet).
"""

from __future__ import annotations

import dataclasses
import math

from jaxnav.core.checks import require_finite


@dataclasses.dataclass(frozen=True)
class RobotSpec:
    """A differential-drive robot with one forward-looking range sensor."""

    name: str = "turtlebot2i"
    """Shown in logs and stored in the run config."""
    mjcf: str = "turtlebot2i.xml"
    """MJCF file of the robot, a file name in jaxnav's scenes or a path. It must define body
    `base` on slide joints x, y and hinge yaw, motors on them, and the collision geom `bumper`."""
    wheeled_mjcf: str = "turtlebot2i_wheeled.xml"
    """MJCF of the wheeled validation model (`SceneConfig.physics="wheeled"`): body `base` whose
    first joints are the same x, y and yaw (more may follow), the same `bumper`, wheel geoms and
    velocity actuators `wheel_left`/`wheel_right` `wheelbase` apart, and contype-2 geoms (wheels,
    castors) that touch the floor."""
    radius: float = 0.177
    """Footprint radius, m (Kobuki diameter 0.354 m): spawns keep it clear of obstacles."""
    wheelbase: float = 0.230
    """Distance between the drive wheels, m: bounds the yaw torque the wheels can apply, and the
    wheeled model's wheels must be this far apart."""
    max_linear_speed: float = 0.7
    """Top forward speed, m/s (Kobuki)."""
    max_angular_speed: float = math.pi
    """Top yaw rate, rad/s (Kobuki, 180 deg/s)."""
    camera_forward: float = -0.05
    """Sensor origin ahead of the base centre, m (turtlebot2i_description: the Astra at -0.05)."""
    camera_height: float = 0.295
    """Sensor origin above the floor, m (0.285 above base_link, itself 0.0102 up)."""
    camera_pitch: float = 0.0
    """Downward tilt of the optical axis, rad."""

    def __post_init__(self):
        require_finite(self, lambda name: f"RobotSpec.{name}")
        for name in ("radius", "wheelbase", "max_linear_speed", "max_angular_speed"):
            if getattr(self, name) <= 0:
                raise ValueError(f"RobotSpec.{name}: must be > 0, got {getattr(self, name)}")
        if self.camera_height <= 0:
            raise ValueError(f"RobotSpec.camera_height: must be > 0 m, got {self.camera_height}")


TURTLEBOT2I = RobotSpec()
ROBOTS: dict[str, RobotSpec] = {"turtlebot2i": TURTLEBOT2I}
