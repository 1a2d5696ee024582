"""Env-step throughput of scene and sensor variants, to choose the defaults by measurement.

    python benchmarks/scene_variants.py --num-envs 1024 --json benchmarks/results/scene_variants_cpu.json

Each variant changes one setting of the default scene (physics substeps, solver iterations, rays per
sector, obstacle slots) and times a jitted random-policy rollout with auto-reset, as env_rollout.py.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
from report import run_info, write_json

import jaxnav
from jaxnav.core.randomize import RandomizeConfig
from jaxnav.core.scene import SceneConfig
from jaxnav.core.sensors import SensorConfig

VARIANTS = {
    "default (2 x 0.05 s, 4 iterations, 24 rays, 8+4 slots)": {},
    "1 substep of 0.1 s": {"scene": {"substeps": 1, "timestep": 0.1}},
    "4 substeps of 0.025 s": {"scene": {"substeps": 4, "timestep": 0.025}},
    "5 substeps of 0.02 s": {"scene": {"substeps": 5, "timestep": 0.02}},
    "1 solver iteration": {"scene": {"solver_iterations": 1}},
    "10 solver iterations": {"scene": {"solver_iterations": 10}},
    "8 rays (1 per sector)": {"sensor": {"rays_per_sector": 1}},
    "16 rays (2 per sector)": {"sensor": {"rays_per_sector": 2}},
    "48 rays (6 per sector)": {"sensor": {"rays_per_sector": 6}},
    "16+8 obstacle slots": {"scene": {"num_boxes": 16, "num_cylinders": 8}},
}


def measure(changes: dict, n: int, steps: int, repeats: int) -> float:
    env = jaxnav.make_env(
        "avoid",
        scene=dataclasses.replace(SceneConfig(), **changes.get("scene", {})),
        sensor=dataclasses.replace(SensorConfig(), **changes.get("sensor", {})),
        randomize=RandomizeConfig(num_boxes=(8, 8), num_cylinders=(4, 4)),
    )

    @jax.jit
    def rollout(state, key):
        def body(state, k):
            state = jax.vmap(env.step)(state, jax.random.randint(k, (n,), 0, 3))
            return state, state.reward.sum()

        state, rewards = jax.lax.scan(body, state, jax.random.split(key, steps))
        return state, rewards.sum()

    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), n))
    state, _ = jax.block_until_ready(rollout(state, jax.random.PRNGKey(1)))
    best = float("inf")
    for i in range(repeats):
        tick = time.perf_counter()
        state, _ = jax.block_until_ready(rollout(state, jax.random.PRNGKey(2 + i)))
        best = min(best, time.perf_counter() - tick)
    return n * steps / best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json")
    args = parser.parse_args()
    rows = []
    for name, changes in VARIANTS.items():
        rate = measure(changes, args.num_envs, args.steps, args.repeats)
        rows.append({"variant": name, "changes": changes, "env_steps_per_s": round(rate)})
        print(f"{name:<55} {rate:>12,.0f} env-steps/s", flush=True)
    if args.json:
        head = {**run_info("device"), "num_envs": args.num_envs, **run_info("jax")}
        write_json(args.json, {**head, "rows": rows})


if __name__ == "__main__":
    jnp.zeros(())  # initialise the backend before timing
    main()
