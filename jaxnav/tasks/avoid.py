"""`avoid`: the paper's task. Drive around a room full of static obstacles without touching any.

Observation: the 8 shortest depth-camera distances (m). Actions: 0 forward, 1 turn left, 2 turn right,
held for one control period. Reward: the paper's Table I (see `AvoidConfig`). A collision ends the
episode with `collision_reward`; so does the time limit, without penalty.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from mujoco import mjx

from jaxnav.core import robot
from jaxnav.core.checks import require_finite
from jaxnav.core.randomize import LayoutBank, RandomizeConfig, SceneParams, sample
from jaxnav.core.scene import Scene, SceneConfig
from jaxnav.core.sensors import SensorConfig, observe

GRAVITY = 9.81  # m/s^2, for the wheels' traction limit


@dataclasses.dataclass(frozen=True)
class AvoidConfig:
    """The task: speeds of the three actions, the paper's reward table, episode length."""

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
    auto_reset: bool = True
    """Start a new episode (new room, new spawn) inside `step` when one ends, as training needs."""

    def __post_init__(self):
        require_finite(self)
        if not 0 < self.forward_speed <= robot.MAX_LINEAR_SPEED:
            raise ValueError(
                f"AvoidConfig.forward_speed: must be in (0, {robot.MAX_LINEAR_SPEED}] m/s, "
                f"got {self.forward_speed}"
            )
        if not 0 < self.turn_rate <= robot.MAX_ANGULAR_SPEED:
            raise ValueError(
                f"AvoidConfig.turn_rate: must be in (0, {robot.MAX_ANGULAR_SPEED:.3f}] "
                f"rad/s, got {self.turn_rate}"
            )
        if self.near_threshold <= 0:
            raise ValueError(f"AvoidConfig.near_threshold: must be > 0, got {self.near_threshold}")
        if self.max_steps < 1:
            raise ValueError(f"AvoidConfig.max_steps: must be >= 1, got {self.max_steps}")


@struct.dataclass
class EnvState:
    """One robot's state (a batch adds a leading axis to every field)."""

    data: mjx.Data  # physics state
    params: SceneParams  # this episode's room, spawn, physics and sensor parameters
    obs: jax.Array  # [8] float32, m
    reward: jax.Array  # [] float32, of the last step
    done: jax.Array  # [] bool: the last step ended an episode (obs is then the next episode's)
    collision: jax.Array  # [] bool: the last step collided
    truncated: jax.Array  # [] bool: the last step hit the time limit
    steps: jax.Array  # [] int32, control steps into the current episode
    episode_return: jax.Array  # [] float32, return of the current episode so far
    last_return: jax.Array  # [] float32, return of the episode that ended last
    last_length: jax.Array  # [] int32, length of the episode that ended last
    key: jax.Array  # PRNG key for resets and sensor noise


class AvoidEnv:
    """Batched-MJX TurtleBot in randomised rooms. `reset`/`step` are pure; vmap them for a batch."""

    observation_size = robot.NUM_SECTORS
    action_size = len(robot.ACTION_NAMES)

    def __init__(
        self,
        bank: LayoutBank,
        task: AvoidConfig = AvoidConfig(),
        randomize: RandomizeConfig = RandomizeConfig(),
        sensor: SensorConfig = SensorConfig(),
        scene: SceneConfig = SceneConfig(),
    ):
        self.task, self.randomize, self.sensor = task, randomize, sensor
        self.bank = bank
        self.scene = Scene(scene)
        self._data0 = mjx.make_data(self.scene.model)
        # [3, 2] commanded (forward speed, yaw rate) per action.
        self._commands = jnp.asarray(robot.ACTIONS * np.array([task.forward_speed, task.turn_rate]))
        self.observation_size = sensor.num_sectors

    def reset(self, key: jax.Array) -> EnvState:
        """A new episode: fresh room, spawn and parameters drawn from the randomisation."""
        key, k_scene, k_obs = jax.random.split(key, 3)
        params, data = self._new_episode(k_scene)
        obs = observe(
            self.scene.model_for(params), data, params, k_obs, self.sensor, self.scene.robot_body
        )
        f0, i0, b0 = jnp.float32(0), jnp.int32(0), jnp.bool_(False)
        return EnvState(
            data=data,
            params=params,
            obs=obs,
            reward=f0,
            done=b0,
            collision=b0,
            truncated=b0,
            steps=i0,
            episode_return=f0,
            last_return=f0,
            last_length=i0,
            key=key,
        )

    def _new_episode(self, key: jax.Array) -> tuple[SceneParams, mjx.Data]:
        params = sample(key, self.randomize, self.bank)
        data = self._data0.replace(qpos=params.spawn)
        # Kinematics places the new room's geoms for the rays; the first physics step of the
        # episode computes its contacts, so no collision pass is needed here.
        return params, mjx.kinematics(self.scene.model_for(params), data)

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """Hold `action` for one control period; reward per Table I; end on collision or time."""
        params = state.params
        m = self.scene.model_for(params)
        command = self._commands[action] * params.speed_gain  # [2] forward m/s, yaw rad/s
        data, hit = self._drive(m, state.data, command, params.friction)
        reward = self._reward(state.obs, action, hit)
        steps = state.steps + 1
        truncated = (steps >= self.task.max_steps) & ~hit
        done = hit | truncated
        episode_return = state.episode_return + reward
        key, k_reset, k_obs = jax.random.split(state.key, 3)
        if self.task.auto_reset:
            new_params, new_data = self._new_episode(k_reset)
            pick = lambda new, old: jax.tree_util.tree_map(  # noqa: E731
                lambda a, b: jnp.where(done, a, b), new, old
            )
            params, data = pick(new_params, params), pick(new_data, data)
            m = self.scene.model_for(params)
        obs = observe(m, data, params, k_obs, self.sensor, self.scene.robot_body)
        return EnvState(
            data=data,
            params=params,
            obs=obs,
            reward=reward,
            done=done,
            collision=hit,
            truncated=truncated,
            steps=jnp.where(done, 0, steps),
            episode_return=jnp.where(done, 0.0, episode_return),
            last_return=jnp.where(done, episode_return, state.last_return),
            last_length=jnp.where(done, steps, state.last_length),
            key=key,
        )

    def _drive(self, m, d, command, friction):
        """Differential drive for one control period; returns the new data and whether it collided.

        Each physics step, the motors push the base towards the commanded forward speed along its
        heading (zero sideways) and the commanded yaw rate, with forces bounded by the floor's traction.
        """
        dt = self.scene.cfg.timestep
        mass, inertia = self.scene.mass, self.scene.yaw_inertia
        force_max = friction * mass * GRAVITY
        torque_max = force_max * 0.5 * robot.WHEELBASE

        def substep(carry, _):
            d, hit = carry
            heading = jnp.stack([jnp.cos(d.qpos[2]), jnp.sin(d.qpos[2])])
            force = mass * (command[0] * heading - d.qvel[:2]) / dt
            force = force * jnp.minimum(1.0, force_max / (jnp.linalg.norm(force) + 1e-9))
            torque = jnp.clip(inertia * (command[1] - d.qvel[2]) / dt, -torque_max, torque_max)
            d = mjx.step(m, d.replace(ctrl=jnp.append(force, torque)))
            return (d, hit | _touching(d)), None

        (d, hit), _ = jax.lax.scan(substep, (d, jnp.bool_(False)), None, self.scene.cfg.substeps)
        d = mjx.collision(m, mjx.kinematics(m, d))  # contacts of the final pose
        return d, hit | _touching(d)

    def _reward(self, obs: jax.Array, action: jax.Array, hit: jax.Array) -> jax.Array:
        """Table I of the paper, from the observation the action was chosen on."""
        t = self.task
        closest = jnp.min(obs)
        near = closest < t.near_threshold
        forward = action == 0
        base = jnp.where(
            near,
            jnp.where(forward, t.near_forward, t.near_turn),
            jnp.where(forward, t.far_forward, t.far_turn),
        )
        reward = base - t.distance_penalty / closest
        return jnp.where(hit, t.collision_reward, reward).astype(jnp.float32)


def _touching(d: mjx.Data) -> jax.Array:
    """Whether any contact (all of them are robot-obstacle or robot-wall) is touching."""
    return jnp.any(d._impl.contact.dist < 0)  # MJX keeps contacts in its JAX implementation data
