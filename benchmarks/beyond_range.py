"""What should a sector read where the camera returns nothing because the wall is beyond its 8 m?

The Orbbec Astra returns 0 both for a surface nearer than 0.6 m and for no return within 8 m. Over
random collision-free poses in the benchmark suite's rooms and in sampled `long_hall` rooms, with
the sim-to-real ranges (noise, dropout, dark obstacles, mount error), each rule reads every
sector; the truth is the nearest non-floor surface the sector's rays meet (noiseless, any range).

- `beyond_reads_max`: the simulator's default (`far_invalid` off): beyond range reads range_max,
  which the real camera never reports;
- `unknown_near`: the camera's 0 beyond range (`far_invalid`) and the blind-zone rule alone: an
  unknown sector reads near, as the robot read it before `far_reads_max`;
- `sector`: every unknown ray at or above the horizon reads range_max;
- `all_witnesses`: as `sector`, but only in columns whose rays that meet the floor within range
  all returned;
- `far_mask` (`far_reads_max`, the rule chosen): as `sector`, but only in columns whose ray that
  meets the floor farthest within range returned.

The dangerous error is a sector whose surface lies in the blind zone (< 0.6 m) read as 1 m or more
(`blind_read_far`); the one the rule is for is a sector with nothing within 8 m read near
(`far_read_near`); blind-zone sectors are also split by whether their surface is an overhang's
(which the floor rays pass under). `--grid` also measures the goal task's traced grid: the
square one of the other families, the one laid along the halls (30 x 12 m), and a square one
that would cover 30 m.

    python benchmarks/beyond_range.py --json benchmarks/results/beyond_range_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from report import write_json

from jaxnav.core import episode, families, goals
from jaxnav.core.geometry import signed_distance
from jaxnav.core.randomize import FIDELITY, RandomizeConfig, make_bank
from jaxnav.core.robot import RobotSpec
from jaxnav.core.sensors import SensorConfig, camera_readings, reduce_sectors
from jaxnav.io.layouts import load_layout
from jaxnav.robot_side.observation import far_mask

ROBOT = RobotSpec()
CAMERA = SensorConfig(rows=5, far_invalid=True)
NEAR = 1.0  # m: a blind-zone surface read at least this far is misread as far (the reward's near)
SUITE = Path(__file__).resolve().parent.parent / "scenes" / "benchmark"


def _witnesses(rise, height, cfg):
    """[rows, C] rays that meet the floor within range (those `far_mask` takes its witness from)."""
    meets = height / jnp.where(rise < 0, -rise, 1.0)
    return (rise < 0) & (meets >= cfg.range_min) & (meets <= cfg.range_max)


def _far_sector(valid, rise, height, cfg):
    """[rows, C] every unknown ray at or above the horizon (no witness asked)."""
    return ~valid & (rise >= 0)


def _far_all_witnesses(valid, rise, height, cfg):
    """[rows, C] `far_mask`, but asking every floor ray of the column to return."""
    witness = _witnesses(rise, height, cfg)
    clear = witness.any(0) & ~(witness & ~valid).any(0)
    return ~valid & (rise >= 0) & clear[None, :]


RULES = {
    "beyond_reads_max": (dataclasses.replace(CAMERA, far_invalid=False), None),
    "unknown_near": (CAMERA, None),
    "sector": (CAMERA, _far_sector),
    "all_witnesses": (CAMERA, _far_all_witnesses),
    "far_mask": (CAMERA, lambda valid, rise, height, cfg: far_mask(valid, rise, height, cfg, jnp)),
}


def _poses(key, params, n: int, tries: int = 8):
    """[n, 3] uniform poses whose robot disc touches nothing (first of `tries` per pose)."""
    k_xy, k_yaw = jax.random.split(key)
    half = params.room_half - ROBOT.radius
    xy = jax.random.uniform(k_xy, (n, tries, 2), minval=-1.0, maxval=1.0) * half
    ok = signed_distance(params, xy) > ROBOT.radius + 0.01  # [n, tries]
    xy = xy[jnp.arange(n), jnp.argmax(ok, -1)]
    # Heading: uniform.
    yaw = jax.random.uniform(k_yaw, (n, 1), minval=-jnp.pi, maxval=jnp.pi)
    return jnp.concatenate([xy, yaw], -1), ok.any(-1)


def _truth(params, rays, cfg: SensorConfig):
    """([S] camera depth of the nearest non-floor surface each sector's rays meet (inf: none),
    [S] bool: that surface is the underside or face of an overhang)."""
    floor = jnp.abs(rays.height + rays.reading * rays.rise) < 1e-3
    depth = jnp.where(floor | ~jnp.isfinite(rays.reading), jnp.inf, rays.reading)
    group = lambda x: (
        x.reshape(cfg.rows, cfg.num_sectors, -1)
        .transpose(1, 0, 2)
        .reshape(  # noqa: E731
            cfg.num_sectors, -1
        )
    )
    depth, slot = group(depth), group(rays.slot)  # [S, rows * k]
    nearest = jnp.take_along_axis(slot, depth.argmin(-1)[:, None], -1)[:, 0]  # [S]
    boxes = params.box_bottom.shape[0]
    hangs = (
        (nearest >= 0)
        & (nearest < boxes)
        & (params.box_bottom[jnp.clip(nearest, 0, boxes - 1)] > 0)
    )
    return depth.min(-1), hangs


def _read(params, qpos, key, rule):
    """([S] observation of the rule, [S] truth, [S] overhang) of one pose."""
    cfg, far = rule
    rays, reading, valid, floor = camera_readings(params, qpos, key, cfg, ROBOT)
    if far is not None:
        mask = far(valid, rays.rise, rays.height, cfg)
        reading, valid = jnp.where(mask, jnp.inf, reading), valid | mask
    return (reduce_sectors(reading, valid, floor, cfg), *_truth(params, rays, cfg))


def _episodes(key, cfg: RandomizeConfig, layouts, rooms: int):
    """`rooms` episodes' `SceneParams` (batched) drawn by `episode.sample`."""
    kinds = [[type(o).__name__ for o in room.obstacles] for room in layouts]
    boxes, cylinders = (max(k.count(kind) for k in kinds) for kind in ("Box", "Cylinder"))
    bank = make_bank(layouts, max(16, boxes), max(4, cylinders))
    draw = jax.vmap(lambda k: episode.sample(k, cfg, bank, ROBOT.radius))
    return draw(jax.random.split(key, rooms))


def _scores(obs, truth, overhang, cfg: SensorConfig) -> dict:
    """The shares of the module doc over sectors obs, truth, overhang [N]."""
    blind, far = truth < cfg.range_min, truth > cfg.range_max
    inside = ~blind & ~far
    share = lambda hit, of: round(float(hit[of].mean()), 5) if of.any() else None  # noqa: E731
    return {
        "blind_sectors": int(blind.sum()),
        "blind_read_far": share(obs >= NEAR, blind),
        "blind_overhang_read_far": share(obs >= NEAR, blind & overhang),
        "blind_other_read_far": share(obs >= NEAR, blind & ~overhang),
        "far_sectors": int(far.sum()),
        "far_read_max": share(obs >= cfg.range_max, far),
        "far_read_near": share(obs <= cfg.range_min, far),
        "in_range_sectors": int(inside.sum()),
        "in_range_off_0_3m": share(np.abs(obs - truth) > 0.3, inside),
    }


def measure(name: str, params, key, poses: int) -> dict:
    """{rule: scores} over `poses` poses in each room of `params`."""
    k_pose, k_obs = jax.random.split(key)
    rooms = params.room_half.shape[0]
    qpos, ok = jax.vmap(lambda k, p: _poses(k, p, poses))(jax.random.split(k_pose, rooms), params)
    keys = jax.random.split(k_obs, (rooms, poses))
    out = {"rooms": rooms, "poses": int(ok.sum())}
    for rule_name, rule in RULES.items():
        per_pose = jax.vmap(lambda p, q, k, r=rule: _read(p, q, k, r), in_axes=(None, 0, 0))
        read = jax.device_get(jax.jit(jax.vmap(per_pose))(params, qpos, keys))
        keep = np.broadcast_to(np.asarray(ok)[..., None], read[0].shape)
        out[rule_name] = _scores(*(x[keep] for x in read), CAMERA)
        print(name, rule_name, out[rule_name])
    return out


def grid_cost(extent: tuple[float, float], envs: int) -> dict:
    """Cells, bytes of the per-env distance field and the time of the goal task's traced grid
    (one `goals.sample_goal` per env, `envs` envs of `long_hall` rooms) covering half extents
    `extent` (long, short)."""
    cfg = RandomizeConfig(sampled_room_prob=1.0, families="long_hall")
    layouts = load_layout(SUITE / "open.json")
    params = _episodes(jax.random.PRNGKey(1), cfg, layouts, envs)
    goal_cells = goals.make_goal_cells(layouts)
    draw = jax.jit(
        jax.vmap(
            lambda k, p: goals.sample_goal(k, p, extent, goal_cells, ROBOT.radius, 0.3, 2.0, 0.1)[2]
        )
    )
    keys = jax.random.split(jax.random.PRNGKey(2), envs)
    start = time.perf_counter()
    jax.block_until_ready(draw(keys, params))
    first = time.perf_counter() - start
    start = time.perf_counter()
    field = jax.block_until_ready(draw(keys, params))
    cells = field.shape[-1] * field.shape[-2]
    return {
        "half_extent_m": list(extent),
        "cells": cells,
        "field_bytes_per_env": cells * 4,
        "first_call_s": round(first, 2),
        "per_env_ms": round(1000 * (time.perf_counter() - start) / envs, 3),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--poses", type=int, default=256, help="poses per room")
    parser.add_argument("--halls", type=int, default=128, help="sampled long_hall rooms")
    parser.add_argument("--grid", action="store_true", help="also the goal grid's cost")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args(argv)
    key = jax.random.PRNGKey(0)
    suite = [room for f in sorted(SUITE.glob("*.json")) for room in load_layout(f)]
    fidelity = RandomizeConfig(**FIDELITY)
    hall = RandomizeConfig(sampled_room_prob=1.0, families="long_hall", **FIDELITY)
    result = {
        "near_m": NEAR,
        "suite": measure("suite", _episodes(key, fidelity, suite, 4 * len(suite)), key, args.poses),
        "long_hall": measure("long_hall", _episodes(key, hall, suite, args.halls), key, args.poses),
    }
    if args.grid:
        square, hall = (goals.GRID_HALF, goals.GRID_HALF), families.LARGE_EXTENTS["long_hall"]
        result["goal_grid"] = [grid_cost(e, 256) for e in (square, hall, (15.25, 15.25))]
        print("goal grid", result["goal_grid"])
    if args.json:
        write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
