"""Wrappers over the env contract: per-episode auto-reset and episode statistics for training.

`EpisodeStats` sums the reward and each declared metric over an episode and publishes the sums in
`info["episode"]` on the step that ends it (per env: vmap it); `AutoReset` runs a batch of envs and
starts a new episode (a fresh draw of room, spawn and parameters: the task's own `reset`) wherever
one ended. Training uses `AutoReset(EpisodeStats(env), pool)`; evaluation uses the bare task and
stops each episode itself.
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
    """A batch of N envs (`reset(keys [N, 2])`, `step(state, action [N])`) in which every env
    whose episode ends continues with a new one, drawn by the env's own `reset`.

    The step's reward, done, truncated and metrics are kept (they belong to the episode that
    ended); physics, observation and info come from the new episode, except the finished-episode
    statistics `info["episode"]`, which carry over.

    `pool`: new episodes drawn per step (None or >= N: one per env). Under vmap a draw costs the
    same whether it is used or not, and episodes last tens to hundreds of steps, so drawing one
    for every env at every step spends most of a step's sensing and room sampling on draws that
    are thrown away. With a pool of P, the k-th env to finish in a step (k = 0, 1, ...) takes draw
    k mod P; if more than P finish in one step, some of them start the same episode (room, spawn
    and parameters), and their trajectories part with the policy's own sampling.
    """

    def __init__(self, env, pool: int | None = None):
        super().__init__(env)
        if pool is not None and pool < 1:
            raise ValueError(f"AutoReset.pool: must be >= 1, got {pool}")
        self.pool = pool

    def reset(self, keys: jax.Array) -> EnvState:
        keys, k_reset = _split(keys)
        state = jax.vmap(self.env.reset)(k_reset)
        return state.replace(info={**state.info, RESET_KEY: keys})

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        keys, k_reset = _split(state.info[RESET_KEY])  # [N, 2] each
        info = {k: v for k, v in state.info.items() if k != RESET_KEY}
        nxt = jax.vmap(self.env.step)(state.replace(info=info), action)
        n = action.shape[0]
        pool = min(self.pool or n, n)
        fresh = jax.vmap(self.env.reset)(k_reset[:pool])  # [P]
        slot = (jnp.cumsum(nxt.done) - 1) % pool  # [N] the draw each finishing env takes
        fresh = jax.tree_util.tree_map(lambda x: x[slot], fresh)
        if EPISODE in nxt.info:
            fresh = fresh.replace(info={**fresh.info, EPISODE: nxt.info[EPISODE]})
        pick = lambda new, old: jnp.where(  # noqa: E731
            nxt.done.reshape(-1, *([1] * (new.ndim - 1))), new, old
        )
        data, obs, info = jax.tree_util.tree_map(
            pick, (fresh.data, fresh.obs, fresh.info), (nxt.data, nxt.obs, nxt.info)
        )
        return nxt.replace(data=data, obs=obs, info={**info, RESET_KEY: keys})


def _split(keys: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each of the keys [N, 2] split in two: ([N, 2], [N, 2])."""
    pairs = jax.vmap(jax.random.split)(keys)  # [N, 2, 2]
    return pairs[:, 0], pairs[:, 1]
