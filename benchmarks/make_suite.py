"""Writes the benchmark suite: rooms of every family from a fixed seed, one file per family.

    python benchmarks/make_suite.py            # -> scenes/benchmark/<family>.json

Rooms are drawn by `jaxnav.core.families` (all families in one compiled call), converted to layouts
with the family's free spawn as the robot pose, and written with `save_layouts`. Evaluate a policy
on them with `python -m jaxnav.evaluate --suite benchmark`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp

from jaxnav.core import families
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.io.layouts import save_layouts

OUT = Path(__file__).resolve().parent.parent / "scenes" / "benchmark"


def make_suite(seed: int = 0, per_family: int = 4) -> dict:
    """{family: [RoomLayout]} with `per_family` rooms each, named `<family>-<i>`."""
    names = list(families.FAMILIES)
    keys = jax.random.split(jax.random.PRNGKey(seed), per_family * len(names))
    index = jnp.repeat(jnp.arange(len(names)), per_family)
    nb, nc, radius = families.FAMILY_BOXES, families.FAMILY_CYLINDERS, TURTLEBOT2I.radius
    draw = jax.jit(jax.vmap(lambda k, i: families.sample_family(k, i, nb, nc, radius)))
    rooms = jax.device_get(draw(keys, index))
    one = lambda j: jax.tree_util.tree_map(lambda x: x[j], rooms)  # noqa: E731
    return {
        name: [
            families.to_layout(one(f * per_family + i), f"{name}-{i}") for i in range(per_family)
        ]
        for f, name in enumerate(names)
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--per-family", type=int, default=4, help="rooms per family (default 4)")
    p.add_argument("--out", type=Path, default=OUT, help="folder of the family files")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, rooms in make_suite(args.seed, args.per_family).items():
        save_layouts(args.out / f"{name}.json", rooms)
        boxes = max(len(r.boxes) for r in rooms)
        print(f"{name:<14} {len(rooms)} rooms, up to {boxes} boxes -> {args.out / name}.json")


if __name__ == "__main__":
    main()
