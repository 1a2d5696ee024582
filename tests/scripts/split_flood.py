"""The GPU flood kernel on each device's part of a batch (`goals._gpu_flood`, through Pallas'
interpreter on CPU devices) against the associative scans: `python split_flood.py OUT.json`.

Run by tests in a subprocess, so that XLA_FLAGS (forced host devices) take effect before jax loads.
"""

import json
import sys

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxnav.core import flood_kernel, goals

flood_kernel.MIN_BATCH = 2  # grids a device needs for the kernel: small batches here
devices = tuple(jax.devices())
rng = np.random.default_rng(0)
SWEEPS = 12


def case(lead: int) -> dict:
    """One batch [lead, 3, 12, 12] split along its first axis: the same steps as the scans, and
    whether the kernel ran (on each device's part) and any op waited for another device."""
    free = rng.random((lead, 3, 12, 12)) > 0.3
    seed = np.zeros_like(free)
    seed[..., 0, 0] = True
    seed &= free
    split = NamedSharding(Mesh(np.array(devices), ("grids",)), PartitionSpec("grids"))
    args = [
        jax.device_put(jnp.asarray(x), split) if lead % len(devices) == 0 else x
        for x in (free, seed)
    ]
    run = jax.jit(lambda f, s: goals._gpu_flood(f, s, SWEEPS, devices, interpret=True))
    got, want = run(*args), goals._flood_scans(jnp.asarray(free), jnp.asarray(seed), SWEEPS)
    jaxpr = str(jax.make_jaxpr(run)(*args))
    hlo = run.lower(*args).compile().as_text()
    waits = ("all-gather", "all-reduce", "collective-permute", "all-to-all")
    return {
        "equal": bool(np.array_equal(np.asarray(got), np.asarray(want))),
        "kernel": "pallas_call" in jaxpr,
        "split": "shard_map" in jaxpr,
        "collectives": sum(hlo.count(w) for w in waits),
        "reached": int(np.isfinite(np.asarray(want)).sum()),
    }


json.dump({"devices": len(devices), "even": case(4), "odd": case(3)}, open(sys.argv[1], "w"))
