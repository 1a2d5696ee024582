"""`python -m jaxnav.evaluate`: a policy in held-out rooms -> collision-free rate, speed, pictures.

Each layout runs on its own env (no sampled rooms). All episodes of a layout run at once: `jax.vmap`
over episodes inside one jitted `jax.lax.scan` over control steps. An episode ends at its first
collision or after `steps` control steps; after that it is frozen (masked), so nothing more is counted.

    python -m jaxnav.evaluate --checkpoint runs/a --layouts scenes/inference_room.json --json out.json
    python -m jaxnav.evaluate --policy forward --episodes 100 --steps 600
    python -m jaxnav.evaluate --checkpoint runs/a --video videos/   # one GIF per layout
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

import jaxnav
from jaxnav.cli import Parser, UsageError, make_callable, print_error
from jaxnav.core.randomize import RandomizeConfig, SceneParams
from jaxnav.core.scene import SCENES_DIR
from jaxnav.io.layouts import LayoutError, RoomLayout
from jaxnav.policy import BASELINES, Policy
from jaxnav.tasks.registry import make_env

DEFAULT_LAYOUTS = SCENES_DIR / "inference_room.json"
MAX_TRAJECTORIES = 20  # paths kept per layout for the pictures; more only clutter them
METRIC_KEYS = ("episodes", "collision_free_rate", "mean_speed", "mean_distance", "mean_steps")


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


@struct.dataclass
class Kept:
    """What a rollout keeps besides the counts: K paths for the pictures, episode 0 for a video."""

    xy: jax.Array  # [K, steps + 1, 2] float32, positions of episodes 0..K-1 (frozen once ended), m
    qpos: jax.Array  # [steps + 1, 3] float32, x, y, yaw of episode 0 (not frozen: trim it), m, rad
    params: SceneParams  # episode 0's room and parameters, from its reset (constant: no auto-reset)


# ------------------------------------------------------------------------------
# Rollouts


def eval_randomize(spawn: str = "layout", stochastic_env: bool = True) -> RandomizeConfig:
    """Layouts only (no sampled rooms); the layout's spawn or a random free one.

    `stochastic_env` keeps the default traction, speed-gain and sensor-noise ranges, so episodes
    from the same spawn differ; otherwise physics and sensing are exact.
    """
    if spawn not in ("layout", "random"):
        raise ValueError(f"spawn: must be 'layout' or 'random', got {spawn!r}")
    cfg = RandomizeConfig(
        sampled_room_prob=0.0, random_spawn_prob=0.0 if spawn == "layout" else 1.0
    )
    if stochastic_env:
        return cfg
    return dataclasses.replace(
        cfg,
        friction=(1.0, 1.0),
        speed_gain=(1.0, 1.0),
        sensor_noise=(0.0, 0.0),
        sensor_dropout=(0.0, 0.0),
    )


def make_rollout(env, act, episodes: int, steps: int, keep: int = MAX_TRAJECTORIES):
    """A jitted `rollout(key) -> (Track, Kept)` of `episodes` episodes (`keep` paths kept)."""
    reset, step = jax.vmap(env.reset), jax.vmap(env.step)
    keep = min(keep, episodes)

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
        )
        return (nxt, track), (track.xy[:keep], nxt.data.qpos[0])

    def rollout(key):
        k_reset, k_act = jax.random.split(key)
        state = reset(jax.random.split(k_reset, episodes))
        xy0 = state.data.qpos[:, :2]  # [E, 2]
        false, zero = jnp.zeros(episodes, bool), jnp.zeros(episodes)
        sums = {k: zero for k in env.metric_names if k != "collision"}
        track = Track(false, false, jnp.zeros(episodes, jnp.int32), zero, xy0, sums)
        keys = jax.random.split(k_act, steps)
        (_, track), (path, qpos) = jax.lax.scan(body, (state, track), keys)  # [steps, keep, 2]
        path = jnp.concatenate([xy0[None, :keep], path])  # [steps + 1, keep, 2]
        qpos = jnp.concatenate([state.data.qpos[:1], qpos])  # [steps + 1, 3]
        first = jax.tree_util.tree_map(lambda x: x[0], state.info["params"])
        return track, Kept(xy=jnp.swapaxes(path, 0, 1), qpos=qpos, params=first)

    return jax.jit(rollout)


def metrics(collided, steps_run, distance, control_period, task_metrics=None) -> dict:
    """Summary of per-episode arrays [N]: rates in [0, 1], speeds m/s, distances m, and the
    mean over episodes of each task metric's episode sum (`task_metrics`: {name: [N]}).

    `control_period` (s) is a float or one per episode [N].
    """
    steps_run = np.asarray(steps_run, np.float64)
    distance = np.asarray(distance, np.float64)
    # Speed over the steps each episode actually ran, so early collisions do not dilute it.
    speed = distance / (np.maximum(steps_run, 1) * control_period)
    return {
        "episodes": int(len(steps_run)),
        "collision_free_rate": float(1.0 - np.mean(collided)),
        "mean_speed": float(np.mean(speed)),
        "mean_distance": float(np.mean(distance)),
        "mean_steps": float(np.mean(steps_run)),
        **{k: float(np.mean(v)) for k, v in (task_metrics or {}).items()},
    }


def _env_kwargs(policy: Policy, steps: int, randomize: RandomizeConfig) -> dict:
    """The policy's training env settings, with evaluation's own room, spawn and time limit."""
    kwargs = {k: v for k, v in policy.env_kwargs.items() if k not in ("layouts", "randomize")}
    return {**kwargs, "randomize": randomize, "max_steps": steps}


def evaluate_layout(
    policy: Policy, layout: RoomLayout, key, *, episodes, steps, randomize
) -> tuple[dict, dict]:
    """One layout -> (per-episode arrays as numpy, its kept trajectories and first episode)."""
    env = make_env(policy.env, layouts=[layout], **_env_kwargs(policy, steps, randomize))
    track, kept = jax.device_get(make_rollout(env, policy.act, episodes, steps)(key))
    # Trim each kept path after its episode ended: [steps_run + 1, 2].
    paths = [np.asarray(p[: n + 1]) for p, n in zip(kept.xy, track.steps, strict=False)]
    episodes_out = {
        "collided": track.collided,
        "steps": track.steps,
        "distance": track.distance,
        "control_period": env.control_period,
        "metrics": track.metrics,
    }
    return episodes_out, {
        "paths": paths,
        "collided": track.collided[: len(paths)].tolist(),
        "qpos": np.asarray(kept.qpos[: track.steps[0] + 1]),  # [steps_run + 1, 3]
        "params": kept.params,
        "env": env,
    }


def evaluate(
    policy: Policy,
    layouts: list[RoomLayout],
    *,
    episodes: int = 100,
    steps: int = 600,
    seed: int = 0,
    spawn: str = "layout",
    stochastic_env: bool = True,
) -> dict:
    """Runs `episodes` episodes of at most `steps` control steps in each layout.

    Returns `{"layouts": {name: metrics}, "overall": metrics, "policy", "steps", "seed",
    "_trajectories": {name: {"paths": [[T_i + 1, 2] arrays], "collided": [bool], "qpos",
    "params", "env"}}}` where metrics are `METRIC_KEYS` (see `metrics`) and at most
    `MAX_TRAJECTORIES` paths per layout are kept; `qpos` [T_0 + 1, 3] (x, y, yaw) and `params`
    (SceneParams) are the first episode's, and `env` the layout's env, for `jaxnav.viz.render`.
    `_trajectories` is for pictures; `strip_private` removes it before writing JSON.
    """
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1, got {episodes}")
    if steps < 1:
        raise ValueError(f"steps: must be >= 1, got {steps}")
    if not layouts:
        raise ValueError("layouts: need at least one layout")
    randomize = eval_randomize(spawn, stochastic_env)
    per_layout, trajectories, everything = {}, {}, []
    for i, (name, layout) in enumerate(zip(unique_names(layouts), layouts, strict=True)):
        key = jax.random.fold_in(jax.random.PRNGKey(seed), i)  # independent episodes per layout
        eps, trajectories[name] = evaluate_layout(
            policy, layout, key, episodes=episodes, steps=steps, randomize=randomize
        )
        per_layout[name] = metrics(
            eps["collided"], eps["steps"], eps["distance"], eps["control_period"], eps["metrics"]
        )
        everything.append(eps)
    # Overall: pooled over all episodes of all layouts (speed uses each layout's control period).
    pooled = {
        k: np.concatenate([e[k] for e in everything]) for k in ("collided", "steps", "distance")
    }
    periods = np.concatenate([np.full(episodes, e["control_period"]) for e in everything])
    names = everything[0]["metrics"]
    task_metrics = {k: np.concatenate([e["metrics"][k] for e in everything]) for k in names}
    overall = metrics(
        pooled["collided"], pooled["steps"], pooled["distance"], periods, task_metrics
    )
    return {
        "layouts": per_layout,
        "overall": overall,
        "policy": policy.name,
        "steps": steps,
        "seed": seed,
        "_trajectories": trajectories,
    }


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
    p.add_argument(
        "--layouts",
        nargs="+",
        metavar="FILE",
        default=[str(DEFAULT_LAYOUTS)],
        help="layout files, each a room or a list of rooms (default: scenes/inference_room.json)",
    )
    p.add_argument("--episodes", type=int, default=100, help="episodes per layout (default 100)")
    p.add_argument("--steps", type=int, default=600, help="control steps per episode (default 600)")
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
        help="no traction, speed-gain or sensor-noise randomisation",
    )
    p.add_argument("--json", metavar="OUT", help="write the metrics here")
    p.add_argument("--plots", metavar="DIR", help="top-down PNGs, one per layout")
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
    if args.steps < 1:
        raise UsageError(f"--steps: must be >= 1, got {args.steps}")
    if args.checkpoint is not None and not Path(args.checkpoint).is_dir():
        raise UsageError(f"--checkpoint: no such directory: {args.checkpoint}")
    for flag, value in (("--plots", args.plots), ("--video", args.video)):
        if value is not None and Path(value).exists() and not Path(value).is_dir():
            raise UsageError(f"{flag}: not a directory: {value}")


def _load_policy(args) -> Policy:
    if args.policy is not None:
        return BASELINES[args.policy]()
    from flax.errors import FlaxError

    from jaxnav.io.checkpoint import CheckpointError, load_policy  # lazy: only checkpoints need it

    try:
        policy = load_policy(args.checkpoint)
    except CheckpointError as err:  # its message names the file; add the flag
        raise UsageError(f"--checkpoint: {err}") from None
    # The weights must fit the network that the checkpoint's config.json describes; tracing one
    # call (no compile) says so now, instead of a traceback from inside the jitted rollout.
    obs = jax.ShapeDtypeStruct((1, policy.env_kwargs["sensor"].num_sectors), jnp.float32)
    try:
        jax.eval_shape(policy.act, obs, jax.random.PRNGKey(0))
    except FlaxError as err:
        detail = str(err).split(" (https://")[0]
        raise UsageError(
            f"--checkpoint: {args.checkpoint}: policy.msgpack does not fit the network of its "
            f"config.json ({detail})"
        ) from None
    return policy


def _plots_dir(args) -> Path:
    """--plots, else beside --json, else `eval/` in the checkpoint folder, else ./eval."""
    if args.plots:
        return Path(args.plots)
    if args.json:
        return Path(args.json).parent
    if args.checkpoint:
        return Path(args.checkpoint) / "eval"
    return Path("eval")


def _file_name(name: str) -> str:
    """A layout name made safe as a file name."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "room"


def format_table(results: dict) -> str:
    """The metrics as a text table, one row per layout and an `overall` row."""
    head = f"{'layout':<24} {'episodes':>8} {'collision-free %':>16} {'speed m/s':>9} "
    head += f"{'distance m':>10} {'steps':>7}"
    rows = [*results["layouts"].items(), ("overall", results["overall"])]
    lines = [head, "-" * len(head)]
    for name, m in rows:
        lines.append(
            f"{name[:24]:<24} {m['episodes']:>8d} {100 * m['collision_free_rate']:>16.1f} "
            f"{m['mean_speed']:>9.3f} {m['mean_distance']:>10.2f} {m['mean_steps']:>7.1f}"
        )
    return "\n".join(lines)


def _write_outputs(args, results: dict, layouts: list[RoomLayout]) -> None:
    """The JSON (if asked) and one top-down PNG per layout."""
    from jaxnav.viz.plots import plot_trajectories  # lazy: matplotlib is slow to import

    if args.json:
        try:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps(strip_private(results), indent=2) + "\n")
        except OSError as err:
            raise UsageError(f"--json: cannot write {args.json} ({err.strerror or err})") from None
        print(f"metrics: {args.json}")
    out = _plots_dir(args)
    _make_dir(out, "--plots")
    for (name, traj), layout in zip(results["_trajectories"].items(), layouts, strict=True):
        m = results["layouts"][name]
        title = (
            f"{name}: {results['policy']}, {100 * m['collision_free_rate']:.0f}% collision-free "
            f"({m['episodes']} episodes)"
        )
        plot_trajectories(
            layout, traj["paths"], traj["collided"], out / f"{_file_name(name)}.png", title
        )
    print(f"plots: {out}/ ({len(layouts)} PNG)")


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
    try:
        for (name, traj), layout in items:
            outcome = "collision" if traj["collided"][0] else "no collision"
            title = f"{name}: {results['policy']}, episode 1 ({outcome})"
            render.render_episode(
                traj["env"],
                traj["params"],
                traj["qpos"],
                out / f"{_file_name(name)}.gif",
                wall_height=layout.wall_height,
                title=title,
            )
    except render.NoGLError:
        from jaxnav.viz.plots import plot_trajectories

        print(f"video: no OpenGL backend ({render.GL_HINT}); top-down PNGs written instead")
        for (name, traj), layout in items:
            path = out / f"{_file_name(name)}.png"
            plot_trajectories(layout, [traj["qpos"][:, :2]], traj["collided"][:1], path)
        return
    print(f"video: {out}/ ({len(items)} GIF, OpenGL via {render.gl_backend()})")


def _run(argv) -> None:
    args = build_parser().parse_args(argv)
    _check_args(args)
    try:
        layouts = [room for path in args.layouts for room in jaxnav.load_layout(path)]
    except LayoutError as err:  # its message names the file, room and field; add the flag
        raise UsageError(f"--layouts: {err}") from None
    policy = _load_policy(args)
    results = evaluate(
        policy,
        layouts,
        episodes=args.episodes,
        steps=args.steps,
        seed=args.seed,
        spawn=args.spawn,
        stochastic_env=not args.deterministic_env,
    )
    print(format_table(results))
    _write_outputs(args, results, layouts)
    if args.video:
        _write_videos(args, results, layouts)


def main(argv=None) -> int:
    """`python -m jaxnav.evaluate`; returns the exit code (2 for user mistakes)."""
    try:
        _run(argv)
    except (UsageError, LayoutError, FileNotFoundError, ValueError) as err:
        print_error(err)
        return 2
    return 0


make_callable(__name__, evaluate)

if __name__ == "__main__":
    sys.exit(main())
