"""Could BARN's worlds run as occupancy grids? Free space and env-step speed, cylinders against cells.

    python benchmarks/barn_grid.py --num-envs 256 --steps 50 --repeats 3 \
        --json benchmarks/results/barn_grid_cpu.json

Each BARN world (`scenes/barn/{easy,medium,hard}.json`) holds up to a few hundred 0.075 m cylinders on 0.15 m
centres. As a grid, each becomes the 0.15 m cell it is inscribed in (`as_grid`): a square reaching
0.031 m further at its corners, so a gap between two diagonal neighbours narrows and may close. This
script counts, per world, whether the goal stays reachable for the robot's disc (the 0.1 m occupancy
grid of `families.reachable`, the robot's radius inflated) and how much of the free floor is lost,
and times the `goal` env step over the whole suite as one bank, both ways.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import numpy as np
from report import run_info, write_json

import jaxnav
from jaxnav.core import families
from jaxnav.core.layout import Cylinder, Grid, RoomLayout
from jaxnav.core.randomize import RandomizeConfig
from jaxnav.core.scene import SCENES_DIR
from jaxnav.io import barn
from jaxnav.io.layouts import load_layout


def as_grid(layout: RoomLayout) -> RoomLayout:
    """`layout` with its cylinders (all on BARN's 0.15 m lattice) as the cells of one grid."""
    cyl = layout.cylinders
    if not cyl:
        return layout
    centres = np.array([c.pos for c in cyl])
    origin = centres.min(0) - 0.5 * barn.CELL
    ij = np.round((centres - origin) / barn.CELL - 0.5).astype(int)  # [N, 2] column, row
    cells = np.zeros(ij.max(0)[::-1] + 1, bool)
    cells[ij[:, 1], ij[:, 0]] = True
    rows = ["".join("#" if c else "." for c in row) for row in cells[::-1]]
    grid = Grid(origin=tuple(origin), cell=barn.CELL, rows=rows, height=cyl[0].height)
    rest = tuple(ob for ob in layout.obstacles if not isinstance(ob, Cylinder))
    return dataclasses.replace(layout, obstacles=(*rest, grid))


def reachability(layout: RoomLayout) -> tuple[bool, int]:
    """(the goal's cell is reachable from the spawn, reachable cells) on the 0.1 m grid."""
    reach, centres = families.reachable(layout)
    d = np.linalg.norm(centres - np.asarray(layout.goal_pos), axis=-1)
    return bool(reach.flat[np.argmin(d)]), int(reach.sum())


def env_speed(layouts, num_envs: int, steps: int, repeats: int) -> dict:
    """{compile_s, env_steps_per_s} of the goal env's step (random actions) over `layouts`."""
    env = jaxnav.make_env("goal", layouts=layouts, randomize=RandomizeConfig())
    spec = env.action_spec

    def actions(key):
        if hasattr(spec, "n"):  # discrete
            return jax.random.randint(key, (num_envs,), 0, spec.n)
        low, high = np.asarray(spec.low), np.asarray(spec.high)
        return jax.random.uniform(key, (num_envs, low.size), minval=low, maxval=high)

    @jax.jit
    def run(state, key):
        def body(s, k):
            s = jax.vmap(env.step)(s, actions(k))
            return s, s.reward.sum()

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), num_envs))
    start = time.perf_counter()
    jax.block_until_ready(run(state, jax.random.PRNGKey(1)))
    compile_s = time.perf_counter() - start
    best = float("inf")
    for r in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run(state, jax.random.PRNGKey(2 + r)))
        best = min(best, time.perf_counter() - start)
    return {"compile_s": round(compile_s, 2), "env_steps_per_s": round(num_envs * steps / best)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--worlds", type=int, default=300, help="the first N worlds of the suite")
    p.add_argument("--no-speed", action="store_true", help="free space only")
    p.add_argument("--json", help="write the result here")
    args = p.parse_args()
    files = [SCENES_DIR / "barn" / f"{g}.json" for g in ("easy", "medium", "hard")]
    rooms = sorted((r for f in files for r in load_layout(f)), key=lambda r: int(r.name[6:]))
    rooms = rooms[: args.worlds]
    grids = [as_grid(room) for room in rooms]
    worlds = {}
    for room, grid in zip(rooms, grids, strict=True):
        (ok_c, area_c), (ok_g, area_g) = reachability(room), reachability(grid)
        worlds[room.name] = {"goal_reachable": [ok_c, ok_g], "free_cells": [area_c, area_g]}
    both = np.array([w["goal_reachable"] for w in worlds.values()])
    area = np.array([w["free_cells"] for w in worlds.values()], float)
    lost = 1 - area[:, 1] / np.maximum(area[:, 0], 1)
    summary = {
        "worlds": len(rooms),
        "goal_reachable_cylinders": int(both[:, 0].sum()),
        "goal_reachable_grid": int(both[:, 1].sum()),
        "closed_by_grid": int((both[:, 0] & ~both[:, 1]).sum()),
        "reachable_area_lost_mean": round(float(lost.mean()), 4),
        "reachable_area_lost_max": round(float(lost.max()), 4),
    }
    print(summary)
    if not args.no_speed:
        for name, bank in (("cylinders", rooms), ("grid", grids)):
            summary[f"speed_{name}"] = env_speed(bank, args.num_envs, args.steps, args.repeats)
            print(name, summary[f"speed_{name}"])
    result = {
        **run_info("device"),
        "num_envs": args.num_envs,
        "steps": args.steps,
        "summary": summary,
        "worlds": worlds,
        **run_info("python", "date", "jax"),
    }
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
