"""Any jaxnav task as a `brax.envs.Env`: `make_brax_env(name, **kwargs)` (needs brax: the `brax`
extra, `pip install -e ".[brax]"` in the repository).

brax's trainers (`brax.training.agents.ppo.train`, `sac.train`) wrap an env with
`brax.envs.wrappers.training.wrap`: a VmapWrapper, an EpisodeWrapper (time limit, episode
metrics) and an AutoResetWrapper, which on `done` puts back the state and observation saved at the
first reset (`info["first_pipeline_state"]`, `info["first_obs"]`): every later episode would
replay the first room, spawn and robot parameters. The adapter keeps jaxnav's per-episode
randomisation: its `pipeline_state` is the task's whole `EnvState` (room and robot parameters
included), and under an AutoResetWrapper each step writes a fresh draw of the task's own `reset`
into those two entries, so wherever an episode ends (a collision, a goal reached or the
EpisodeWrapper's time limit) the next is a new episode. Under vmap a draw costs the same whether
it is used or not: one task reset per robot per step (jaxnav's own `AutoReset` draws a pool of
1/16 of the robots instead).

The time limit is brax's: the adapter reports terminations only, and the EpisodeWrapper ends an
episode after `episode_length` steps as a truncation (not a terminal for brax's PPO). Pass
`episode_length=env.episode_length`, the task's `max_steps`. Actions are brax's [-1, 1] per
dimension, mapped linearly onto the task's continuous bounds (`to_command`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

try:
    from brax.envs.base import Env, State
except ImportError as err:  # one line for the user, not a traceback from deep inside brax
    raise ImportError(
        'jaxnav.make_brax_env needs brax: pip install brax (or -e ".[brax]" in the repository)'
    ) from err

from jaxnav.core.types import ContinuousActions
from jaxnav.tasks.registry import make_env, task_entry
from jaxnav.wrappers import RESET_KEY


def _restore_device_put_replicated() -> None:
    """brax 0.14.2's trainers call `jax.device_put_replicated`, which jax 0.10 removed (brax issue
    671, open): where it is missing, put it back as jax's pmap migration guide does (a copy per
    device, stacked and sharded over the devices). Nothing else of jax changes."""
    if hasattr(jax, "device_put_replicated"):
        return

    def device_put_replicated(x, devices):
        # The sharding pmap gives its own outputs: with any other, brax's pmapped training epoch
        # would compile a second time when its outputs come back as inputs.
        sharding = jax.pmap(lambda y: y, devices=devices)(jnp.zeros(len(devices))).sharding
        return jax.tree.map(lambda y: jax.device_put(jnp.stack([y] * len(devices)), sharding), x)

    jax.device_put_replicated = device_put_replicated


_restore_device_put_replicated()
FIRST_STATE, FIRST_OBS = "first_pipeline_state", "first_obs"  # brax AutoResetWrapper's info keys


def to_command(spec: ContinuousActions, action: jax.Array) -> jax.Array:
    """brax action [..., A] in [-1, 1] -> command [..., A] within the spec's bounds (linear: -1 ->
    low, 1 -> high; outside [-1, 1] clipped)."""
    low, high = jnp.asarray(spec.low), jnp.asarray(spec.high)
    return low + 0.5 * (jnp.clip(action, -1.0, 1.0) + 1.0) * (high - low)


class BraxEnv(Env):
    """A jaxnav task (one robot, continuous actions) behind brax's `Env` interface."""

    def __init__(self, env):
        if not isinstance(env.action_spec, ContinuousActions):
            raise ValueError(
                "make_brax_env: brax's trainers need continuous actions; this task has "
                f"{type(env.action_spec).__name__} (pass actions='continuous')"
            )
        self.env = env

    @property
    def observation_size(self) -> int:
        return self.env.observation_size

    @property
    def action_size(self) -> int:
        return self.env.action_spec.size

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def dt(self) -> float:
        """Seconds per step."""
        return self.env.control_period

    @property
    def episode_length(self) -> int:
        """The task's time limit in steps: pass it as brax's `episode_length`."""
        return self.env.task.max_steps

    def reset(self, rng: jax.Array) -> State:
        key, k_task = jax.random.split(rng)
        return self._wrap(self.env.reset(k_task), {RESET_KEY: key})

    def step(self, state: State, action: jax.Array) -> State:
        inner = self.env.step(state.pipeline_state, to_command(self.env.action_spec, action))
        info = dict(state.info)
        if FIRST_STATE in info:  # under brax's AutoResetWrapper: the next episode is a new draw
            key, k_new = jax.random.split(info[RESET_KEY])
            fresh = self.env.reset(k_new)
            info.update({FIRST_STATE: fresh, FIRST_OBS: fresh.obs, RESET_KEY: key})
        # Wrappers add metrics too (brax's EvalWrapper: "reward"): keep theirs, as brax envs do.
        return self._wrap(inner, info, state.metrics)

    def _wrap(self, inner, info: dict, metrics: dict | None = None) -> State:
        """The brax State of a task's EnvState; done = terminations (not the task's time limit)."""
        return State(
            pipeline_state=inner,
            obs=inner.obs,  # [observation_size]
            reward=inner.reward.astype(jnp.float32),  # []
            done=(inner.done & ~inner.truncated).astype(jnp.float32),  # []
            metrics={
                **(metrics or {}),
                **{k: v.astype(jnp.float32) for k, v in inner.metrics.items()},
            },
            info=info,
        )


def make_brax_env(name: str = "avoid", **kwargs) -> BraxEnv:
    """Task `name` as a `brax.envs.Env` with continuous actions; `kwargs` are `jaxnav.make_env`'s
    (layouts, randomize, sensor, scene, robot and task fields). Train it with brax as it is:
    `ppo.train(environment=env, episode_length=env.episode_length, ...)`."""
    fields = {f.name for f in dataclasses.fields(task_entry(name).config_cls)}
    if "actions" in fields:
        kwargs = {"actions": "continuous", **kwargs}
    return BraxEnv(make_env(name, **kwargs))
