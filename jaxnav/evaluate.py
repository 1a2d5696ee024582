"""`python -m jaxnav.evaluate`: a policy in held-out rooms -> collision-free rate, speed, pictures.

Each layout runs on its own env (no sampled rooms). All episodes of a layout run at once: `jax.vmap`
over episodes inside one jitted `jax.lax.scan` over control steps. An episode ends at its first
collision or after `steps` control steps; after that it is frozen (masked), so nothing more is counted.

    python -m jaxnav.evaluate --checkpoint runs/a --layouts scenes/inference_room.json --json out.json
    python -m jaxnav.evaluate --policy forward --episodes 100 --steps 600
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

import jaxnav
from jaxnav.layouts import LayoutError, RoomLayout
from jaxnav.policy import BASELINES, Policy
from jaxnav.randomize import RandomizeConfig
from jaxnav.scene import SCENES_DIR

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
    """A jitted `rollout(key) -> (Track, paths [keep, steps + 1, 2])` of `episodes` episodes."""
    reset, step = jax.vmap(env.reset), jax.vmap(env.step)
    keep = min(keep, episodes)

    def body(carry, key):
        state, track = carry
        nxt = step(state, act(state.obs, key))  # act: obs [E, 8] -> actions [E]
        live = ~track.done  # [E]; only episodes still running count this step
        xy = nxt.data.qpos[:, :2]  # [E, 2]
        moved = jnp.linalg.norm(xy - track.xy, axis=-1)  # [E] m
        track = Track(
            done=track.done | nxt.done,
            collided=track.collided | (live & nxt.collision),
            steps=track.steps + live.astype(jnp.int32),
            distance=track.distance + jnp.where(live, moved, 0.0),
            xy=jnp.where(live[:, None], xy, track.xy),
        )
        return (nxt, track), track.xy[:keep]

    def rollout(key):
        k_reset, k_act = jax.random.split(key)
        state = reset(jax.random.split(k_reset, episodes))
        xy0 = state.data.qpos[:, :2]  # [E, 2]
        false = jnp.zeros(episodes, bool)
        track = Track(false, false, jnp.zeros(episodes, jnp.int32), jnp.zeros(episodes), xy0)
        keys = jax.random.split(k_act, steps)
        (_, track), path = jax.lax.scan(body, (state, track), keys)  # path [steps, keep, 2]
        path = jnp.concatenate([xy0[None, :keep], path])  # [steps + 1, keep, 2]
        return track, jnp.swapaxes(path, 0, 1)

    return jax.jit(rollout)


def metrics(collided, steps_run, distance, control_period) -> dict:
    """Summary of per-episode arrays [N]: rates in [0, 1], speeds m/s, distances m.

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
    }


def _env_kwargs(policy: Policy, steps: int, randomize: RandomizeConfig) -> dict:
    """The policy's training env settings, with evaluation's own room, spawn and time limit."""
    kwargs = {k: v for k, v in policy.env_kwargs.items() if k not in ("layouts", "randomize")}
    return {**kwargs, "randomize": randomize, "auto_reset": False, "max_steps": steps}


def evaluate_layout(
    policy: Policy, layout: RoomLayout, key, *, episodes, steps, randomize
) -> tuple[dict, dict]:
    """One layout -> (per-episode arrays as numpy, its kept trajectories)."""
    env = jaxnav.make_env("avoid", layouts=[layout], **_env_kwargs(policy, steps, randomize))
    track, paths = make_rollout(env, policy.act, episodes, steps)(key)
    track = jax.tree_util.tree_map(np.asarray, track)
    # Trim each kept path after its episode ended: [steps_run + 1, 2].
    kept = [np.asarray(p[: n + 1]) for p, n in zip(paths, track.steps, strict=False)]
    period = env.scene.cfg.control_period
    episodes_out = {
        "collided": track.collided,
        "steps": track.steps,
        "distance": track.distance,
        "control_period": period,
    }
    return episodes_out, {"paths": kept, "collided": track.collided[: len(kept)].tolist()}


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
    "_trajectories": {name: {"paths": [[T_i + 1, 2] arrays], "collided": [bool]}}}` where metrics are
    `METRIC_KEYS` (see `metrics`) and at most `MAX_TRAJECTORIES` paths per layout are kept.
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
            eps["collided"], eps["steps"], eps["distance"], eps["control_period"]
        )
        everything.append(eps)
    # Overall: pooled over all episodes of all layouts (speed uses each layout's control period).
    pooled = {
        k: np.concatenate([e[k] for e in everything]) for k in ("collided", "steps", "distance")
    }
    periods = np.concatenate([np.full(episodes, e["control_period"]) for e in everything])
    overall = metrics(pooled["collided"], pooled["steps"], pooled["distance"], periods)
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


class UsageError(Exception):
    """A user mistake; its message is printed as one `error: ...` line."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse would print usage and exit; we want one line
        raise UsageError(message)


def build_parser() -> argparse.ArgumentParser:
    """The CLI flags."""
    p = _Parser(prog="python -m jaxnav.evaluate", description=__doc__.splitlines()[0])
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
    return p


def _check_args(args) -> None:
    """Cheap checks before anything is loaded or compiled."""
    if args.episodes < 1:
        raise UsageError(f"--episodes: must be >= 1, got {args.episodes}")
    if args.steps < 1:
        raise UsageError(f"--steps: must be >= 1, got {args.steps}")
    if args.checkpoint is not None and not Path(args.checkpoint).is_dir():
        raise UsageError(f"--checkpoint: no such directory: {args.checkpoint}")


def _load_policy(args) -> Policy:
    if args.policy is not None:
        return BASELINES[args.policy]()
    from jaxnav.checkpoint import load_policy  # lazy: needs orbax, and only checkpoints need it

    return load_policy(args.checkpoint)


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
    from jaxnav.plots import plot_trajectories  # lazy: matplotlib is slow to import

    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(strip_private(results), indent=2) + "\n")
        print(f"metrics: {args.json}")
    out = _plots_dir(args)
    out.mkdir(parents=True, exist_ok=True)
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


def main(argv=None) -> int:
    """`python -m jaxnav.evaluate`; returns the exit code (2 for user mistakes)."""
    try:
        _run(argv)
    except (UsageError, LayoutError, FileNotFoundError, ValueError) as err:
        message = " ".join(str(err).split())  # one line, whatever the message held
        print(f"error: {message}", file=sys.stderr)
        return 2
    return 0


class _CallableModule(types.ModuleType):
    """Lets `jaxnav.evaluate(...)` work whether `jaxnav.evaluate` names this module or the function."""

    def __call__(self, *args, **kwargs):
        return evaluate(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule

if __name__ == "__main__":
    sys.exit(main())
