"""Toy envs of a few numbers for the auto-reset's tests, in this process or in a subprocess with
forced host devices (`tests/scripts/`)."""

import jax
import jax.numpy as jnp

from jaxnav.core.types import EnvState, window


class Countdown:
    """A toy env whose episodes last 1-6 steps, drawn per episode, so that in a batch some steps
    end fewer episodes than the auto-reset pool holds and some more."""

    metric_names = ()

    def reset(self, key):
        k_len, k_obs, key = jax.random.split(key, 3)
        length = jax.random.randint(k_len, (), 1, 7)
        obs = jax.random.normal(k_obs, (2,))
        f0, b0 = jnp.float32(0), jnp.bool_(False)
        info = {"left": length, "key": key}
        return EnvState(data=obs, obs=obs, reward=f0, done=b0, truncated=b0, metrics={}, info=info)

    def step(self, state, action):
        left = state.info["left"] - 1
        data = state.data + action
        return state.replace(
            data=data,
            obs=2 * data,
            reward=data.sum(),
            done=left <= 0,
            info={**state.info, "left": left},
        )


class Ledger(Countdown):
    """A Countdown whose episodes each draw a table [8] at their reset, which every step reads a
    window of (`banked_info`): an array `AutoReset.bank` leaves in place. Its state also holds an
    array of no elements, as a room without walkers does."""

    banked_info = ("table",)

    def reset(self, key):
        state = super().reset(key)
        table = jax.random.normal(jax.random.fold_in(key, 1), (8,))
        return state.replace(info={**state.info, "table": table, "none": jnp.zeros((0, 2))})

    def step(self, state, action):
        nxt = super().step(state, action)
        read = window(state.info["table"], (jnp.clip(nxt.info["left"], 0, 6),), (2,))
        return nxt.replace(reward=nxt.reward + read.sum())
