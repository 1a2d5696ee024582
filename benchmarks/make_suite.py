"""Writes the benchmark suites: rooms of every family from a fixed seed, one file per family.

    python benchmarks/make_suite.py                 # -> scenes/benchmark/<family>.json
    python benchmarks/make_suite.py --suite hard    # -> scenes/hard/<family>.json

`benchmark`: the eight families of 'all', drawn by `jaxnav.core.families` (all of them in one
compiled call). `hard`: the families 'all' leaves out (`HARD`: BARN-like dense fields, halls to
30 m, people crossing the room), drawn by the env's own reset (`make_env` with only that family),
so a `crowd` room's walkers are those training meets, written as cylinders walking to a goal and
back. Rooms become layouts with the family's free spawn as the robot pose (`families.to_layout`)
and are written with `save_layouts`. Evaluate a policy on them with `python -m jaxnav.evaluate
--suite benchmark` (or `--suite hard`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp

import jaxnav
from jaxnav.core import families
from jaxnav.core.randomize import RandomizeConfig, family_weights
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.io.layouts import save_layouts

SCENES = Path(__file__).resolve().parent.parent / "scenes"
HARD = ("dense_field", "long_hall", "crowd")  # the families of the `hard` suite


def _one(rooms, j: int):
    """Room `j` of a batch of rooms."""
    return jax.tree_util.tree_map(lambda x: x[j], rooms)


def make_suite(seed: int = 0, per_family: int = 4) -> dict:
    """{family: [RoomLayout]} of the benchmark suite, `per_family` rooms each, `<family>-<i>`."""
    names = [name for name in families.FAMILIES if name in family_weights("all")]
    keys = jax.random.split(jax.random.PRNGKey(seed), per_family * len(names))
    index = jnp.repeat(jnp.array([list(families.FAMILIES).index(n) for n in names]), per_family)
    nb, nc, radius = families.FAMILY_BOXES, families.FAMILY_CYLINDERS, TURTLEBOT2I.radius
    draw = jax.jit(jax.vmap(lambda k, i: families.sample_family(k, i, nb, nc, radius)))
    rooms = jax.device_get(draw(keys, index))
    return {
        name: [
            families.to_layout(_one(rooms, f * per_family + i), f"{name}-{i}")
            for i in range(per_family)
        ]
        for f, name in enumerate(names)
    }


def make_hard(seed: int = 0, per_family: int = 4) -> dict:
    """{family: [RoomLayout]} of the hard suite: `per_family` rooms of each of `HARD`, each
    drawn by the reset of an env that samples only that family."""
    out = {}
    for f, name in enumerate(HARD):
        mix = RandomizeConfig(sampled_room_prob=1.0, families=name)
        env = jaxnav.make_env("avoid", randomize=mix)
        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), f), per_family)
        rooms = jax.device_get(jax.jit(jax.vmap(env.reset))(keys).info["params"])
        out[name] = [families.to_layout(_one(rooms, i), f"{name}-{i}") for i in range(per_family)]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", choices=("benchmark", "hard"), default="benchmark")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--per-family", type=int, default=4, help="rooms per family (default 4)")
    p.add_argument("--out", type=Path, help="folder of the family files (scenes/<suite>)")
    args = p.parse_args()
    out = args.out or SCENES / args.suite
    out.mkdir(parents=True, exist_ok=True)
    make = make_hard if args.suite == "hard" else make_suite
    for name, rooms in make(args.seed, args.per_family).items():
        save_layouts(out / f"{name}.json", rooms)
        print(
            f"{name:<14} {len(rooms)} rooms, up to {max(len(r.obstacles) for r in rooms)} "
            f"obstacles -> {out / name}.json"
        )


if __name__ == "__main__":
    main()
