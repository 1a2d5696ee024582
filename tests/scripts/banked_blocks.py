"""Banked arrays on two devices, a block of robots on each (`AutoReset.bank`), against the select:
`python banked_blocks.py OUT.json`.

Run by tests in a subprocess, so that XLA_FLAGS (forced host devices) take effect before jax loads.
"""

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # tests/: the toy envs
from toy_envs import Ledger  # noqa: E402

from jaxnav.ppo.train import shard_envs  # noqa: E402
from jaxnav.wrappers import AutoReset, EpisodeStats  # noqa: E402

devices = jax.devices()
n, steps = 32, 8
env = AutoReset(EpisodeStats(Ledger()), pool=8, groups=len(devices), devices=devices)
robots, blocks = shard_envs(n, devices), shard_envs(n, devices, axis=1)


def window(state, banked: bool):
    """A window of steps drawing its new episodes ahead, as a PPO rollout, with the banks or
    selecting the arrays along; the rewards [T, N] and the state after it."""
    state, fresh = env.draw(state, steps)
    fresh, banks = blocks(fresh), {}
    if banked:
        state, fresh, banks = env.bank(state, fresh)
    step = lambda s, f: (robots(env.step(s, jnp.ones(n), f, banks)),) * 2  # noqa: E731
    state, states = jax.lax.scan(step, state, fresh)
    return states.reward, robots(env.unbank(state, banks))


state = jax.jit(lambda keys: robots(env.reset(keys)))(jax.random.split(jax.random.PRNGKey(0), n))
runs = {banked: jax.jit(window, static_argnums=1) for banked in (False, True)}
(selected, after), (banked, banked_after) = (runs[b](state, b) for b in (False, True))
hlo = runs[True].lower(state, True).compile().as_text()
waits = ("all-gather", "all-reduce", "collective-permute", "all-to-all", "reduce-scatter")
leaves = [jax.tree_util.tree_leaves(x) for x in ((selected, after), (banked, banked_after))]
same = all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(*leaves, strict=True))
json.dump(
    {
        "devices": len(devices),
        "equal": same,
        "ended": int(np.asarray(after.info["episode"]["length"]).astype(bool).sum()),
        "collectives": sum(hlo.count(f" {w}") for w in waits),
        "shards": len(banked_after.info["table"].sharding.device_set),
    },
    open(sys.argv[1], "w"),
)
