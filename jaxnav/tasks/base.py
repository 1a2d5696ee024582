"""What every navigation task shares: a robot in randomised MJX rooms, driven and sensed.

A task subclasses `NavTask` and adds its observation, reward, termination and metrics (see
`jaxnav.tasks.avoid`). `NavTask` owns the scene, the per-episode draw of room, spawn and parameters
(`new_episode`), the differential drive (`actuate`, `drive`), the depth sensor (`sense`) and collision
detection (the analytic signed distance of the bumper at the base's x/y, `jaxnav.core.geometry`)
and the moving obstacles (`with_movers` at the reset, `move` once per control step before the
physics, `jaxnav.core.motion`; both do nothing in an env where nothing can move).

The drive has two physics (`SceneConfig.physics`) behind one command pipeline: "fast" pushes the
base with forces that track the command; "wheeled" sets the two wheels' speed loops to it and lets
MuJoCo roll the robot on the floor. Collision detection is the same analytic test in both, at the
pose qpos[:3]: the wheeled base's small pitch, roll and bounce (about 2 degrees and 1.3 mm at most,
benchmarks/wheeled_model.py) are not seen by it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxnav.core import crowd, mjx, motion
from jaxnav.core.episode import sample, walker_config
from jaxnav.core.geometry import signed_distance
from jaxnav.core.randomize import LayoutBank, RandomizeConfig, SceneParams
from jaxnav.core.robot import TURTLEBOT2I, RobotSpec
from jaxnav.core.scene import Scene, SceneConfig
from jaxnav.core.sensors import SensorConfig, observe
from jaxnav.core.types import ActionSpec, Body, ContinuousActions, DiscreteActions, EnvState

GRAVITY = 9.81  # m/s^2, for the wheels' traction limit
MAX_LATENCY = 4  # control steps of command history kept for the episode's latency
ACTIONS = ("discrete", "discrete_stop", "discrete_back", "continuous")  # `velocity_actions`
BACK_SHARE = 0.5  # the `back` action's speed, as a share of forward_speed


def velocity_actions(actions: str, forward_speed: float, turn_rate: float) -> ActionSpec:
    """The paper's three commands (forward, turn left or right in place); with `actions` =
    "discrete_stop" a fourth, stop (0, 0), to wait with the view kept where it looks; with
    "discrete_back" a fourth, back (-BACK_SHARE x forward_speed, 0), to back away from what
    comes, slower than forward as the camera does not see behind; with "continuous", any
    (forward m/s, yaw rad/s) in [0, forward_speed] x [-turn_rate, turn_rate] (no reversing)."""
    if actions == "continuous":
        return ContinuousActions(low=(0.0, -turn_rate), high=(forward_speed, turn_rate))
    names = ("forward", "left", "right")
    commands = ((forward_speed, 0.0), (0.0, turn_rate), (0.0, -turn_rate))
    if actions == "discrete_stop":
        names, commands = names + ("stop",), commands + ((0.0, 0.0),)
    elif actions == "discrete_back":
        names, commands = names + ("back",), commands + ((-BACK_SHARE * forward_speed, 0.0),)
    return DiscreteActions(names=names, commands=commands)


def stack_frames(frame: jax.Array, obs: jax.Array, size: int) -> jax.Array:
    """[size] stacked frames: `frame` [F], then the newest size - F entries of the stacked `obs`
    (newest first), as the robot side's `FrameStack` stacks them."""
    return jnp.concatenate([frame, obs[: size - frame.shape[0]]])


def observation_size(task, sensor: SensorConfig) -> int:
    """The observation length of a task config with `sensor`: the depth sectors, then the task's
    `extra_observations` (the goal task's goal and last command), times the frames a task stacks
    (`history`: either task's earlier observations), then the memory's bins (`memory_bins`)."""
    frame = sensor.num_sectors + getattr(task, "extra_observations", 0)
    return frame * (1 + getattr(task, "history", 0)) + getattr(task, "memory_bins", 0)


def check_velocity_config(cfg, robot: RobotSpec) -> None:
    """`cfg.actions` is known and its forward_speed / turn_rate are within the robot's limits."""
    name = type(cfg).__name__
    if cfg.actions not in ACTIONS:
        raise ValueError(
            f"{name}.actions: must be one of {', '.join(ACTIONS)}, got {cfg.actions!r}"
        )
    for field, top in (
        ("forward_speed", robot.max_linear_speed),
        ("turn_rate", robot.max_angular_speed),
    ):
        if not 0 < getattr(cfg, field) <= top:
            raise ValueError(
                f"{name}.{field}: must be in (0, {top:.3f}] for {robot.name}, "
                f"got {getattr(cfg, field)}"
            )


@dataclasses.dataclass(frozen=True)
class EvalMetric:
    """A number evaluation (`jaxnav.evaluation`) reports for a task that declares it
    (`NavTask.eval_metrics`): per room, per family of a suite and overall, in the results, their
    JSON and, with a `column`, the table.

    It is computed from a room's episode record (`jaxnav.evaluation.evaluate_rooms`: numpy arrays
    over the room's N episodes, "collided", "steps", "control_period", "distance", "start", "goal",
    "metrics" (the task's metrics summed per episode), and "layout", "robot_radius", "task" (the
    task's config)), then pooled over the episodes of the rooms reported together.
    """

    name: str
    """Its key in the results and in their JSON."""
    value: Callable[[dict], np.ndarray]
    """[N] float: its value in each episode of a room record."""
    over: Callable[[dict], np.ndarray] | None = None
    """[N] bool: the episodes whose values are averaged (where there are none, the largest value
    of all is reported); None: every episode."""
    column: str = ""
    """Its column head in the table; "" keeps it out of the table."""
    width: int = 5
    """Characters of its column."""
    scale: float = 1.0
    """The table shows the value times this (100: a rate as a percentage)."""
    digits: int = 2
    """Decimals of its value in the table."""
    title: str = ""
    """How a room's picture's title shows the value, a format string ("SPL {:.2f}"); a task
    whose metrics have none is titled with its collision-free rate and coverage."""


def _run_into(room: dict) -> np.ndarray:
    """[N] bool: a non-reactive walker ran into the robot while it stood (the task metric
    `walker_hit`, `crowd.hit_by_walker`), which ended the episode."""
    return np.asarray(room["metrics"]["walker_hit"]) > 0


def _caused(room: dict) -> np.ndarray:
    """[N] 1.0 where the episode collided and not by a walker running into the standing robot."""
    return (np.asarray(room["collided"], bool) & ~_run_into(room)).astype(np.float64)


WALKER_EVAL_METRICS = (
    EvalMetric(
        "robot_collision_rate", value=_caused, column="caused %", width=8, scale=100.0, digits=1
    ),
    EvalMetric(
        "collision_free_unhit_rate",
        value=lambda room: 1.0 - np.asarray(room["collided"], np.float64),
        over=lambda room: ~_run_into(room),
    ),
)
"""Evaluation's metrics where people walk: the share of episodes that ended in a collision the
robot caused (`collision_free_rate` counts every collision; the task metric `walker_hit` the
episodes in which a non-reactive walker ran into the robot while it stood, `crowd.hit_by_walker`),
and the collision-free share of the episodes no walker ran into the robot in (where there are
none, the largest value: 0, every one of them having collided)."""


def success_unhit(success_metric: str) -> EvalMetric:
    """Where people walk and episodes have goals: the share of the episodes no walker ran into
    the robot in that reached the goal (task metric `success_metric` > 0)."""
    return EvalMetric(
        "success_unhit_rate",
        value=lambda room: (np.asarray(room["metrics"][success_metric]) > 0).astype(np.float64),
        over=lambda room: ~_run_into(room),
    )


@struct.dataclass
class Actuator:
    """The drive's command pipeline between the policy and the motors."""

    queue: jax.Array  # [MAX_LATENCY + 1, 2] the newest commands (m/s, rad/s), newest first
    velocity: jax.Array  # [2] the command the velocity smoother passed last (m/s, rad/s)

    @classmethod
    def zero(cls) -> Actuator:
        return cls(jnp.zeros((MAX_LATENCY + 1, 2)), jnp.zeros(2))


class NavTask:
    """Batched-MJX robot in randomised rooms. Subclasses define `step`, `action_spec` and
    `metric_names` (with `reset`, the env contract, `jaxnav.core.types`; `observation_size` is set
    here from the task config, by `observation_size`), the reset in two parts (`begin` and
    `first_observation`, see `reset`) or `reset` itself, and may declare what evaluation reports
    besides its own metrics (`eval_metrics`)."""

    eval_metrics: tuple[EvalMetric, ...] = ()
    """What evaluation reports for this task besides the metrics every task gets."""
    success_metric: str | None = None
    """The metric (of `metric_names`) whose episode sum > 0 says an episode reached its goal, for
    scores that need it (BARN's); None: the task has no goals."""
    uses_goals = False
    """Episodes have goals (`state.info["goal"]`): `make_env` adds goal data to the bank."""

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
        self.observation_size = observation_size(task, sensor)
        self.bank = bank
        self.scene = Scene(scene, robot)
        self._data0 = mjx.make_data(self.scene.data_model, device=jax.local_devices()[0])
        # Static: obstacles move in this env (added movers, or a layout's motions).
        self.moving = randomize.moving_count[1] > 0 or bank.rooms.motion is not None
        self.walkers = walker_config(randomize)  # the people the randomisation adds
        layout_walkers = bank.rooms.motion is not None and bank.rooms.motion.walkers is not None
        self.walking = self.walkers.slots > 0 or layout_walkers  # static: people walk here
        self.moving |= self.walking
        if self.walking:
            self.metric_names = (*self.metric_names, "walker_hit")
            self.eval_metrics = (*self.eval_metrics, *WALKER_EVAL_METRICS)
            if self.success_metric is not None:
                self.eval_metrics = (*self.eval_metrics, success_unhit(self.success_metric))

    @property
    def control_period(self) -> float:
        """Seconds per control step."""
        return self.scene.cfg.control_period

    @property
    def critic_size(self) -> int:
        """C, the task's inputs for a privileged critic in `state.info["critic"]` (0: none)."""
        return getattr(self.task, "critic_observations", 0)

    def reset(self, key: jax.Array) -> EnvState:
        """A new episode: `begin`'s, with its first observation (`first_observation`). A task
        defines the two: `begin(key)` -> (the episode's state, its obs None; the key of its first
        observation), and `first_observation(state, key)` -> the state with its obs (and what
        makes it, such as the goal task's memory). Training's draws
        (`jaxnav.wrappers.AutoReset`) then make a batch's observations apart from its rooms,
        which costs the CPU less. A task may define `reset` itself instead."""
        return self.first_observation(*self.begin(key))

    def new_episode(self, key: jax.Array) -> tuple[SceneParams, Body]:
        """A fresh room, spawn, moving obstacles and parameters, and the physics state at the
        spawn."""
        params = sample(key, self.randomize, self.bank, self.robot.radius)
        params = self.with_movers(key, params)
        return params, self.place(params)

    def with_movers(self, key: jax.Array, params: SceneParams, goal=None) -> SceneParams:
        """`params` with the randomisation's moving obstacles added (`motion.add_movers`), clear
        of the spawn and of the robot's disc at `goal` [2] if given; `key` is the one `sample`
        drew `params` with (a key of its own is folded from it, so that an env without movers
        draws exactly what it drew before they existed). The walkers (`crowd.add_walkers`) come
        first, in the slots before the movers'."""
        if self.walkers.slots:
            first = params.cyl_pos.shape[0] - self.randomize.moving_count[1] - self.walkers.slots
            k_walk = jax.random.fold_in(key, 2)
            params = crowd.add_walkers(k_walk, params, self.walkers, first, self.robot.radius, goal)
        if not self.randomize.moving_count[1]:
            return params
        k_move = jax.random.fold_in(key, 1)
        return motion.add_movers(k_move, params, self.randomize, self.robot.radius, goal)

    def move(self, params: SceneParams, data: Body | mjx.Data) -> SceneParams:
        """`params` after the obstacles' motion over one control period (`motion.advance`; the
        reactive walkers give way to the robot as `data` has it); unchanged in an env where
        nothing moves."""
        if not self.moving:
            return params
        robot = (data.qpos[:2], data.qvel[:2], self.robot.radius)
        return motion.advance(params, self.control_period, robot)

    def walker_hit(self, params: SceneParams, data: Body | mjx.Data, hit) -> dict:
        """{"walker_hit": [] float32, 1 where this step's collision `hit` is a non-reactive walker
        running into the robot while it stood (`crowd.hit_by_walker`)}; {} where nobody walks."""
        if not self.walking:
            return {}
        z = tuple(jnp.float32(v) for v in self.scene.bumper_z)
        by = crowd.hit_by_walker(params, data.qpos[:2], data.qvel[:2], self.scene.bumper_radius, z)
        return {"walker_hit": (by & hit).astype(jnp.float32)}

    def place(self, params: SceneParams) -> Body:
        """The physics state of the robot at rest at `params.spawn`: its position alone. The
        quantities MuJoCo derives from it (body and geom poses, contacts) come with each step,
        which computes them from the carried `Body` before anything reads them, so a reset
        computes none (MJX's kinematics cost the reset's compile 1 s of 5.6 s for avoid on 2
        CPU cores, docs/results.md "Start-up"; `tests/test_speed.py` checks that the steps are
        the same either way)."""
        return Body.of(self._data0.replace(qpos=self._data0.qpos.at[:3].set(params.spawn)))

    def command(self, action: jax.Array) -> jax.Array:
        """[2] the (forward m/s, yaw rad/s) the policy's `action` asks for: a row of the command
        table (`DiscreteActions`), or the command itself clipped to the bounds (`ContinuousActions`;
        a non-finite component reads 0, so a broken policy cannot break the physics)."""
        spec = self.action_spec
        if isinstance(spec, ContinuousActions):
            action = jnp.asarray(action, jnp.float32)
            action = jnp.where(jnp.isfinite(action), action, 0.0)
            return jnp.clip(action, jnp.asarray(spec.low), jnp.asarray(spec.high))
        return jnp.asarray(spec.table())[action]

    def sense(self, params: SceneParams, data: Body | mjx.Data, key: jax.Array) -> jax.Array:
        """[num_sectors] float32 sector minima of the depth sensor, with the episode's noise."""
        return observe(params, data.qpos, key, self.sensor, self.robot)

    def gap(self, params: SceneParams, data: Body | mjx.Data) -> jax.Array:
        """[] m between the robot's collision volume and the nearest wall or obstacle (moving
        ones included); < 0 where they overlap."""
        z = tuple(jnp.float32(v) for v in self.scene.bumper_z)
        return signed_distance(params, data.qpos[:2], z) - self.scene.bumper_radius

    def touching(self, params: SceneParams, data: Body | mjx.Data) -> jax.Array:
        """[] bool: the robot's collision volume, grown by the episode's margin (training's
        `RandomizeConfig.collision_margin`, else 0), touches a wall or an obstacle."""
        return self.gap(params, data) < params.margin

    def actuate(self, params: SceneParams, act: Actuator, target: jax.Array):
        """What reaches the motors this step for the policy's command `target` [2] (m/s, rad/s):
        delayed by the episode's latency, rate-limited by its acceleration limits (the Kobuki's
        velocity smoother, `_smoothed`; a limit <= 0 is none), split over the wheels with their gains and scaled
        by the speed gain. Returns ([2] command, the new Actuator)."""
        queue = jnp.concatenate([target[None], act.queue[:-1]])
        delayed = queue[jnp.clip(params.latency, 0, MAX_LATENCY)]
        velocity = act.velocity + self._smoothed(delayed - act.velocity, params.accel)
        half_track = 0.5 * self.robot.wheelbase
        left, right = params.wheel_gain * (
            velocity[0] + jnp.array([-1.0, 1.0]) * velocity[1] * half_track
        )
        command = jnp.stack([0.5 * (left + right), (right - left) / (2 * half_track)])
        return command * params.speed_gain, Actuator(queue, velocity)

    def _smoothed(self, change: jax.Array, accel: jax.Array) -> jax.Array:
        """[2] the velocity smoother's part of the wanted `change` [2] (m/s, rad/s) in one control
        period, at acceleration limits `accel` [2] (<= 0: none), by its rule
        (`RandomizeConfig.coupled_smoother`)."""
        bound = accel * self.control_period  # [2]
        if not self.randomize.coupled_smoother:
            return jnp.where(bound > 0, jnp.clip(change, -bound, bound), change)
        limited = (bound > 0) & (change != 0)
        ratio = jnp.where(limited, bound / jnp.where(limited, jnp.abs(change), 1.0), jnp.inf)
        return change * jnp.minimum(1.0, ratio.min())

    def drive(self, params: SceneParams, body: Body, command: jax.Array):
        """Holds `command` [2] (forward m/s, yaw rad/s, as `actuate` passes it) for one period of
        the scene's physics steps from `body`. Returns the new Body and whether the bumper touched
        anything after any of them. MuJoCo's matrix products run in float32 on every platform (on
        a GPU JAX's default rounds their inputs to TF32, and the step costs the same either way)."""
        m = self.scene.physics_model(params)
        control = self._wheel_speeds if self.scene.wheeled else self._base_forces

        def substep(body, _):
            d = body.into(self._data0)
            d = mjx.step(m, d.replace(ctrl=control(params, d, command)))
            return Body.of(d), self.touching(params, d)

        # The scan carries Body alone, every leaf batched from the start, and the touches are its
        # outputs: under vmap a carry that starts unbatched (mjx.Data's other fields, from
        # `_data0`) and ends batched makes the scan batch its body twice.
        with jax.default_matmul_precision("highest"):
            body, touched = jax.lax.scan(substep, body, None, self.scene.substeps)
        return body, touched.any()

    def _base_forces(self, params: SceneParams, d: mjx.Data, command: jax.Array) -> jax.Array:
        """Fast physics: [3] forces (x, y) and yaw torque that push the base towards the commanded
        forward speed along its heading (zero sideways) and yaw rate within one step, bounded by
        the floor's traction."""
        dt, mass, inertia = self.scene.timestep, self.scene.mass, self.scene.yaw_inertia
        force_max = params.friction * mass * GRAVITY
        torque_max = force_max * 0.5 * self.robot.wheelbase
        heading = jnp.stack([jnp.cos(d.qpos[2]), jnp.sin(d.qpos[2])])
        force = mass * (command[0] * heading - d.qvel[:2]) / dt
        force = force * jnp.minimum(1.0, force_max / (jnp.linalg.norm(force) + 1e-9))
        torque = jnp.clip(inertia * (command[1] - d.qvel[2]) / dt, -torque_max, torque_max)
        return jnp.append(force, torque)

    def _wheel_speeds(self, params: SceneParams, d: mjx.Data, command: jax.Array) -> jax.Array:
        """Wheeled physics: [nu] the left and right wheel speed targets (rad/s) of a differential
        drive, for the wheels' velocity loops; the floor's friction does the rest."""
        half_track = 0.5 * self.robot.wheelbase
        rim = command[0] + jnp.array([-1.0, 1.0]) * command[1] * half_track  # [2] m/s
        ctrl = jnp.zeros(self.scene.model.nu)
        return ctrl.at[self.scene.wheel_actuators].set(rim / self.scene.wheel_radius)
