"""`avoid`: the paper's task. Drive around a room full of obstacles without touching any.

Observation: the 8 shortest depth-camera distances (m); with `history`, the frames before them
follow, newest first (stacked frames: what moved, e.g. a person walking into the robot's way).
Actions: 0 forward, 1 turn left, 2 turn right, held for one control period; or
(`actions="continuous"`) any command (forward m/s, yaw rad/s) within [0, forward_speed] x
[-turn_rate, turn_rate]. Reward: the paper's Table I (see `AvoidConfig`). A
collision ends the episode with `collision_reward`; so does the time limit, without penalty.
Metric: `collision`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnav.core.checks import require_finite
from jaxnav.core.robot import RobotSpec
from jaxnav.core.types import ActionSpec, EnvState
from jaxnav.tasks.base import (
    ACTIONS,
    Actuator,
    NavTask,
    check_velocity_config,
    stack_frames,
    velocity_actions,
)


@dataclasses.dataclass(frozen=True)
class AvoidConfig:
    """The task: speeds of the three actions, the paper's reward table, episode length, and the
    stacked frames of the observation."""

    actions: str = "discrete"
    """'discrete': the paper's forward / left / right; 'continuous': (forward m/s, yaw rad/s) in
    [0, forward_speed] x [-turn_rate, turn_rate], its reward Table I interpolated by the forward
    share v / forward_speed (1: the forward entries, 0: the turn entries). ('discrete_stop' and
    'discrete_back', the goal task's, are refused: Table I has no entry for standing still or
    backing.)"""
    forward_speed: float = 0.5
    """Commanded speed of the `forward` action, m/s (Kobuki top speed 0.7)."""
    turn_rate: float = 1.5
    """Commanded yaw rate of the `left`/`right` actions (in place), rad/s (Kobuki top ~3.14)."""
    near_threshold: float = 1.0
    """The paper's "near from obstacles": the closest reading is below this, m (not given there)."""
    near_forward: float = 0.4
    """Table I: forward, near obstacles: near_forward - distance_penalty / min(s)."""
    near_turn: float = 0.6
    """Table I: left or right, near obstacles."""
    far_forward: float = 0.6
    """Table I: forward, far from obstacles."""
    far_turn: float = 0.4
    """Table I: left or right, far from obstacles."""
    distance_penalty: float = 0.2
    """Table I: coefficient of 1 / min(s), the closest reading of the observation the action saw."""
    collision_reward: float = -100.0
    """Table I: reward of the step that collides; the episode ends."""
    max_steps: int = 600
    """Time limit in control steps (600 = 60 s at 10 Hz); ends the episode without penalty."""
    history: int = 0
    """Earlier observations appended to the current one, newest first (stacked frames, as the
    goal task's); 0 = the paper's observation. Table I reads the newest frame only."""

    def __post_init__(self):
        require_finite(self)
        for name in ("forward_speed", "turn_rate", "near_threshold"):
            if getattr(self, name) <= 0:
                raise ValueError(f"AvoidConfig.{name}: must be > 0, got {getattr(self, name)}")
        if self.max_steps < 1:
            raise ValueError(f"AvoidConfig.max_steps: must be >= 1, got {self.max_steps}")
        if self.history < 0:
            raise ValueError(f"AvoidConfig.history: must be >= 0, got {self.history}")
        if self.actions not in ACTIONS:
            raise ValueError(
                f"AvoidConfig.actions: must be one of {', '.join(ACTIONS)}, got {self.actions!r}"
            )
        if self.actions in ("discrete_stop", "discrete_back"):
            raise ValueError(
                f"AvoidConfig.actions: {self.actions!r} is for the goal task; Table I has no "
                "reward for standing still or backing (it would pay either as a turn)"
            )

    @property
    def action_spec(self) -> ActionSpec:
        """The paper's three actions (turning in place, as the paper's robot does), or continuous
        commands within the same speeds."""
        return velocity_actions(self.actions, self.forward_speed, self.turn_rate)

    def check_robot(self, robot: RobotSpec) -> None:
        """The commanded speeds are within the robot's limits."""
        check_velocity_config(self, robot)


class AvoidEnv(NavTask):
    """The paper's obstacle avoidance. `reset`/`step` are pure; vmap them for a batch."""

    metric_names = ("collision",)

    def __init__(self, bank, task: AvoidConfig = AvoidConfig(), **specs):
        super().__init__(bank, task, **specs)
        task.check_robot(self.robot)
        self.action_spec = task.action_spec

    def begin(self, key: jax.Array) -> tuple[EnvState, jax.Array]:
        """A new episode (`NavTask.begin`): fresh room, spawn and parameters drawn from the
        randomisation."""
        key, k_scene, k_obs = jax.random.split(key, 3)
        params, data = self.new_episode(k_scene)
        f0, b0 = jnp.float32(0), jnp.bool_(False)
        state = EnvState(
            data=data,
            obs=None,
            reward=f0,
            done=b0,
            truncated=b0,
            metrics={"collision": f0, **self.walker_hit(params, data, b0)},
            info={"params": params, "steps": jnp.int32(0), "key": key, "actuator": Actuator.zero()},
        )
        return state, k_obs

    def first_observation(self, state: EnvState, key: jax.Array) -> EnvState:
        """The first frame, standing in for the earlier ones."""
        frame = self.sense(state.info["params"], state.data, key)
        return state.replace(obs=jnp.tile(frame, 1 + self.task.history))

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Hold `action` for one control period; reward per Table I; end on collision or time."""
        params = self.move(state.info["params"], state.data)
        target = self.command(action)
        command, actuator = self.actuate(params, state.info["actuator"], target)
        data, hit = self.drive(params, state.data, command)
        steps = state.info["steps"] + 1
        truncated = (steps >= self.task.max_steps) & ~hit
        key, k_obs = jax.random.split(state.info["key"])
        frame, sectors = self.sense(params, data, k_obs), self.sensor.num_sectors
        return EnvState(
            data=data,
            obs=stack_frames(frame, state.obs, self.observation_size),
            reward=self._reward(state.obs[:sectors], action, target, hit),
            done=hit | truncated,
            truncated=truncated,
            metrics={"collision": hit.astype(jnp.float32), **self.walker_hit(params, data, hit)},
            info={"params": params, "steps": steps, "key": key, "actuator": actuator},
        )

    def _reward(self, obs, action, target, hit) -> jax.Array:
        """Table I of the paper, from the observation (its newest frame) the action was chosen on;
        continuous commands interpolate between its forward and turn entries by v / forward_speed."""
        t = self.task
        closest = jnp.min(obs)
        near = closest < t.near_threshold
        if t.actions == "continuous":
            share = jnp.clip(target[0] / t.forward_speed, 0.0, 1.0)
            forward_value = jnp.where(near, t.near_forward, t.far_forward)
            turn_value = jnp.where(near, t.near_turn, t.far_turn)
            base = turn_value + share * (forward_value - turn_value)
        else:
            forward = action == 0
            base = jnp.where(
                near,
                jnp.where(forward, t.near_forward, t.near_turn),
                jnp.where(forward, t.far_forward, t.far_turn),
            )
        reward = base - t.distance_penalty / closest
        return jnp.where(hit, t.collision_reward, reward).astype(jnp.float32)
