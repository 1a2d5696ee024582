"""What obstacles cost the env step: a 16-obstacle room against 200 obstacles in slots and on a grid.

    python benchmarks/obstacle_scaling.py --num-envs 256 --steps 50 --repeats 3 \
        --json benchmarks/results/obstacle_scaling_cpu.json

Rooms (6 x 6 m, the `avoid` task, exact physics and sensing, the default 5-row camera):
`room16` (12 boxes and 4 cylinders in slots), `room16_grid` (the same with an empty 30 x 30
occupancy grid: what a room without cells pays in a batch with grid rooms), `cyl200` (200 BARN
cylinders, radius 0.075 m, on 0.15 m centres: 200 cylinder slots) and `grid200` (the same 200
places as cells of a 0.15 m occupancy grid, `jaxnav.core.grid`). Times a jitted `lax.scan` of
`--steps` batched env steps with uniform random actions (no resets) after compiling it once.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from report import run_info, write_json

import jaxnav
from jaxnav.core.layout import Box, Cylinder, Grid, RoomLayout
from jaxnav.core.randomize import RandomizeConfig

SIZE, FIELD, CELL = 6.0, 30, 0.15  # room side m; field cells a side; cell m (BARN's)
SPAWN = (0.0, -2.6)  # the robot by the south wall, facing the field
VARIANTS = ("room16", "room16_grid", "cyl200", "grid200")


def _field(rng, count: int) -> np.ndarray:
    """[FIELD, FIELD] bool, rows south to north: `count` random cells, none near the spawn."""
    origin = -0.5 * FIELD * CELL
    centres = origin + (np.stack(np.meshgrid(np.arange(FIELD), np.arange(FIELD)), -1) + 0.5) * CELL
    free = np.linalg.norm(centres - SPAWN, axis=-1) > 0.8
    picks = rng.choice(np.flatnonzero(free), count, replace=False)
    cells = np.zeros(FIELD * FIELD, bool)
    cells[picks] = True
    return cells.reshape(FIELD, FIELD)


def _grid(cells: np.ndarray) -> Grid:
    rows = ["".join("#" if c else "." for c in row) for row in cells[::-1]]
    return Grid(origin=(-0.5 * FIELD * CELL,) * 2, cell=CELL, rows=rows, height=1.0)


def rooms(seed: int = 0) -> dict[str, RoomLayout]:
    """{variant: its room}."""
    rng = np.random.default_rng(seed)
    room = dict(size=(SIZE, SIZE), robot_pos=SPAWN, robot_yaw=np.pi / 2)
    sixteen = _field(rng, 16)
    centres = -0.5 * FIELD * CELL + (np.argwhere(sixteen)[:, ::-1] + 0.5) * CELL
    few = [Box(pos=tuple(p), size=(0.4, 0.3), yaw=0.3) for p in centres[:12]]
    few += [Cylinder(pos=tuple(p), radius=0.15) for p in centres[12:]]
    dense = _field(rng, 200)
    places = -0.5 * FIELD * CELL + (np.argwhere(dense)[:, ::-1] + 0.5) * CELL
    barn = [Cylinder(pos=tuple(p), radius=0.075, height=1.0) for p in places]
    empty = _grid(np.zeros((FIELD, FIELD), bool))
    return {
        "room16": RoomLayout(name="room16", obstacles=tuple(few), **room),
        "room16_grid": RoomLayout(name="room16_grid", obstacles=(*few, empty), **room),
        "cyl200": RoomLayout(name="cyl200", obstacles=tuple(barn), **room),
        "grid200": RoomLayout(name="grid200", obstacles=(_grid(dense),), **room),
    }


def compiled(layout: RoomLayout, num_envs: int, steps: int):
    """(a function of a seed that runs `steps` batched env steps in `layout`, its compile s)."""
    env = jaxnav.make_env("avoid", layouts=[layout], randomize=RandomizeConfig())
    n = env.action_spec.n

    @jax.jit
    def run(state, key):
        def body(s, k):
            s = jax.vmap(env.step)(s, jax.random.randint(k, (num_envs,), 0, n))
            return s, s.reward.sum()

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), num_envs))
    start = time.perf_counter()
    jax.block_until_ready(run(state, jax.random.PRNGKey(1)))
    return lambda seed: jax.block_until_ready(run(state, jax.random.PRNGKey(seed))), (
        time.perf_counter() - start
    )


def measure(layouts: dict, num_envs: int, steps: int, repeats: int) -> dict:
    """{variant: {compile_s, env_steps_per_s}}: every variant compiled first, then timed in turn
    `repeats` times (best of them), so that a load that comes and goes touches each alike."""
    runs = {name: compiled(layout, num_envs, steps) for name, layout in layouts.items()}
    best = dict.fromkeys(layouts, float("inf"))
    for r in range(repeats):
        for name, (run, _) in runs.items():
            start = time.perf_counter()
            run(2 + r)
            best[name] = min(best[name], time.perf_counter() - start)
    return {
        name: {"compile_s": round(runs[name][1], 2), "env_steps_per_s": round(num_envs * steps / t)}
        for name, t in best.items()
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--json", help="write the result here")
    args = p.parse_args()
    layouts = {name: rooms()[name] for name in args.variants.split(",")}
    results = measure(layouts, args.num_envs, args.steps, args.repeats)
    print(
        f"{'room':<12} {'slots':>5} {'cells':>5} {'env-steps/s':>12} {'vs room16':>9} {'compile s':>9}"
    )
    base = results.get("room16", next(iter(results.values())))["env_steps_per_s"]
    for name, out in results.items():
        layout = layouts[name]
        out["slots"] = len(layout.boxes) + len(layout.cylinders)
        out["grid_cells"] = layout.grid.cell_boxes()[0].shape[0] if layout.grid else 0
        out["vs_room16"] = round(out["env_steps_per_s"] / base, 3)
        print(
            f"{name:<12} {out['slots']:>5} {out['grid_cells']:>5} {out['env_steps_per_s']:>12,} "
            f"{out['vs_room16']:>9.2f} {out['compile_s']:>9.1f}"
        )
    result = {
        **run_info("device"),
        "num_envs": args.num_envs,
        "steps": args.steps,
        "repeats": args.repeats,
        "variants": results,
        **run_info("python", "date", "jax"),
    }
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
