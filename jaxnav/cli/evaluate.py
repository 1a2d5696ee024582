"""`python -m jaxnav.evaluate`: a policy in held-out rooms -> collision-free rate, speed, pictures.

The command line of `jaxnav.evaluation` (how rooms, episodes and metrics are run and measured).

    python -m jaxnav.evaluate --checkpoint runs/a --layouts scenes/inference_room.json --json out.json
    python -m jaxnav.evaluate --policy forward --episodes 100 --steps 600
    python -m jaxnav.evaluate --checkpoint runs/a --video videos/   # one GIF per layout
    python -m jaxnav.evaluate --policy forward --suite benchmark --episodes 20  # every family
    python -m jaxnav.evaluate --checkpoint runs/a --physics wheeled  # the wheeled validation model
    python -m jaxnav.evaluate --checkpoint runs/a --suite benchmark --randomize.moving-count 1 3

Checked before anything compiles: the flags, the layouts (`load_layouts`: one set of rooms, a goal
task's goals beyond its success radius from the spawn), the memory the batch needs
(`jaxnav.evaluation.check_memory`) and the space left where the results go. Per-room pictures get
safe, distinct file names (`file_stems`), and names are printed with control characters escaped
(`printable`).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import stat
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

from jaxnav.cli import Parser, UsageError, print_error
from jaxnav.core.randomize import RandomizeConfig
from jaxnav.core.scene import PHYSICS, SCENES_DIR
from jaxnav.evaluation import (
    MAX_COUNT,
    MOVING_FIELDS,
    NotFinite,
    barn_line,
    baseline,
    evaluate,
    file_stems,
    format_bytes,
    format_table,
    load_suite,
    printable,
    strip_private,
    success_radius,
)
from jaxnav.io.files import check_writable, write_atomic
from jaxnav.io.layouts import LayoutError, RoomLayout, load_layouts
from jaxnav.policy import BASELINES, Policy
from jaxnav.process import compile_cache
from jaxnav.runconfig import add_field_flags, overrides_from_args
from jaxnav.tasks.base import observation_size

DEFAULT_LAYOUTS = SCENES_DIR / "inference_room.json"
# Bytes of results per room, to refuse a folder without the space before evaluating (a top-down
# PNG is 50-150 kB, a GIF of 600 steps a few MB).
RESULT_BYTES = {"--json": 2_000, "--plots": 300_000, "--video": 10_000_000}


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
        "--coupled-smoother",
        action="store_true",
        help="the velocity smoother limits both speeds by one factor, as the Kobuki's "
        "kobuki_velocity_smoother does (default: each on its own, as in training)",
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
    if args.coupled_smoother and args.deterministic_env:
        raise UsageError("--coupled-smoother: --deterministic-env has no velocity smoother")
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
                f"{flag} {folder}: {format_bytes(free)} free, the results need about {format_bytes(need)}"
            )


def _load_policy(args) -> Policy:
    if args.policy is not None:
        try:
            return baseline(args.policy, args.env or "avoid")
        except ValueError as err:  # an unknown task; its message lists the valid ones
            raise UsageError(f"--env: {err}") from None
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


def _listing(folder: Path, files: list[str]) -> str:
    """`folder/ (N PNG: a.png, b.png, ...)`: the names of the files written there."""
    kinds = ", ".join(sorted({f.rsplit(".", 1)[-1].upper() for f in files}))
    shown = ", ".join(files[:8]) + (f", ... ({len(files)} in all)" if len(files) > 8 else "")
    return f"{folder}/ ({len(files)} {kinds}: {shown})"


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
            _title(printable(name), results, m),
            goals=traj["goals"],
            movers=traj["params"],
        )
    print(f"plots: {_listing(out, files)}")


def _title(name: str, results: dict, m: dict) -> str:
    """A room's picture's title: its name, the policy and its main metrics (the task's
    `EvalMetric.title`s, else the collision-free rate and coverage)."""
    shown = [e.title.format(m[e.name]) for e in results.get("_eval_metrics", ()) if e.title]
    if not shown:
        shown = [
            f"{100 * m['collision_free_rate']:.0f}% collision-free",
            f"coverage {100 * m['coverage']:.0f}%",
        ]
    return f"{name}: {results['policy']}, {', '.join(shown)} ({m['episodes']} episodes)"


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
        steps=args.steps,
        seed=args.seed,
        spawn=args.spawn,
        stochastic_env=not args.deterministic_env,
        physics=args.physics,
        moving=overrides_from_args(args)["randomize"],
        coupled_smoother=args.coupled_smoother,
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


if __name__ == "__main__":
    sys.exit(main())
