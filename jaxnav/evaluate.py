"""`python -m jaxnav.evaluate`: a policy in held-out rooms -> collision-free rate, speed, pictures.

All episodes of all layouts run at once (no sampled rooms): `jax.vmap` over episodes inside one
jitted `jax.lax.scan` over control steps. An episode ends at its first
collision or after `steps` control steps; after that it is frozen (masked), so nothing more is counted.

    python -m jaxnav.evaluate --checkpoint runs/a --layouts scenes/inference_room.json --json out.json
    python -m jaxnav.evaluate --policy forward --episodes 100 --steps 600
    python -m jaxnav.evaluate --checkpoint runs/a --video videos/   # one GIF per layout
    python -m jaxnav.evaluate --policy forward --suite benchmark --episodes 20  # every family
    python -m jaxnav.evaluate --checkpoint runs/a --physics wheeled  # the wheeled validation model
    python -m jaxnav.evaluate --checkpoint runs/a --suite benchmark --randomize.moving-count 1 3

All rooms run in one env and one compiled batch (`make_rollout(..., pinned=True)`): the rooms are
data, so a 32-room suite compiles once. Coverage (`jaxnav.core.families.coverage`) is the share of
a room's reachable free area (0.1 m cells where the robot's disc fits, flood-filled from the spawn)
that the robot's path came within 1.0 m of (straight-line distance), averaged over episodes.

Checked before anything compiles: the flags, the layouts (`load_layouts`: one set of rooms, a goal
task's goals beyond its success radius from the spawn), the memory the batch needs
(`check_memory`) and the space left where the results go. Per-room pictures get safe, distinct
file names (`file_stems`), and names are printed with control characters escaped (`printable`).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import os
import re
import shutil
import stat
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

import jaxnav
from jaxnav.cli import (
    Parser,
    UsageError,
    compile_cache,
    interruptible,
    make_callable,
    print_error,
)
from jaxnav.core import families, goals
from jaxnav.core.assets import scenes_dir
from jaxnav.core.randomize import FIDELITY, RandomizeConfig, SceneParams
from jaxnav.core.scene import PHYSICS, SCENES_DIR, SceneConfig
from jaxnav.io import barn
from jaxnav.io.files import check_writable, read_json, write_atomic
from jaxnav.io.layouts import LayoutError, RoomLayout, check_goal_distance, load_layouts
from jaxnav.policy import BASELINES, Policy
from jaxnav.runconfig import add_field_flags, overrides_from_args
from jaxnav.tasks.registry import make_env, observation_size, task_entry

DEFAULT_LAYOUTS = SCENES_DIR / "inference_room.json"
MAX_TRAJECTORIES = 20  # paths kept per layout for the pictures; more only clutter them
MAX_COUNT = 2**31 - 1  # steps per episode, and episodes in all: 32-bit counters and indices
MAX_FILE_STEM = 80  # characters of a room's name kept in its picture's file name
# Bytes of results per room, to refuse a folder without the space before evaluating (a top-down
# PNG is 50-150 kB, a GIF of 600 steps a few MB).
RESULT_BYTES = {"--json": 2_000, "--plots": 300_000, "--video": 10_000_000}
METRIC_KEYS = (
    "episodes",
    "collision_free_rate",
    "mean_speed",
    "mean_distance",
    "mean_steps",
    "time_to_collision",
    "coverage",
)
GOAL_KEYS = ("success_rate", "spl", "time_to_goal")  # added for tasks with a `success` metric
MOVING_FIELDS = ("moving_count", "moving_speed", "moving_radius", "moving_clearance")
"""The `RandomizeConfig` fields evaluation takes (`--randomize.moving-count` ...): moving
obstacles added to every room."""


@struct.dataclass
class Track:
    """What is counted per episode while it runs. E = episodes."""

    done: (
        jax.Array
    )  # [E] bool: the episode has ended (collision or time limit); frozen from then on
    collided: jax.Array  # [E] bool: it ended with a collision
    steps: jax.Array  # [E] int32, control steps run before it ended
    distance: jax.Array  # [E] float32, path length travelled, m
    xy: jax.Array  # [E, 2] float32, position (the last one before freezing), m
    metrics: dict  # {name: [E] float32}: the task's metrics summed over each episode
    start: jax.Array  # [E, 2] float32, position at the reset, m
    goal: jax.Array  # [E, 2] float32, the episode's goal (goal tasks; else the start), m


@struct.dataclass
class Kept:
    """What a rollout keeps besides the counts. R = rooms (1 unless pinned), K = paths per room."""

    xy: jax.Array  # [R * K, steps + 1, 2] float32, positions of each room's first K episodes, m
    qpos: jax.Array  # [R, steps + 1, 3] float32, x, y, yaw of each room's first episode (not
    # frozen: trim it), m, rad
    params: SceneParams  # [R] each room's first episode's parameters, from its reset


# ------------------------------------------------------------------------------
# Rollouts


def eval_randomize(
    spawn: str = "layout", stochastic_env: bool = True, moving: dict | None = None
) -> RandomizeConfig:
    """Layouts only (no sampled rooms); the layout's spawn or a random free one; `moving`: the
    `MOVING_FIELDS` that add moving obstacles to every room ({"moving_count": (1, 3)}).

    `stochastic_env`: the robot as it really is, drawn per episode from the training ranges and
    the sim-to-real ranges of `randomize.FIDELITY` (traction, speed gain, the Kobuki's velocity
    smoother, command latency, wheel mismatch, depth noise, dark obstacles, camera mount error),
    so episodes from the same spawn differ. Otherwise physics and sensing are exact: commands
    reach the wheels at once, no noise.
    """
    if spawn not in ("layout", "random"):
        raise ValueError(f"spawn: must be 'layout' or 'random', got {spawn!r}")
    unknown = sorted(set(moving or {}) - set(MOVING_FIELDS))
    if unknown:
        raise ValueError(f"moving: unknown fields {unknown}; valid: {', '.join(MOVING_FIELDS)}")
    rooms = dict(sampled_room_prob=0.0, random_spawn_prob=0.0 if spawn == "layout" else 1.0)
    rooms.update(moving or {})
    if stochastic_env:
        return RandomizeConfig(**rooms, **FIDELITY)
    return RandomizeConfig(
        **rooms,
        friction=(1.0, 1.0),
        speed_gain=(1.0, 1.0),
        sensor_noise=(0.0, 0.0),
        sensor_dropout=(0.0, 0.0),
    )


def reset_in(env, key: jax.Array, room: jax.Array):
    """`env.reset(key)` with the room fixed to layout `room` (traced int32) of `env.bank`.

    The env's own draw runs on a one-room bank sliced out of its bank, so the spawn (the layout's
    or a free one) and the physics and sensing come from the same `episode.sample` as training.
    """
    one = jax.tree_util.tree_map(lambda x: jax.lax.dynamic_slice_in_dim(x, room, 1), env.bank)
    pinned = copy.copy(env)  # shares the scene and the compiled model; only the bank differs
    pinned.bank = one
    state = pinned.reset(key)
    params = state.info["params"].replace(layout_id=jnp.asarray(room, jnp.int32))
    return state.replace(info={**state.info, "params": params})


def first_state(env, key, episodes: int, pinned: bool):
    """The batch's reset: E = R * episodes envs, episode e in room e // episodes if `pinned`."""
    rooms = env.bank.size if pinned else 1
    keys = jax.random.split(key, rooms * episodes)
    if not pinned:
        return jax.vmap(env.reset)(keys)
    room = jnp.repeat(jnp.arange(rooms, dtype=jnp.int32), episodes)  # [E]
    return jax.vmap(lambda k, r: reset_in(env, k, r))(keys, room)


def make_rollout(env, act, episodes, steps, keep=MAX_TRAJECTORIES, *, pinned=False):
    """A jitted `rollout(key) -> (Track, Kept)`.

    `pinned`: `episodes` episodes in every layout of the env's bank (E = R * episodes, episode e
    in layout e // episodes), all in one compiled batch; otherwise `episodes` episodes drawn by
    the env's own randomisation (R = 1). `keep` paths per room are kept.
    """
    step = jax.vmap(env.step)
    rooms = env.bank.size if pinned else 1
    keep = min(keep, episodes)
    kept = (jnp.arange(rooms)[:, None] * episodes + jnp.arange(keep)).reshape(-1)  # [R * K]
    firsts = jnp.arange(rooms) * episodes  # [R]

    def body(carry, key):
        state, track = carry
        nxt = step(state, act(state.obs, key))  # act: obs [E, D] -> actions [E]
        live = ~track.done  # [E]; only episodes still running count this step
        xy = nxt.data.qpos[:, :2]  # [E, 2]
        moved = jnp.linalg.norm(xy - track.xy, axis=-1)  # [E] m
        track = Track(
            done=track.done | nxt.done,
            collided=track.collided | (live & (nxt.metrics["collision"] > 0)),
            steps=track.steps + live.astype(jnp.int32),
            distance=track.distance + jnp.where(live, moved, 0.0),
            xy=jnp.where(live[:, None], xy, track.xy),
            metrics={k: v + jnp.where(live, nxt.metrics[k], 0.0) for k, v in track.metrics.items()},
            start=track.start,
            goal=track.goal,
        )
        return (nxt, track), (track.xy[kept], nxt.data.qpos[firsts, :3])

    def rollout(key):
        k_reset, k_act = jax.random.split(key)
        state = first_state(env, k_reset, episodes, pinned)
        n = rooms * episodes
        xy0 = state.data.qpos[:, :2]  # [E, 2]
        false, zero = jnp.zeros(n, bool), jnp.zeros(n)
        sums = {k: zero for k in env.metric_names if k != "collision"}
        goal = state.info.get("goal", xy0)  # [E, 2]
        track = Track(false, false, jnp.zeros(n, jnp.int32), zero, xy0, sums, xy0, goal)
        keys = jax.random.split(k_act, steps)
        (_, track), (path, qpos) = jax.lax.scan(body, (state, track), keys)  # [steps, R * K, 2]
        path = jnp.concatenate([xy0[None, kept], path])  # [steps + 1, R * K, 2]
        qpos = jnp.concatenate([state.data.qpos[None, firsts, :3], qpos])  # [steps + 1, R, 3]
        first = jax.tree_util.tree_map(lambda x: x[firsts], state.info["params"])
        return track, Kept(xy=jnp.swapaxes(path, 0, 1), qpos=jnp.swapaxes(qpos, 0, 1), params=first)

    return jax.jit(rollout)


def metrics(
    collided, steps_run, distance, control_period, task_metrics=None, cover=None, spl=None
) -> dict:
    """Summary of per-episode arrays [N]: rates in [0, 1], speeds m/s, distances m, times s, and
    the mean over episodes of each task metric's episode sum (`task_metrics`: {name: [N]}).

    `control_period` (s) is a float or one per episode [N]. `cover` [N] is each episode's
    coverage (`jaxnav.core.families.coverage`). `time_to_collision` is the mean time to the first
    collision of the episodes that collided, and the longest episode's time when none did.
    Goal tasks (a `success` task metric, and `spl` [N], see `spl_values`) add `success_rate`,
    `spl` and `time_to_goal`: the mean time of the successful episodes, and the longest
    episode's time when none succeeded.
    """
    steps_run = np.asarray(steps_run, np.float64)
    distance = np.asarray(distance, np.float64)
    collided = np.asarray(collided, bool)
    seconds = steps_run * control_period  # [N]
    # Speed over the steps each episode actually ran, so early collisions do not dilute it.
    speed = distance / (np.maximum(steps_run, 1) * control_period)
    out = {
        "episodes": int(len(steps_run)),
        "collision_free_rate": float(1.0 - np.mean(collided)),
        "mean_speed": float(np.mean(speed)),
        "mean_distance": float(np.mean(distance)),
        "mean_steps": float(np.mean(steps_run)),
        "time_to_collision": float(
            np.mean(seconds[collided]) if collided.any() else np.max(seconds)
        ),
        **{k: float(np.mean(v)) for k, v in (task_metrics or {}).items()},
    }
    if cover is not None:
        out["coverage"] = float(np.mean(cover))
    if spl is not None:
        success = np.asarray(task_metrics["success"]) > 0
        out["success_rate"] = float(np.mean(success))
        out["spl"] = float(np.mean(spl))
        out["time_to_goal"] = float(np.mean(seconds[success]) if success.any() else np.max(seconds))
    return out


def spl_values(layout: RoomLayout, track_room: dict, radius: float, success_radius: float):
    """[N] success weighted by path length per episode (Anderson et al., 2018): S l / max(p, l),
    with p the path the robot drove and l the shortest path that reaches the goal: the shortest
    path from the start to the goal on the room's occupancy grid (`goals.shortest_paths`: 0.1 m
    cells, obstacles inflated by the robot radius, 8-connected) less the success radius (stricter
    than taking the path to the goal's centre, which lets every successful path be that much
    shorter than l)."""
    shortest = goals.shortest_paths(layout, track_room["start"], track_room["goal"], radius)
    return spl_from(shortest - success_radius, track_room)


def spl_from(reach: np.ndarray, track_room: dict) -> np.ndarray:
    """[N] S l / max(p, l) for shortest paths l = `reach` [N] (m) and the episodes' successes and
    driven distances p of `track_room` (0 where l is not finite)."""
    success = np.asarray(track_room["metrics"]["success"]) > 0
    driven = np.asarray(track_room["distance"], np.float64)
    reach = np.maximum(reach, 0.0)
    ratio = np.where(success, reach / np.maximum(np.maximum(driven, reach), 1e-9), 0.0)
    return np.where(np.isfinite(ratio), ratio, 0.0)


def make_eval_env(policy: Policy, layouts, *, steps: int, randomize, physics: str | None = None):
    """The env of evaluation: the policy's training settings (task, sensor, scene, robot) in
    `layouts` with evaluation's own randomisation and time limit (`steps`), and `physics`
    ("fast" or "wheeled", `SceneConfig.physics`) instead of the policy's own if given."""
    kwargs = {k: v for k, v in policy.env_kwargs.items() if k not in ("layouts", "randomize")}
    if physics is not None:
        scene = kwargs.get("scene") or SceneConfig()
        kwargs["scene"] = dataclasses.replace(scene, physics=physics)
    return make_env(policy.env, layouts=layouts, randomize=randomize, max_steps=steps, **kwargs)


def evaluate_rooms(
    policy: Policy, layouts, key, *, episodes, steps, randomize, physics=None
) -> list[dict]:
    """All layouts in one env and one compiled batch -> per room: its per-episode arrays (numpy)
    and what `evaluate` keeps for pictures (`paths`, `collided`, `qpos`, `params`, `env`)."""
    env = make_eval_env(policy, layouts, steps=steps, randomize=randomize, physics=physics)
    check_memory(env, episodes, steps)
    rollout = make_rollout(env, policy.act, episodes, steps, keep=episodes, pinned=True)
    track, kept = interruptible(lambda: jax.device_get(rollout(key)))  # Ctrl-C acts at once
    with_goals = "success" in env.metric_names
    out = []
    for r, layout in enumerate(layouts):
        room = slice(r * episodes, (r + 1) * episodes)
        per_episode = {
            "collided": track.collided[room],
            "steps": track.steps[room],
            "distance": track.distance[room],
            "start": track.start[room],
            "goal": track.goal[room],
            "metrics": {k: v[room] for k, v in track.metrics.items()},
        }
        # Trim each path after its episode ended: [steps_run + 1, 2].
        paths = [
            np.asarray(p[: n + 1]) for p, n in zip(kept.xy[room], track.steps[room], strict=True)
        ]
        params = jax.tree_util.tree_map(lambda x, r=r: x[r], kept.params)
        if with_goals:
            per_episode["spl"] = spl_values(
                layout, per_episode, env.robot.radius, env.task.success_radius
            )
        out.append(
            {
                **per_episode,
                "control_period": env.control_period,
                "coverage": families.coverage(layout, paths),
                "paths": paths[:MAX_TRAJECTORIES],
                "qpos": np.asarray(kept.qpos[r, : track.steps[room][0] + 1]),  # [T_0 + 1, 3]
                "params": params,
                "env": env,
            }
        )
    return out


def _available_memory() -> tuple[int | None, str]:
    """(bytes the batch may use, where): MemAvailable on the CPU, else the first accelerator's
    `bytes_limit`; None where neither is known."""
    device = jax.local_devices()[0]
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        return stats.get("bytes_limit"), f"memory of one {device.device_kind}"
    try:
        with open("/proc/meminfo") as fh:
            kb = next(int(line.split()[1]) for line in fh if line.startswith("MemAvailable:"))
    except (OSError, ValueError, IndexError, StopIteration):
        return None, ""
    return kb * 1024, "free CPU memory (MemAvailable)"


def check_memory(env, episodes: int, steps: int) -> None:
    """Refuses, before it compiles, a batch (`episodes` in every room of `env`'s bank, `steps`
    long) that cannot fit in memory. Per episode: its state three times (the carry, the next one
    and the step's intermediates; shapes from `jax.eval_shape`, nothing allocated) and its path,
    [steps + 1, 2] float32 on the device and again on the host; and one PRNG key per step."""
    available, where = _available_memory()
    if available is None:
        return
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    state_bytes = sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(state))
    per_episode = 3 * state_bytes + 2 * 8 * (steps + 1)
    rooms, keys = env.bank.size, 8 * steps
    need = rooms * episodes * per_episode + keys
    if need <= available:
        return
    fit = int((available - keys) // (rooms * per_episode))
    hint = (
        f"at {steps:,} steps about {fit:,} episodes per room fit"
        if fit >= 1
        else f"not even 1 episode per room of {steps:,} steps fits: fewer steps"
    )
    raise ValueError(
        f"episodes {episodes:,} x {rooms} room(s) x steps {steps:,}: needs about "
        f"{_size(need)} ({_size(per_episode)} per episode), but the {where} is "
        f"{_size(available)}; {hint}"
    )


def _size(n: float) -> str:
    """A byte count for people: 8.8 kB, 880.2 GB."""
    units = {"TB": 1e12, "GB": 1e9, "MB": 1e6}
    unit = next((u for u, size in units.items() if n >= size), "kB")
    return f"{n / units.get(unit, 1e3):.1f} {unit}"


SUITE_META = "suite.json"  # in a suite's folder: its own data (e.g. BARN's optimal paths)


def load_suite(name: str) -> dict[str, list[RoomLayout]]:
    """The rooms of suite `name` (a folder of jaxnav's scenes, e.g. "benchmark"): {family: rooms},
    one family per JSON file (but `SUITE_META`), in file-name order."""
    folder = scenes_dir() / name
    files = sorted(f for f in folder.glob("*.json") if f.name != SUITE_META)
    files = files if folder.is_dir() else []
    if not files:
        suites = sorted(
            p.name for p in scenes_dir().iterdir() if p.is_dir() and any(p.glob("*.json"))
        )
        raise FileNotFoundError(f"no suite {name!r} in {scenes_dir()}; suites: {', '.join(suites)}")
    return {f.stem: jaxnav.load_layout(f) for f in files}


def suite_meta(name: str) -> dict:
    """A suite's `SUITE_META` ({} if it has none): `{"score": "barn", "time_limit_s": s,
    "rooms": {room: {"optimal_path_m": m, ...}}}` for BARN."""
    path = scenes_dir() / name / SUITE_META
    return read_json(path) if path.is_file() else {}


def default_steps(suite: str | None, policy: Policy) -> int:
    """Control steps per episode when none are given: the suite's time limit (`SUITE_META`'s
    `time_limit_s`), else 600 (60 s)."""
    limit = suite_meta(suite).get("time_limit_s") if suite else None
    if limit is None:
        return 600
    period = (policy.env_kwargs.get("scene") or SceneConfig()).control_period
    return round(limit / period)


def barn_scores(rooms: list[dict], names: list[str], meta: dict, top_speed: float) -> list[dict]:
    """Per room, BARN's score (`jaxnav.io.barn.barn_score`) of every episode [N]: `barn_score`
    with the challenge's optimal time (the optimal path at 2 m/s), `barn_score_own_speed` with
    the optimal path at `top_speed` (the robot's), and `timeout` (neither success nor collision)."""
    out = []
    for room, name in zip(rooms, names, strict=True):
        length = meta["rooms"][name]["optimal_path_m"]
        success = np.asarray(room["metrics"]["success"]) > 0
        seconds = np.asarray(room["steps"], np.float64) * room["control_period"]
        out.append(
            {
                "barn_score": barn.barn_score(success, seconds, barn.optimal_time(length)),
                "barn_score_own_speed": barn.barn_score(success, seconds, length / top_speed),
                "timeout": ~success & ~np.asarray(room["collided"], bool),
            }
        )
    return out


def _mean_scores(scores: list[dict]) -> dict:
    """The BARN scores and timeout share pooled over the episodes of `scores`' rooms."""
    keys = ("barn_score", "barn_score_own_speed", "timeout")
    pooled = {k: float(np.mean(np.concatenate([s[k] for s in scores]))) for k in keys}
    pooled["timeout_rate"] = pooled.pop("timeout")
    return pooled


def barn_line(results: dict) -> str:
    """BARN's scores per difficulty group and overall, one line."""
    own = results["barn"]["own_speed"]
    parts = [
        f"{name} {m['barn_score']:.3f} ({m['barn_score_own_speed']:.3f} at {own:g} m/s)"
        for name, m in [*results["families"].items(), ("overall", results["overall"])]
    ]
    return "BARN score (optimal path at 2 m/s): " + ", ".join(parts)


def _add_barn(results: dict, rooms, names, groups: dict, meta: dict) -> None:
    """BARN's metrics into `results`: per room, per family (difficulty group) and overall."""
    top_speed = rooms[0]["env"].robot.max_linear_speed
    scores = barn_scores(rooms, names, meta, top_speed)
    for name, s in zip(names, scores, strict=True):
        results["layouts"][name].update(_mean_scores([s]))
        results["layouts"][name]["difficulty_rank"] = meta["rooms"][name].get("difficulty_rank")
    sizes = np.cumsum([0] + [len(v) for v in groups.values()])
    for family, a, b in zip(groups, sizes[:-1], sizes[1:], strict=True):
        results["families"][family].update(_mean_scores(scores[a:b]))
    results["overall"].update(_mean_scores(scores))
    results["barn"] = {"optimal_speed": barn.OPTIMAL_SPEED, "own_speed": top_speed}


def pool(rooms: list[dict]) -> dict:
    """Metrics pooled over all episodes of `rooms` (speed uses each room's control period); the
    twin pools its rooms with it too."""
    cat = lambda k: np.concatenate([e[k] for e in rooms])  # noqa: E731
    periods = np.concatenate([np.full(len(e["steps"]), e["control_period"]) for e in rooms])
    task = {k: np.concatenate([e["metrics"][k] for e in rooms]) for k in rooms[0]["metrics"]}
    spl = cat("spl") if "spl" in rooms[0] else None
    return metrics(
        cat("collided"), cat("steps"), cat("distance"), periods, task, cat("coverage"), spl
    )


def evaluate(
    policy: Policy,
    layouts: list[RoomLayout] | None = None,
    *,
    suite: str | None = None,
    episodes: int = 100,
    steps: int = 600,
    seed: int = 0,
    spawn: str = "layout",
    stochastic_env: bool = True,
    physics: str | None = None,
    moving: dict | None = None,
) -> dict:
    """Runs `episodes` episodes of at most `steps` control steps in each layout (or each room of
    `suite`, see `load_suite`), all rooms in one compiled batch.

    Returns `{"layouts": {name: metrics}, "overall": metrics, "policy", "steps", "seed",
    "_trajectories": {name: {"paths": [[T_i + 1, 2] arrays], "collided": [bool], "qpos",
    "params", "env"}}}`, and with a suite also `"suite"` and `"families": {family: metrics}`
    (pooled over its rooms). Metrics are `METRIC_KEYS` (see `metrics`); at most
    `MAX_TRAJECTORIES` paths per layout are kept; `qpos` [T_0 + 1, 3] (x, y, yaw) and `params`
    (SceneParams) are the first episode's, and `env` the env of the batch, for `jaxnav.viz.render`.
    `_trajectories` is for pictures; `strip_private` removes it before writing JSON.
    `physics` ("fast" or "wheeled") replaces the policy's own `SceneConfig.physics`; the results
    name the one used under `"physics"`. `moving` adds moving obstacles to every room (the
    `RandomizeConfig` fields of `MOVING_FIELDS`, e.g. {"moving_count": (1, 3)}); the results
    then give them under `"moving"`.
    """
    for name, value in (("episodes", episodes), ("steps", steps)):
        if not 1 <= value <= MAX_COUNT:
            raise ValueError(f"{name}: must be 1 to {MAX_COUNT:,}, got {value:,}")
    if (layouts is None) == (suite is None):
        raise ValueError("layouts, suite: give exactly one of them")
    groups = load_suite(suite) if suite is not None else {}
    layouts = [room for rooms in groups.values() for room in rooms] if suite else list(layouts)
    if not layouts:
        raise ValueError("layouts: need at least one layout")
    if len(layouts) * episodes > MAX_COUNT:
        raise ValueError(
            f"episodes: {episodes:,} in each of {len(layouts)} rooms is more than {MAX_COUNT:,} "
            "in one batch"
        )
    radius = success_radius(policy)
    if radius is not None:  # a goal task: a goal on the fixed spawn would measure nothing
        for layout in layouts:
            check_goal_distance(layout, radius)
    randomize = eval_randomize(spawn, stochastic_env, moving)
    rooms = evaluate_rooms(
        policy,
        layouts,
        jax.random.PRNGKey(seed),
        episodes=episodes,
        steps=steps,
        randomize=randomize,
        physics=physics,
    )
    names = unique_names(layouts)
    per_layout = {name: pool([room]) for name, room in zip(names, rooms, strict=True)}
    for name, m in per_layout.items():
        _check_finite(m, name)
    keys = ("paths", "collided", "qpos", "params", "env")
    trajectories = {
        name: {
            **{k: room[k] for k in keys},
            "collided": room["collided"][:MAX_TRAJECTORIES].tolist(),
            "goals": room["goal"][:MAX_TRAJECTORIES] if "spl" in room else None,
        }
        for name, room in zip(names, rooms, strict=True)
    }
    results = {
        "layouts": per_layout,
        "overall": pool(rooms),
        "policy": policy.name,
        "physics": rooms[0]["env"].scene.cfg.physics,
        "steps": steps,
        "seed": seed,
        "_trajectories": trajectories,
    }
    if randomize.moving_count[1]:
        results["moving"] = {k: getattr(randomize, k) for k in MOVING_FIELDS}
    if suite is not None:
        sizes = np.cumsum([0] + [len(v) for v in groups.values()])
        results["suite"] = suite
        results["families"] = {
            f: pool(rooms[a:b]) for f, a, b in zip(groups, sizes[:-1], sizes[1:], strict=True)
        }
        results["_families"] = {f: names[a] for f, a in zip(groups, sizes[:-1], strict=False)}
        meta = suite_meta(suite)
        if meta.get("score") == "barn" and "success" in rooms[0]["metrics"]:
            _add_barn(results, rooms, names, groups, meta)
    return results


class NotFinite(ValueError):
    """A metric of a room came out NaN or infinite: the simulation of that room failed."""


def _check_finite(room_metrics: dict, name: str) -> None:
    """No NaN or Inf is ever reported as a result (NotFinite names the room and the metric)."""
    bad = [k for k, v in room_metrics.items() if not np.isfinite(v)]
    if bad:
        raise NotFinite(
            f"room {name!r}: {bad[0]} is {room_metrics[bad[0]]} (the simulation diverged in this "
            "room); no results written"
        )


def success_radius(policy: Policy) -> float | None:
    """The success radius (m) of the policy's task, None for tasks without goals."""
    task = policy.env_kwargs.get("task") or task_entry(policy.env).config_cls()
    return getattr(task, "success_radius", None)


def unique_names(layouts: list[RoomLayout]) -> list[str]:
    """Layout names, with `-2`, `-3`... added where two files use the same name."""
    seen: dict[str, int] = {}
    names = []
    for layout in layouts:
        seen[layout.name] = seen.get(layout.name, 0) + 1
        names.append(
            layout.name if seen[layout.name] == 1 else f"{layout.name}-{seen[layout.name]}"
        )
    return names


def strip_private(results: dict) -> dict:
    """The results without `_`-prefixed keys (trajectories): what goes into the JSON."""
    return {k: v for k, v in results.items() if not k.startswith("_")}


# ------------------------------------------------------------------------------
# Command line


def build_parser() -> argparse.ArgumentParser:
    """The CLI flags."""
    p = Parser(prog="python -m jaxnav.evaluate", description=__doc__.splitlines()[0])
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument(
        "--checkpoint", metavar="DIR", help="a training run folder or a checkpoint in it"
    )
    who.add_argument(
        "--policy", choices=sorted(BASELINES), help="a baseline instead of a checkpoint"
    )
    rooms = p.add_mutually_exclusive_group()
    rooms.add_argument(
        "--layouts",
        nargs="+",
        metavar="FILE",
        help="layout files, each a room or a list of rooms (default: scenes/inference_room.json)",
    )
    rooms.add_argument(
        "--suite",
        metavar="NAME",
        help="a suite of jaxnav's scenes (benchmark: rooms of every family, per-family metrics)",
    )
    p.add_argument(
        "--env",
        help="the task of a --policy baseline (default avoid; a checkpoint brings its own)",
    )
    p.add_argument("--episodes", type=int, default=100, help="episodes per layout (default 100)")
    p.add_argument(
        "--steps",
        type=int,
        help="control steps per episode (default 600, or the suite's time limit: BARN's 100 s)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--spawn",
        choices=("layout", "random"),
        default="layout",
        help="the layout's spawn pose, or a random free pose per episode",
    )
    p.add_argument(
        "--deterministic-env",
        action="store_true",
        help="exact physics and sensing: no randomised traction, gains, smoother, latency or noise",
    )
    p.add_argument(
        "--physics",
        choices=PHYSICS,
        help="the robot's physics: fast (the training default) or wheeled (the validation model: "
        "driven wheels, castors, friction contacts; about 18x slower); default: the policy's own",
    )
    moving = p.add_argument_group("moving obstacles (added to every room; default: none)")
    add_field_flags(moving, "randomize", RandomizeConfig, "randomize.", MOVING_FIELDS)
    p.add_argument("--json", metavar="OUT", help="write the metrics here")
    p.add_argument(
        "--plots",
        metavar="DIR",
        help="top-down PNGs, one per layout (default: beside --json, else RUN/eval for a "
        "--checkpoint; a baseline without either writes none)",
    )
    p.add_argument(
        "--no-compile-cache",
        action="store_true",
        help="compile anew (default: reuse compiled programs of earlier runs, ~/.cache/jaxnav/xla)",
    )
    p.add_argument(
        "--video",
        metavar="DIR",
        help="an animated GIF of the first episode per layout (needs OpenGL: EGL or OSMesa)",
    )
    return p


def _check_args(args) -> None:
    """Cheap checks before anything is loaded or compiled."""
    if args.episodes < 1:
        raise UsageError(f"--episodes: must be >= 1, got {args.episodes}")
    if args.steps is not None and args.steps < 1:
        raise UsageError(f"--steps: must be >= 1, got {args.steps}")
    for flag, value in (("--episodes", args.episodes), ("--steps", args.steps or 1)):
        if value > MAX_COUNT:
            raise UsageError(f"{flag}: at most {MAX_COUNT:,} (a 32-bit count), got {value:,}")
    if args.checkpoint is not None and _kind(args.checkpoint, "--checkpoint") != "folder":
        raise UsageError(f"--checkpoint: no such directory: {args.checkpoint}")
    for flag, value in (("--plots", args.plots), ("--video", args.video)):
        if value is not None and _kind(value, flag) not in (None, "folder"):
            raise UsageError(f"{flag}: not a directory: {value}")
    if args.json is not None and _kind(args.json, "--json") == "folder":
        raise UsageError(f"--json: {args.json} is a directory, expected a file name")


def _kind(path: str, flag: str) -> str | None:
    """What `path` is: "folder", "file" (anything else) or None (missing); one that cannot be
    looked at (a folder without permission on the way) is a UsageError naming `flag`."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as err:
        raise UsageError(f"{flag} {path}: cannot access ({err.strerror or err})") from None
    return "folder" if stat.S_ISDIR(mode) else "file"


def _check_outputs(args, rooms: int) -> None:
    """Every folder the results go to can be written and has space for the results of `rooms`
    rooms, before minutes of evaluation."""
    folders = {"--json": (Path(args.json).parent, rooms + 1)} if args.json else {}
    if _plots_dir(args) is not None:
        folders["--plots"] = (_plots_dir(args), rooms)
    if args.video:
        folders["--video"] = (Path(args.video), rooms)
    for flag, (folder, count) in folders.items():
        check_writable(folder, flag)
        free, need = shutil.disk_usage(folder).free, RESULT_BYTES[flag] * count
        if free < need:
            raise UsageError(
                f"{flag} {folder}: {_size(free)} free, the results need about {_size(need)}"
            )


def _load_policy(args) -> Policy:
    if args.policy is not None:
        return baseline(args.policy, args.env or "avoid")
    if args.env is not None:
        raise UsageError("--env: only with --policy (a checkpoint evaluates its own task)")
    from flax.errors import FlaxError

    from jaxnav.io.checkpoint import CheckpointError
    from jaxnav.runs import load_policy  # lazy: only checkpoints need it

    try:
        policy = load_policy(args.checkpoint)
    except CheckpointError as err:  # its message names the file; add the flag
        raise UsageError(f"--checkpoint: {err}") from None
    except OSError as err:  # a folder inside it without permission
        where = err.filename or args.checkpoint
        raise UsageError(f"--checkpoint: {where}: cannot read ({err.strerror or err})") from None
    # The weights must fit the network that the checkpoint's config.json describes; tracing one
    # call (no compile) says so now, instead of a traceback from inside the jitted rollout.
    size = observation_size(policy.env_kwargs["task"], policy.env_kwargs["sensor"])
    obs = jax.ShapeDtypeStruct((1, size), jnp.float32)
    try:
        jax.eval_shape(policy.act, obs, jax.random.PRNGKey(0))
    except FlaxError as err:
        detail = str(err).split(" (https://")[0]
        raise UsageError(
            f"--checkpoint: {args.checkpoint}: policy.msgpack does not fit the network of its "
            f"config.json ({detail})"
        ) from None
    return policy


def baseline(name: str, env: str = "avoid") -> Policy:
    """Baseline `name` (forward, random) acting in task `env` with its default actions."""
    try:
        spec = task_entry(env).config_cls().action_spec
    except ValueError as err:
        raise UsageError(f"--env: {err}") from None
    return dataclasses.replace(BASELINES[name](spec), env=env)


def _plots_dir(args) -> Path | None:
    """--plots, else beside --json, else `eval/` in the checkpoint's run folder; None (no
    pictures) for a baseline given neither: nothing is written where the user did not ask."""
    if args.plots:
        return Path(args.plots)
    if args.json:
        return Path(args.json).parent
    if args.checkpoint:
        return Path(args.checkpoint) / "eval"
    return None


def file_stems(names: list[str]) -> list[str]:
    """Distinct, safe file names (without suffix) for room `names`: characters other than
    letters, digits, `.`, `_` and `-` become `_`, at most MAX_FILE_STEM of them, no leading dot;
    a name that would repeat an earlier one (case aside, as some file systems see it) gets `-`
    and a short hash of the room's full name, then `-2`, `-3`... if it still does."""
    out, taken = [], set()
    for name in names:
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", name).lstrip(".")[:MAX_FILE_STEM] or "room"
        if stem.lower() in taken:
            stem = f"{stem}-{hashlib.sha256(name.encode()).hexdigest()[:8]}"
        unique, k = stem, 2
        while unique.lower() in taken:
            unique, k = f"{stem}-{k}", k + 1
        taken.add(unique.lower())
        out.append(unique)
    return out


def printable(name: str) -> str:
    """`name` with control characters (newlines, terminal escapes) written as escapes (`\\n`,
    `\\x1b`), so a room name can neither break a table's rows nor drive the terminal."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in name)


def _listing(folder: Path, files: list[str]) -> str:
    """`folder/ (N PNG: a.png, b.png, ...)`: the names of the files written there."""
    kinds = ", ".join(sorted({f.rsplit(".", 1)[-1].upper() for f in files}))
    shown = ", ".join(files[:8]) + (f", ... ({len(files)} in all)" if len(files) > 8 else "")
    return f"{folder}/ ({len(files)} {kinds}: {shown})"


def format_table(results: dict) -> str:
    """The metrics as a text table: one row per layout, per family (suites) and `overall`."""
    head = f"{'layout':<24} {'episodes':>8} {'collision-free %':>16} {'speed m/s':>9} "
    head += f"{'distance m':>10} {'steps':>7} {'coverage %':>10}"
    goal = "spl" in results["overall"]
    if goal:
        head += f" {'success %':>9} {'SPL':>5}"
    families_ = [(f"family {k}", m) for k, m in results.get("families", {}).items()]
    rows = [*results["layouts"].items(), *families_, ("overall", results["overall"])]
    lines = [head, "-" * len(head)]
    for name, m in rows:
        lines.append(
            f"{printable(name)[:24]:<24} {m['episodes']:>8d} "
            f"{100 * m['collision_free_rate']:>16.1f} "
            f"{m['mean_speed']:>9.3f} {m['mean_distance']:>10.2f} {m['mean_steps']:>7.1f} "
            f"{100 * m['coverage']:>10.1f}"
            + (f" {100 * m['success_rate']:>9.1f} {m['spl']:>5.2f}" if goal else "")
        )
    return "\n".join(lines)


def _write_outputs(args, results: dict, layouts: list[RoomLayout]) -> None:
    """The JSON (if asked) and one top-down PNG per layout."""
    from jaxnav.viz.plots import plot_trajectories  # lazy: matplotlib is slow to import

    if args.json:
        text = json.dumps(strip_private(results), indent=2, allow_nan=False) + "\n"
        try:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            write_atomic(args.json, text)
        except OSError as err:
            raise UsageError(f"--json: cannot write {args.json} ({err.strerror or err})") from None
        print(f"metrics: {args.json}")
    out = _plots_dir(args)
    if out is None:
        print("plots: none (give --plots DIR or --json FILE for top-down pictures)")
        return
    _make_dir(out, "--plots")
    # A suite: one picture per family (its first room); otherwise one per layout.
    by_name = dict(zip(results["_trajectories"], layouts, strict=True))
    shown = results.get("_families") or {name: name for name in by_name}
    files = [f"{stem}.png" for stem in file_stems(list(shown))]
    for name, file in zip(shown.values(), files, strict=True):
        traj, m = results["_trajectories"][name], results["layouts"][name]
        plot_trajectories(
            by_name[name],
            traj["paths"],
            traj["collided"],
            out / file,
            _title(printable(name), results["policy"], m),
            goals=traj["goals"],
            movers=traj["params"],
        )
    print(f"plots: {_listing(out, files)}")


def _title(name: str, policy: str, m: dict) -> str:
    """A room's picture's title: its name, the policy and its main metrics."""
    if "spl" in m:
        return (
            f"{name}: {policy}, {100 * m['success_rate']:.0f}% success, "
            f"SPL {m['spl']:.2f} ({m['episodes']} episodes)"
        )
    return (
        f"{name}: {policy}, {100 * m['collision_free_rate']:.0f}% collision-free, "
        f"coverage {100 * m['coverage']:.0f}% ({m['episodes']} episodes)"
    )


def _make_dir(path: Path, flag: str) -> None:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"{flag}: cannot create {path} ({err.strerror or err})") from None


def _write_videos(args, results: dict, layouts: list[RoomLayout]) -> None:
    """One GIF of the first episode per layout; without OpenGL, that episode as a top-down PNG."""
    from jaxnav.viz import render  # lazy: only --video needs it

    out = Path(args.video)
    _make_dir(out, "--video")
    items = list(zip(results["_trajectories"].items(), layouts, strict=True))
    stems = file_stems(list(results["_trajectories"]))
    try:
        for ((name, traj), layout), stem in zip(items, stems, strict=True):
            outcome = "collision" if traj["collided"][0] else "no collision"
            title = f"{printable(name)}: {results['policy']}, episode 1 ({outcome})"
            render.render_episode(
                traj["env"],
                traj["params"],
                traj["qpos"],
                out / f"{stem}.gif",
                wall_height=layout.wall_height,
                title=title,
            )
    except render.NoGLError:
        from jaxnav.viz.plots import plot_trajectories

        print(f"video: no OpenGL backend ({render.GL_HINT}); top-down PNGs written instead")
        for ((_, traj), layout), stem in zip(items, stems, strict=True):
            path = out / f"{stem}.png"
            plot_trajectories(layout, [traj["qpos"][:, :2]], traj["collided"][:1], path)
        print(f"video: {_listing(out, [f'{stem}.png' for stem in stems])}")
        return
    gifs = [f"{stem}.gif" for stem in stems]
    print(f"video: {_listing(out, gifs)}, OpenGL via {render.gl_backend()}")


def _rooms(args, policy: Policy) -> tuple[list[RoomLayout], str | None]:
    """The layouts of --layouts (default: the inference room) or of --suite, and the suite."""
    if args.suite is not None:
        try:
            return [r for rooms in load_suite(args.suite).values() for r in rooms], args.suite
        except FileNotFoundError as err:
            raise UsageError(f"--suite: {err}") from None
    try:
        paths = args.layouts or [str(DEFAULT_LAYOUTS)]
        return load_layouts(paths, success_radius=success_radius(policy)), None
    except LayoutError as err:  # its message names the file, room and field; add the flag
        raise UsageError(f"--layouts: {err}") from None


def _run(argv) -> None:
    args = build_parser().parse_args(argv)
    _check_args(args)
    compile_cache(not args.no_compile_cache)
    policy = _load_policy(args)
    layouts, suite = _rooms(args, policy)
    _check_outputs(args, len(layouts))
    results = evaluate(
        policy,
        None if suite else layouts,
        suite=suite,
        episodes=args.episodes,
        steps=args.steps or default_steps(args.suite, policy),
        seed=args.seed,
        spawn=args.spawn,
        stochastic_env=not args.deterministic_env,
        physics=args.physics,
        moving=overrides_from_args(args)["randomize"],
    )
    print(format_table(results))
    if "barn" in results:
        print(barn_line(results))
    _write_outputs(args, results, layouts)
    if args.video:
        _write_videos(args, results, layouts)


def main(argv=None) -> int:
    """`python -m jaxnav.evaluate`; returns the exit code (2 for user mistakes)."""
    try:
        _run(argv)
    except NotFinite as err:
        print_error(err)
        return 1
    except (UsageError, LayoutError, FileNotFoundError, ValueError) as err:
        print_error(err)
        return 2
    except OSError as err:  # a write that failed after the checks (disk full)
        print_error(f"{err.filename or 'output'}: cannot write ({err.strerror or err})")
        return 1
    return 0


make_callable(__name__, evaluate)

if __name__ == "__main__":
    sys.exit(main())
