"""Evaluation as a library: a policy in held-out rooms -> collision-free rate, speed, coverage and
what the task declares (`NavTask.eval_metrics`: the goal task's success rate, SPL, time to goal).
`evaluate(...)` is the Python API (`jaxnav.evaluate`); `python -m jaxnav.evaluate` is its command
line (`jaxnav.cli.evaluate`).

All episodes of all layouts run at once (no sampled rooms): `jax.vmap` over episodes inside one
jitted `jax.lax.scan` over control steps. An episode ends at its first
collision or after `steps` control steps; after that it is frozen (masked), so nothing more is counted.

All rooms run in one env and one compiled batch (`make_rollout(..., pinned=True)`): the rooms are
data, so a 32-room suite compiles once. Coverage (`jaxnav.core.families.coverage`) is the share of
a room's reachable free area (0.1 m cells where the robot's disc fits, flood-filled from the spawn)
that the robot's path came within 1.0 m of (straight-line distance), averaged over episodes.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import re

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

import jaxnav
from jaxnav.core import families
from jaxnav.core.assets import scenes_dir
from jaxnav.core.randomize import FIDELITY, RandomizeConfig, SceneParams
from jaxnav.core.scene import SceneConfig
from jaxnav.core.xla import compiler_options
from jaxnav.io import barn
from jaxnav.io.files import read_json
from jaxnav.io.layouts import RoomLayout, check_goal_distance
from jaxnav.policy import BASELINES, Policy
from jaxnav.process import interruptible
from jaxnav.tasks.registry import make_env, task_entry

MAX_TRAJECTORIES = 20  # paths kept per layout for the pictures; more only clutter them
MAX_COUNT = 2**31 - 1  # steps per episode, and episodes in all: 32-bit counters and indices
MAX_FILE_STEM = 80  # characters of a room's name kept in its picture's file name
METRIC_KEYS = (
    "episodes",
    "collision_free_rate",
    "mean_speed",
    "mean_distance",
    "mean_steps",
    "time_to_collision",
    "coverage",
)
MOVING_FIELDS = ("moving_count", "moving_speed", "moving_radius", "moving_clearance", "walkers")
"""The `RandomizeConfig` fields evaluation takes (`--randomize.moving-count` ...,
`--randomize.walkers`): moving obstacles and people added to every room."""


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
    spawn: str = "layout",
    stochastic_env: bool = True,
    moving: dict | None = None,
    coupled_smoother: bool = False,
) -> RandomizeConfig:
    """Layouts only (no sampled rooms); the layout's spawn or a random free one; `moving`: the
    `MOVING_FIELDS` that add moving obstacles to every room ({"moving_count": (1, 3)});
    `coupled_smoother`: the velocity smoother limits as kobuki_velocity_smoother does
    (`RandomizeConfig.coupled_smoother`: what the robot meets), not per axis.

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
        return RandomizeConfig(**rooms, **FIDELITY, coupled_smoother=coupled_smoother)
    if coupled_smoother:
        raise ValueError("coupled_smoother: exact physics has no velocity smoother to couple")
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


def run_episodes(env, act, key, episodes: int, steps: int, pinned: bool, start, body):
    """(the first state, the last carry, [steps, ...] outputs) of `steps` steps of the batch of
    `first_state(env, ., episodes, pinned)`: the one loop every rollout runs, so that rollouts of
    the same key run the same episodes. `start(state) -> carry` begins what the caller keeps;
    `body(state, action, nxt, carry) -> (carry, output)` takes each step (`act`: obs [E, D],
    key -> actions [E])."""
    step = jax.vmap(env.step)

    def scan_body(carry, k):
        state, kept = carry
        action = act(state.obs, k)
        nxt = step(state, action)
        kept, out = body(state, action, nxt, kept)
        return (nxt, kept), out

    k_reset, k_act = jax.random.split(key)
    first = first_state(env, k_reset, episodes, pinned)
    keys = jax.random.split(k_act, steps)
    (_, carry), outs = jax.lax.scan(scan_body, (first, start(first)), keys)
    return first, carry, outs


def make_rollout(env, act, episodes, steps, keep=MAX_TRAJECTORIES, *, pinned=False):
    """`rollout_program` jitted with jaxnav's compiler options."""
    program = rollout_program(env, act, episodes, steps, keep, pinned=pinned)
    return jax.jit(program, compiler_options=compiler_options())


def rollout_program(env, act, episodes, steps, keep=MAX_TRAJECTORIES, *, pinned=False):
    """`rollout(key) -> (Track, Kept)`, not jitted: for a program that calls it inside its own
    jit (JAX takes compiler options at the top level only).

    `pinned`: `episodes` episodes in every layout of the env's bank (E = R * episodes, episode e
    in layout e // episodes), all in one compiled batch; otherwise `episodes` episodes drawn by
    the env's own randomisation (R = 1). `keep` paths per room are kept.
    """
    rooms = env.bank.size if pinned else 1
    keep = min(keep, episodes)
    kept = (jnp.arange(rooms)[:, None] * episodes + jnp.arange(keep)).reshape(-1)  # [R * K]
    firsts = jnp.arange(rooms) * episodes  # [R]

    def start(state):
        n = rooms * episodes
        xy0 = state.data.qpos[:, :2]  # [E, 2]
        false, zero = jnp.zeros(n, bool), jnp.zeros(n)
        sums = {k: zero for k in env.metric_names if k != "collision"}
        goal = state.info.get("goal", xy0)  # [E, 2]
        return Track(false, false, jnp.zeros(n, jnp.int32), zero, xy0, sums, xy0, goal)

    def body(state, action, nxt, track):
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
        return track, (track.xy[kept], nxt.data.qpos[firsts, :3])

    def rollout(key):
        state, track, (path, qpos) = run_episodes(
            env, act, key, episodes, steps, pinned, start, body
        )  # path [steps, R * K, 2], qpos [steps, R, 3]
        path = jnp.concatenate([track.start[None, kept], path])  # [steps + 1, R * K, 2]
        qpos = jnp.concatenate([state.data.qpos[None, firsts, :3], qpos])  # [steps + 1, R, 3]
        first = jax.tree_util.tree_map(lambda x: x[firsts], state.info["params"])
        return track, Kept(xy=jnp.swapaxes(path, 0, 1), qpos=jnp.swapaxes(qpos, 0, 1), params=first)

    return rollout


def make_recorder(env, act, episodes: int, steps: int, record):
    """A jitted `run(key) -> [steps, ...]`: `record(state, action, nxt, running)` at each step of
    `episodes` episodes in every layout of the env's bank, the episodes of `make_rollout(...,
    pinned=True)` with the same key (`run_episodes`); `running` [E]: the episode had not ended
    before the step. For analyses that need more than a rollout's counts, such as where a policy
    collided and with what."""

    def body(state, action, nxt, done):
        return done | nxt.done, record(state, action, nxt, ~done)

    def run(key):
        start = lambda state: jnp.zeros(state.done.shape, bool)  # noqa: E731
        return run_episodes(env, act, key, episodes, steps, True, start, body)[2]

    return jax.jit(run, compiler_options=compiler_options())


def metrics(
    collided, steps_run, distance, control_period, task_metrics=None, cover=None, declared=None
) -> dict:
    """Summary of per-episode arrays [N]: rates in [0, 1], speeds m/s, distances m, times s, and
    the mean over episodes of each task metric's episode sum (`task_metrics`: {name: [N]}).

    `control_period` (s) is a float or one per episode [N]. `cover` [N] is each episode's
    coverage (`jaxnav.core.families.coverage`). `time_to_collision` is the mean time to the first
    collision of the episodes that collided, and the longest episode's time when none did.
    `declared`: the task's own (`NavTask.eval_metrics`), {name: (value [N], over [N] bool or
    None)} as `declared_values` gives them, each pooled by `pooled`.
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
        "time_to_collision": pooled(seconds, collided),
        **{k: float(np.mean(v)) for k, v in (task_metrics or {}).items()},
    }
    if cover is not None:
        out["coverage"] = float(np.mean(cover))
    out.update({name: pooled(value, over) for name, (value, over) in (declared or {}).items()})
    return out


def pooled(value, over=None) -> float:
    """The mean of `value` [N] over the episodes where `over` [N] bool holds (every episode if
    None); the largest value where it holds for none (`EvalMetric.over`)."""
    value = np.asarray(value, np.float64)
    if over is None:
        return float(np.mean(value))
    over = np.asarray(over, bool)
    return float(np.mean(value[over]) if over.any() else np.max(value))


def declared_values(eval_metrics, room: dict) -> dict:
    """{name: (value [N], over [N] bool or None)} of each of a task's `eval_metrics` in `room`,
    a room's episode record (`EvalMetric`)."""
    return {m.name: (m.value(room), None if m.over is None else m.over(room)) for m in eval_metrics}


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
    """All layouts in one env and one compiled batch -> per room, its record: the per-episode
    arrays (numpy), the room and what a task's `EvalMetric` reads ("layout", "robot_radius",
    "task"), the task's `declared_values` and what `evaluate` keeps for pictures (`paths`,
    `collided`, `qpos`, `params`, `env`)."""
    env = make_eval_env(policy, layouts, steps=steps, randomize=randomize, physics=physics)
    check_memory(env, episodes, steps)
    rollout = make_rollout(env, policy.act, episodes, steps, keep=episodes, pinned=True)
    track, kept = interruptible(lambda: jax.device_get(rollout(key)))  # Ctrl-C acts at once
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
            "control_period": env.control_period,
            "layout": layout,
            "robot_radius": env.robot.radius,
            "task": env.task,
        }
        # Trim each path after its episode ended: [steps_run + 1, 2].
        paths = [
            np.asarray(p[: n + 1]) for p, n in zip(kept.xy[room], track.steps[room], strict=True)
        ]
        params = jax.tree_util.tree_map(lambda x, r=r: x[r], kept.params)
        out.append(
            {
                **per_episode,
                "declared": declared_values(env.eval_metrics, per_episode),
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
        f"{format_bytes(need)} ({format_bytes(per_episode)} per episode), but the {where} is "
        f"{format_bytes(available)}; {hint}"
    )


def format_bytes(n: float) -> str:
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
    `time_limit_s`) at the policy's control period, else 600 (60 s)."""
    period = (policy.env_kwargs.get("scene") or SceneConfig()).control_period
    return suite_steps(suite, period)


def suite_steps(suite: str | None, period: float, default: int = 600) -> int:
    """Control steps of `period` s in `suite`'s time limit (`SUITE_META`'s `time_limit_s`);
    `default` where it has none (or no suite is named). The simulator's evaluation and the
    twin both take their default episode length from here."""
    limit = suite_meta(suite).get("time_limit_s") if suite else None
    return default if limit is None else round(limit / period)


def barn_scores(
    rooms: list[dict], names: list[str], meta: dict, top_speed: float, success: str
) -> list[dict]:
    """Per room, BARN's score (`jaxnav.io.barn.barn_score`) of every episode [N]: `barn_score`
    with the challenge's optimal time (the optimal path at 2 m/s), `barn_score_own_speed` with
    the optimal path at `top_speed` (the robot's), and `timeout` (neither success nor collision).
    `success`: the task metric whose episode sum > 0 marks a reached goal (`success_metric`)."""
    out = []
    for room, name in zip(rooms, names, strict=True):
        length = meta["rooms"][name]["optimal_path_m"]
        reached = np.asarray(room["metrics"][success]) > 0
        seconds = np.asarray(room["steps"], np.float64) * room["control_period"]
        out.append(
            {
                "barn_score": barn.barn_score(reached, seconds, barn.optimal_time(length)),
                "barn_score_own_speed": barn.barn_score(reached, seconds, length / top_speed),
                "timeout": ~reached & ~np.asarray(room["collided"], bool),
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


def _add_barn(results: dict, rooms, names, groups: dict, meta: dict, success="success") -> None:
    """BARN's metrics into `results`: per room, per family (difficulty group) and overall, with
    `success` the task's metric of a reached goal (`NavTask.success_metric`)."""
    top_speed = rooms[0]["env"].robot.max_linear_speed
    scores = barn_scores(rooms, names, meta, top_speed, success)
    for name, s in zip(names, scores, strict=True):
        results["layouts"][name].update(_mean_scores([s]))
        results["layouts"][name]["difficulty_rank"] = meta["rooms"][name].get("difficulty_rank")
    sizes = np.cumsum([0] + [len(v) for v in groups.values()])
    for family, a, b in zip(groups, sizes[:-1], sizes[1:], strict=True):
        results["families"][family].update(_mean_scores(scores[a:b]))
    results["overall"].update(_mean_scores(scores))
    results["barn"] = {"optimal_speed": barn.OPTIMAL_SPEED, "own_speed": top_speed}


def pool(rooms: list[dict]) -> dict:
    """Metrics pooled over all episodes of `rooms` (speed uses each room's control period), the
    task's declared ones (a record's "declared") included; the twin pools its rooms with it too."""
    cat = lambda k: np.concatenate([e[k] for e in rooms])  # noqa: E731
    periods = np.concatenate([np.full(len(e["steps"]), e["control_period"]) for e in rooms])
    task = {k: np.concatenate([e["metrics"][k] for e in rooms]) for k in rooms[0]["metrics"]}
    declared = {
        name: (
            np.concatenate([e["declared"][name][0] for e in rooms]),
            None if over is None else np.concatenate([e["declared"][name][1] for e in rooms]),
        )
        for name, (_, over) in rooms[0].get("declared", {}).items()
    }
    return metrics(
        cat("collided"), cat("steps"), cat("distance"), periods, task, cat("coverage"), declared
    )


def evaluate(
    policy: Policy,
    layouts: list[RoomLayout] | None = None,
    *,
    suite: str | None = None,
    episodes: int = 100,
    steps: int | None = None,
    seed: int = 0,
    spawn: str = "layout",
    stochastic_env: bool = True,
    physics: str | None = None,
    moving: dict | None = None,
    coupled_smoother: bool = False,
) -> dict:
    """Runs `episodes` episodes of at most `steps` control steps (None: `default_steps`, the
    suite's time limit or 600) in each layout (or each room of `suite`, see `load_suite`), all
    rooms in one compiled batch.

    Returns `{"layouts": {name: metrics}, "overall": metrics, "policy", "steps", "seed",
    "_trajectories": {name: {"paths": [[T_i + 1, 2] arrays], "collided": [bool], "qpos",
    "params", "env"}}}`, and with a suite also `"suite"` and `"families": {family: metrics}`
    (pooled over its rooms). Metrics are `METRIC_KEYS` (see `metrics`), the mean episode sum of
    each task metric and what the task declares (`NavTask.eval_metrics`, also under
    `"_eval_metrics"` for `format_table`); at most
    `MAX_TRAJECTORIES` paths per layout are kept; `qpos` [T_0 + 1, 3] (x, y, yaw) and `params`
    (SceneParams) are the first episode's, and `env` the env of the batch, for `jaxnav.viz.render`.
    `_trajectories` is for pictures; `strip_private` removes the `_` keys before writing JSON.
    `physics` ("fast" or "wheeled") replaces the policy's own `SceneConfig.physics`; the results
    name the one used under `"physics"`. `moving` adds moving obstacles to every room (the
    `RandomizeConfig` fields of `MOVING_FIELDS`, e.g. {"moving_count": (1, 3)}); the results
    then give them under `"moving"`. `coupled_smoother`: the Kobuki's smoother rule
    (`eval_randomize`), named under `"smoother"` in the results.
    """
    steps = default_steps(suite, policy) if steps is None else steps
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
    randomize = eval_randomize(spawn, stochastic_env, moving, coupled_smoother)
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
    env = rooms[0]["env"]
    trajectories = {
        name: {
            **{k: room[k] for k in keys},
            "collided": room["collided"][:MAX_TRAJECTORIES].tolist(),
            "goals": room["goal"][:MAX_TRAJECTORIES] if env.uses_goals else None,
        }
        for name, room in zip(names, rooms, strict=True)
    }
    results = {
        "layouts": per_layout,
        "overall": pool(rooms),
        "policy": policy.name,
        "physics": env.scene.cfg.physics,
        "steps": steps,
        "seed": seed,
        "smoother": "coupled" if coupled_smoother else "per-axis",
        "_trajectories": trajectories,
        "_eval_metrics": env.eval_metrics,
    }
    if randomize.moving_count[1] or randomize.walkers:
        results["moving"] = {k: getattr(randomize, k) for k in MOVING_FIELDS}
    if suite is not None:
        sizes = np.cumsum([0] + [len(v) for v in groups.values()])
        results["suite"] = suite
        results["families"] = {
            f: pool(rooms[a:b]) for f, a, b in zip(groups, sizes[:-1], sizes[1:], strict=True)
        }
        results["_families"] = {f: names[a] for f, a in zip(groups, sizes[:-1], strict=False)}
        meta = suite_meta(suite)
        if meta.get("score") == "barn" and env.success_metric is not None:
            _add_barn(results, rooms, names, groups, meta, env.success_metric)
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


def baseline(name: str, env: str = "avoid") -> Policy:
    """Baseline `name` (forward, random, stand) acting in task `env` with its default actions."""
    spec = task_entry(env).config_cls().action_spec
    return dataclasses.replace(BASELINES[name](spec), env=env)


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


def format_table(results: dict) -> str:
    """The metrics as a text table: one row per layout, per family (suites) and `overall`; a
    column for each of the task's `EvalMetric`s that has one (`results["_eval_metrics"]`)."""
    head = f"{'layout':<24} {'episodes':>8} {'collision-free %':>16} {'speed m/s':>9} "
    head += f"{'distance m':>10} {'steps':>7} {'coverage %':>10}"
    columns = [m for m in results.get("_eval_metrics", ()) if m.column]
    head += "".join(f" {m.column:>{m.width}}" for m in columns)
    families_ = [(f"family {k}", m) for k, m in results.get("families", {}).items()]
    rows = [*results["layouts"].items(), *families_, ("overall", results["overall"])]
    lines = [head, "-" * len(head)]
    for name, m in rows:
        lines.append(
            f"{printable(name)[:24]:<24} {m['episodes']:>8d} "
            f"{100 * m['collision_free_rate']:>16.1f} "
            f"{m['mean_speed']:>9.3f} {m['mean_distance']:>10.2f} {m['mean_steps']:>7.1f} "
            f"{100 * m['coverage']:>10.1f}"
            + "".join(f" {c.scale * m[c.name]:>{c.width}.{c.digits}f}" for c in columns)
        )
    return "\n".join(lines)
