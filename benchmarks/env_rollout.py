"""Env-only throughput: random-policy rollouts of the default `avoid` distribution.

    python benchmarks/env_rollout.py --num-envs 1024 --steps 100 --json benchmarks/env_rollout.json
    python benchmarks/env_rollout.py --fidelity rows,dynamics ...   # with sim-to-real pieces on
    python benchmarks/env_rollout.py --physics fast,wheeled ...     # and the wheeled validation model

`--fidelity` switches on pieces of the sim-to-real model, to time what each costs: `rows` (the
5-row camera with the Astra's far-range invalid readings), `dynamics` (randomize.FIDELITY: velocity
smoother, latency, wheel mismatch, noise model, dark obstacles, camera error, low obstacles and
overhangs). `--physics fast,wheeled` also times the wheeled validation model, the repeats of the
two taking turns.

Times a jitted `lax.scan` of `--steps` batched steps (auto-reset included) after compiling it once,
and prints env-steps/s per batch size.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time

import jax
import jax.numpy as jnp

import jaxnav
from jaxnav.core.randomize import FIDELITY, TRAINING
from jaxnav.core.scene import PHYSICS, SceneConfig
from jaxnav.core.sensors import SensorConfig
from jaxnav.wrappers import AutoReset


def make(fidelity: tuple[str, ...], physics: str = "fast"):
    """The training env with the named fidelity pieces on, under `physics`."""
    kwargs = {"scene": SceneConfig(physics=physics)}
    if "rows" in fidelity:
        kwargs["sensor"] = SensorConfig(rows=5, far_invalid=True)
    if "dynamics" in fidelity:
        kwargs["randomize"] = dataclasses.replace(TRAINING, **FIDELITY)
    return AutoReset(jaxnav.make_env("avoid", **kwargs))  # new episodes where they end


def prepare(num_envs: int, steps: int, fidelity=(), physics="fast"):
    """(jitted rollout(state, key), a reset batch state, compile seconds) of one configuration."""
    env = make(fidelity, physics)
    reset = jax.jit(jax.vmap(env.reset))

    @jax.jit
    def rollout(state, key):
        def body(carry, k):
            state, total = carry
            action = jax.random.randint(k, (num_envs,), 0, env.action_spec.n)
            state = jax.vmap(env.step)(state, action)
            return (state, total + state.reward.sum()), None

        (state, total), _ = jax.lax.scan(
            body, (state, jnp.float32(0)), jax.random.split(key, steps)
        )
        return state, total

    tick = time.perf_counter()
    state = jax.block_until_ready(reset(jax.random.split(jax.random.PRNGKey(0), num_envs)))
    state, _ = jax.block_until_ready(rollout(state, jax.random.PRNGKey(1)))
    return rollout, state, time.perf_counter() - tick


def measure(num_envs: int, steps: int, repeats: int, fidelity=(), physics=("fast",)) -> list:
    """One row per physics. The timed repeats take turns between them (each repeat runs every
    physics once), so the load of a shared machine falls on all alike."""
    runs = {p: list(prepare(num_envs, steps, fidelity, p)) for p in physics}
    best = dict.fromkeys(physics, float("inf"))
    for i in range(repeats):
        for p, run in runs.items():
            tick = time.perf_counter()
            run[1], _ = jax.block_until_ready(run[0](run[1], jax.random.PRNGKey(2 + i)))
            best[p] = min(best[p], time.perf_counter() - tick)
    return [
        {
            "num_envs": num_envs,
            "fidelity": ",".join(fidelity) or "off",
            "physics": p,
            "steps": steps,
            "compile_s": round(runs[p][2], 2),
            "seconds": round(best[p], 4),
            "env_steps_per_s": round(num_envs * steps / best[p]),
        }
        for p in physics
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", default="1024", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--fidelity", default="", help="comma-separated: rows, dynamics")
    parser.add_argument(
        "--physics",
        default="fast",
        help=f"comma-separated, of {', '.join(PHYSICS)}: the robot's physics (several: timed in turns)",
    )
    args = parser.parse_args()
    fidelity = tuple(f for f in args.fidelity.split(",") if f)
    sizes = [int(n) for n in args.num_envs.split(",")]
    physics = tuple(args.physics.split(","))
    unknown = sorted(set(physics) - set(PHYSICS))
    if unknown:
        parser.error(f"--physics: unknown {unknown}; valid: {', '.join(PHYSICS)}")
    rows = [row for n in sizes for row in measure(n, args.steps, args.repeats, fidelity, physics)]
    device = jax.devices()[0]
    result = {
        "device": f"{device.platform}: {device.device_kind}",
        "cpus": jax.local_device_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "rows": rows,
    }
    print(
        f"{'robots':>8} {'physics':>8} {'steps':>6} {'compile s':>10} {'env-steps/s':>12}   "
        f"({result['device']}, fidelity: {args.fidelity or 'off'})"
    )
    for r in rows:
        print(
            f"{r['num_envs']:>8} {r['physics']:>8} {r['steps']:>6} {r['compile_s']:>10} "
            f"{r['env_steps_per_s']:>12,}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)


if __name__ == "__main__":
    main()
