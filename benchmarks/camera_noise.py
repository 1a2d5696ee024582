"""The camera's per-step random numbers for a batch of robots: `jax.random.uniform` (threefry)
against `jaxnav.core.draws.hashed_uniform`, which the sensor draws its noise and dropout with.

    python benchmarks/camera_noise.py --num-envs 256,512 --json benchmarks/results/camera_noise_cpu.json

Each robot draws [2, rows, rays] values of its own key (the noise's and the dropout's), as
`sensors.camera_readings` does under the env's vmap; the default camera's 5 rows of 24 rays. Each
time is the best of `--repeats` runs of a jitted loop of `--steps` draws (keys split per step, as
the env's are) after its compile (`throughput.timed`), in ms a step.
"""

from __future__ import annotations

import argparse

import jax
from report import run_info, write_json
from throughput import timed

from jaxnav.core.draws import hashed_uniform
from jaxnav.core.sensors import SensorConfig

DRAWS = {"threefry": jax.random.uniform, "hash": hashed_uniform}


def loop(draw, shape, steps):
    """jit(keys [N, 2] -> the last step's sum): `steps` draws of `shape` a robot, new keys a step."""

    def step(keys, _):
        keys = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
        return keys, jax.vmap(lambda k: draw(k, shape).sum())(keys)

    return jax.jit(lambda keys: jax.lax.scan(step, keys, None, steps)[1][-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num-envs", default="256,512", help="robots, comma-separated")
    p.add_argument("--steps", type=int, default=32)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", help="write the results here")
    args = p.parse_args()
    cfg = SensorConfig()
    shape = (2, cfg.rows, cfg.num_sectors * cfg.rays_per_sector)
    rows = []
    for n in map(int, args.num_envs.split(",")):
        keys = jax.random.split(jax.random.PRNGKey(0), n)
        row = {"num_envs": n, "shape": list(shape)}
        for name, draw in DRAWS.items():
            compile_s, best = timed(loop(draw, shape, args.steps), keys, repeats=args.repeats)
            row[name] = {"ms_per_step": round(best / args.steps * 1e3, 4)}
            row[name]["compile_s"] = round(compile_s, 2)
        rows.append(row)
        print(
            f"{n:>7} robots  threefry {row['threefry']['ms_per_step']:.3f} ms/step  "
            f"hash {row['hash']['ms_per_step']:.3f} ms/step  ({run_info('device')['device']})"
        )
    if args.json:
        write_json(args.json, {**run_info("device", "jax"), "steps": args.steps, "rows": rows})


if __name__ == "__main__":
    main()
