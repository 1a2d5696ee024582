"""A toy second task for the env-contract tests: stand still, wherever you are put.

It is a new file plus one `register` line: nothing in ppo/, train, evaluate or export knows it.
Reward: minus the distance moved in the step (m). Metric `drift`: the distance moved, summed over
the episode. Actions: stay, creep forward, turn.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxnav.core.types import DiscreteActions, EnvState
from jaxnav.tasks.base import NavTask


@dataclasses.dataclass(frozen=True)
class StandStillConfig:
    """The toy task's settings."""

    creep_speed: float = 0.3
    """Forward speed of the `creep` action, m/s."""
    max_steps: int = 50
    """Time limit in control steps."""

    @property
    def action_spec(self) -> DiscreteActions:
        """Stay, creep forward, turn left."""
        return DiscreteActions(
            names=("stay", "creep", "turn"),
            commands=((0.0, 0.0), (self.creep_speed, 0.0), (0.0, 1.0)),
        )

    def check_robot(self, robot) -> None:
        """Nothing to check: every command is within the TurtleBot's limits."""


class StandStillEnv(NavTask):
    """Stay put; moving costs its distance."""

    metric_names = ("collision", "drift")

    def __init__(self, bank, task: StandStillConfig = StandStillConfig(), **specs):
        super().__init__(bank, task, **specs)
        self.action_spec = task.action_spec
        self.observation_size = self.sensor.num_sectors
        self._commands = jnp.asarray(self.action_spec.table())

    def reset(self, key: jax.Array) -> EnvState:
        key, k_scene, k_obs = jax.random.split(key, 3)
        params, data = self.new_episode(k_scene)
        zero, false = jnp.float32(0), jnp.bool_(False)
        return EnvState(
            data=data,
            obs=self.sense(params, data, k_obs),
            reward=zero,
            done=false,
            truncated=false,
            metrics={"collision": zero, "drift": zero},
            info={"params": params, "steps": jnp.int32(0), "key": key},
        )

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        params = state.info["params"]
        data, hit = self.drive(params, state.data, self._commands[action])
        moved = jnp.linalg.norm(data.qpos[:2] - state.data.qpos[:2])
        steps = state.info["steps"] + 1
        truncated = (steps >= self.task.max_steps) & ~hit
        key, k_obs = jax.random.split(state.info["key"])
        return EnvState(
            data=data,
            obs=self.sense(params, data, k_obs),
            reward=-moved,
            done=hit | truncated,
            truncated=truncated,
            metrics={"collision": hit.astype(jnp.float32), "drift": moved},
            info={"params": params, "steps": steps, "key": key},
        )
