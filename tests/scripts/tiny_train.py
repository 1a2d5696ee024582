"""Trains a tiny run and saves its final weights: `python tiny_train.py OUT.npz`.

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
)
trainer = make_train(cfg, env)
ts, metrics = trainer.train(jax.random.PRNGKey(0))
leaves = jax.tree_util.tree_leaves(jax.device_get(ts.params))
# The compiled program's cross-device ops within the rollout (`make_train` names it), read from
# the executable just run (the lowering is cached: nothing compiles again).
hlo = trainer.train.lower(jax.random.PRNGKey(0)).compile().as_text()
rollout = [line for line in hlo.splitlines() if "/rollout/" in line]
collectives = ("all-reduce", "all-gather", "all-to-all", "collective-permute", "reduce-scatter")
waits = [
    line
    for line in rollout
    if any(f" {op}(" in line or f" {op}-start(" in line for op in collectives)
]
# The same updates as a run trains them: init and chunks of the trainer's programs (the draws,
# start and update, with the new episodes drawn ahead).
run_ts, _ = trainer.run_chunk(trainer.init(jax.random.PRNGKey(0)))
chunk_leaves = jax.tree_util.tree_leaves(jax.device_get(run_ts.params))
# And as a run starts them: every program compiled at once before any has run (on several
# devices too: their shardings are fixed, `Trainer.laid_out`), then called.
early, _, ahead = find_programs(trainer, None, env, jax.random.PRNGKey(0))
early_ts, _ = early.run_chunk(early.init(jax.random.PRNGKey(0)))
early_leaves = jax.tree_util.tree_leaves(jax.device_get(early_ts.params))
np.savez(
    sys.argv[1],
    *leaves,
    **{f"chunk_{i}": x for i, x in enumerate(chunk_leaves)},
    **{f"ahead_{i}": x for i, x in enumerate(early_leaves)},
    ahead=ahead,
    chunk_updates=int(run_ts.update),
    chunk_shards=len(run_ts.env_state.obs.sharding.device_set),
    devices=len(jax.devices()),
    shards=len(ts.env_state.obs.sharding.device_set),
    rollout_ops=len(rollout),
    rollout_collectives=len(waits),
)
