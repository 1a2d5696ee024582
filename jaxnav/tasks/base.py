"""What every navigation task shares: a robot in randomised MJX rooms, driven and sensed.

A task subclasses `NavTask` and adds its observation, reward, termination and metrics (see
`jaxnav.tasks.avoid`). `NavTask` owns the scene, the per-episode draw of room, spawn and parameters
(`new_episode`), the differential drive (`drive`), the depth sensor (`sense`) and collision detection
(the analytic signed distance of the bumper sphere, `jaxnav.core.geometry`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco import mjx

from jaxnav.core.geometry import signed_distance
from jaxnav.core.randomize import LayoutBank, RandomizeConfig, SceneParams, sample
from jaxnav.core.robot import TURTLEBOT2I, RobotSpec
from jaxnav.core.scene import Scene, SceneConfig
from jaxnav.core.sensors import SensorConfig, observe

GRAVITY = 9.81  # m/s^2, for the wheels' traction limit


class NavTask:
    """Batched-MJX robot in randomised rooms. Subclasses define `reset`, `step`, `action_spec`,
    `metric_names` and `observation_size` (the env contract, `jaxnav.core.types`)."""

    def __init__(
        self,
        bank: LayoutBank,
        task,
        randomize: RandomizeConfig = RandomizeConfig(),
        sensor: SensorConfig = SensorConfig(),
        scene: SceneConfig = SceneConfig(),
        robot: RobotSpec = TURTLEBOT2I,
    ):
        randomize.check_robot(robot.radius)
        self.task, self.randomize, self.sensor, self.robot = task, randomize, sensor, robot
        self.bank = bank
        self.scene = Scene(scene, robot)
        self._data0 = mjx.make_data(self.scene.model)

    @property
    def control_period(self) -> float:
        """Seconds per control step."""
        return self.scene.cfg.control_period

    def new_episode(self, key: jax.Array) -> tuple[SceneParams, mjx.Data]:
        """A fresh room, spawn and parameters, and the physics state at the spawn."""
        params = sample(key, self.randomize, self.bank, self.robot.radius)
        data = self._data0.replace(qpos=params.spawn)
        # Kinematics places the new room's geoms for the rays; contacts come with the first step.
        return params, mjx.kinematics(self.scene.model_for(params), data)

    def sense(self, params: SceneParams, data: mjx.Data, key: jax.Array) -> jax.Array:
        """[num_sectors] float32 sector minima of the depth sensor, with the episode's noise."""
        m = self.scene.model_for(params)
        return observe(m, data, params, key, self.sensor, self.robot, self.scene.robot_body)

    def touching(self, params: SceneParams, data: mjx.Data) -> jax.Array:
        """[] bool: the bumper sphere touches a wall or an obstacle."""
        z = jnp.float32(self.scene.bumper_z)
        return signed_distance(params, data.qpos[:2], z) < self.scene.bumper_radius

    def drive(self, params: SceneParams, data: mjx.Data, command: jax.Array):
        """Holds `command` [2] (forward m/s, yaw rad/s) for one control period.

        Each physics step, the motors push the base towards the commanded forward speed along its
        heading (zero sideways) and the commanded yaw rate, with forces bounded by the floor's
        traction. Returns the new data and whether the bumper touched anything on the way.
        """
        m = self.scene.model_for(params)
        dt = self.scene.cfg.timestep
        mass, inertia = self.scene.mass, self.scene.yaw_inertia
        force_max = params.friction * mass * GRAVITY
        torque_max = force_max * 0.5 * self.robot.wheelbase
        command = command * params.speed_gain

        def substep(carry, _):
            d, hit = carry
            heading = jnp.stack([jnp.cos(d.qpos[2]), jnp.sin(d.qpos[2])])
            force = mass * (command[0] * heading - d.qvel[:2]) / dt
            force = force * jnp.minimum(1.0, force_max / (jnp.linalg.norm(force) + 1e-9))
            torque = jnp.clip(inertia * (command[1] - d.qvel[2]) / dt, -torque_max, torque_max)
            d = mjx.step(m, d.replace(ctrl=jnp.append(force, torque)))
            return (d, hit | self.touching(params, d)), None

        init = (data, jnp.bool_(False))
        (data, hit), _ = jax.lax.scan(substep, init, None, self.scene.cfg.substeps)
        return data, hit
