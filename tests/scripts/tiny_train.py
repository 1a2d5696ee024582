"""Trains a tiny run as a run does (its programs: init from the draws and start, then a chunk of
the draws, rollout and learner) and saves its final weights: `python tiny_train.py OUT.npz`.

Run by tests in a subprocess, so that XLA_FLAGS (forced host devices) take effect before jax loads.
"""

import sys

import jax
import numpy as np

import jaxnav
from jaxnav.ppo.config import preset
from jaxnav.ppo.train import make_train
from jaxnav.training import find_programs

env = jaxnav.make_env("avoid", max_steps=50)
# Two robot blocks whatever the device count: one device then computes what two devices do,
# each rollout's new episodes drawn ahead (sharded by block).
cfg = preset(
    "cpu",
    num_envs=16,
    rollout_length=8,
    minibatch_size=64,
    num_epochs=2,
    total_steps=16 * 8 * 3,
    groups=2,
    reset_ahead=True,
    updates_per_chunk=3,
)
trainer = make_train(cfg, env)
# Each program compiled at its first call: init, then one chunk of the whole budget's updates.
ts, _ = trainer.run_chunk(trainer.init(jax.random.PRNGKey(0)))
leaves = jax.tree_util.tree_leaves(jax.device_get(ts.params))
# The cross-device ops of the programs every env step runs in (the rollout and the draws of its
# new episodes), compiled again from the abstract arguments a run gives them (as `find_programs`
# does: the same programs, so XLA's in-memory cache has them).
collectives = ("all-reduce", "all-gather", "all-to-all", "collective-permute", "reduce-scatter")


def hlo_of(name: str) -> list[str]:
    args = trainer.arguments(name, trainer.programs, jax.random.PRNGKey(0))
    return trainer.programs[name].lower(*args).compile().as_text().splitlines()


stepped = [*hlo_of("rollout"), *hlo_of("draws")]
rollout = [line for line in stepped if "/rollout/" in line]  # `make_train` names its scope
waits = [
    line
    for line in stepped
    if any(f" {op}(" in line or f" {op}-start(" in line for op in collectives)
]
# And as a run starts them: every program compiled at once before any has run (on several
# devices too: their shardings are fixed, `Trainer.laid_out`), then called.
early, _, ahead = find_programs(trainer, None, env, jax.random.PRNGKey(0))
early_ts, _ = early.run_chunk(early.init(jax.random.PRNGKey(0)))
early_leaves = jax.tree_util.tree_leaves(jax.device_get(early_ts.params))
np.savez(
    sys.argv[1],
    *leaves,
    **{f"ahead_{i}": x for i, x in enumerate(early_leaves)},
    ahead=ahead,
    updates=int(ts.update),
    devices=len(jax.devices()),
    shards=len(ts.env_state.obs.sharding.device_set),
    rollout_ops=len(rollout),
    rollout_collectives=len(waits),
)
