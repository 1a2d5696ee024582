"""Wrappers over the env contract: per-episode auto-reset and episode statistics for training.

`EpisodeStats` sums the reward and each declared metric over an episode and publishes the sums in
`info["episode"]` on the step that ends it; `AutoReset` starts a new episode (a fresh draw of room,
spawn and parameters: the task's own `reset`) inside `step` wherever one ended. Training uses
`AutoReset(EpisodeStats(env))`; evaluation uses the bare task and stops each episode itself.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxnav.core.types import EnvState

EPISODE = "episode"  # info key of the finished-episode sums: return, length and each metric
RUNNING = "episode_running"  # info key of the sums of the episode in progress
RESET_KEY = "reset_key"  # info key of AutoReset's PRNG key


class Wrapper:
    """Forwards the contract's attributes to the wrapped env."""

    def __init__(self, env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)


class EpisodeStats(Wrapper):
    """info["episode"]: {"return", "length", *metric_names} of the last finished episode."""

    def _zeros(self) -> dict:
        names = ("return", "length", *self.env.metric_names)
        return {k: jnp.float32(0) for k in names}

    def reset(self, key: jax.Array) -> EnvState:
        state = self.env.reset(key)
        return state.replace(info={**state.info, RUNNING: self._zeros(), EPISODE: self._zeros()})

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        running = state.info[RUNNING]
        nxt = self.env.step(state, action)
        step_values = {"return": nxt.reward, "length": jnp.float32(1), **nxt.metrics}
        total = {k: running[k] + step_values[k].astype(jnp.float32) for k in running}
        done = nxt.done
        finished = {k: jnp.where(done, total[k], state.info[EPISODE][k]) for k in total}
        running = {k: jnp.where(done, 0.0, v) for k, v in total.items()}
        return nxt.replace(info={**nxt.info, RUNNING: running, EPISODE: finished})


class AutoReset(Wrapper):
    """Where a step ends an episode, the state continues with a new episode from `env.reset`.

    The step's reward, done, truncated and metrics are kept (they belong to the episode that
    ended); physics, observation and info come from the new episode, except the finished-episode
    statistics `info["episode"]`, which carry over.
    """

    def reset(self, key: jax.Array) -> EnvState:
        key, k_reset = jax.random.split(key)
        state = self.env.reset(k_reset)
        return state.replace(info={**state.info, RESET_KEY: key})

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        key, k_reset = jax.random.split(state.info[RESET_KEY])
        info = {k: v for k, v in state.info.items() if k != RESET_KEY}
        nxt = self.env.step(state.replace(info=info), action)
        fresh = self.env.reset(k_reset)
        if EPISODE in nxt.info:
            fresh = fresh.replace(info={**fresh.info, EPISODE: nxt.info[EPISODE]})
        pick = lambda new, old: jnp.where(nxt.done, new, old)  # noqa: E731
        data, obs, info = jax.tree_util.tree_map(
            pick, (fresh.data, fresh.obs, fresh.info), (nxt.data, nxt.obs, nxt.info)
        )
        return nxt.replace(data=data, obs=obs, info={**info, RESET_KEY: key})
