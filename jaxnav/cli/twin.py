"""`python -m jaxnav.twin`: an exported policy on the robot's own code, in classic MuJoCo, no JAX.

    python -m jaxnav.twin --policy policy.npz --layouts scenes/inference_room.json --json twin.json
    python -m jaxnav.twin --policy policy.npz --suite benchmark --episodes 5 --video videos/

The command line over `jaxnav.twin` (which says what the twin simulates): the flags become a
`TwinConfig` and rooms, the outputs are checked before the episodes run, and the metrics table is
printed (`--json` writes evaluate's keys, `--video` a GIF per room). User mistakes (flags, files, a
missing package or OpenGL) end with one `error: ...` line, exit status 2.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from jaxnav.cli import Parser, UsageError, print_error
from jaxnav.core.layout import LayoutError, RoomLayout
from jaxnav.io.layouts import load_layouts
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.robot_side.ros_node import control_rate
from jaxnav.twin import TwinConfig, TwinError, run_twin, write_videos


def parse_args(argv=None):
    p = Parser(prog="python -m jaxnav.twin", description=__doc__.splitlines()[0])
    p.add_argument("--policy", required=True, metavar="FILE", help="exported policy (.npz)")
    rooms = p.add_mutually_exclusive_group(required=True)
    rooms.add_argument(
        "--layouts", nargs="+", metavar="FILE", help="layout files, each a room or a list of rooms"
    )
    rooms.add_argument("--suite", metavar="NAME", help="a suite of jaxnav's scenes (benchmark)")
    p.add_argument(
        "--episodes", type=int, default=TwinConfig.episodes, help="episodes per room (default 5)"
    )
    p.add_argument(
        "--steps", type=int, help="control steps per episode (default 600, or the suite's limit)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=TwinConfig.width, help="depth image px (640)")
    p.add_argument("--height", type=int, default=TwinConfig.height, help="depth image px (480)")
    p.add_argument(
        "--every-frame", action="store_true", help="render every 30 Hz frame, not only those read"
    )
    p.add_argument("--json", metavar="OUT", help="write the metrics here (evaluate's keys)")
    p.add_argument("--video", metavar="DIR", help="a GIF of the first episode per room")
    return p.parse_args(argv)


def _policy(path: str) -> NumpyPolicy:
    try:
        return NumpyPolicy.from_npz(path)
    except (OSError, ValueError) as err:
        raise TwinError(f"--policy: {err}") from None


def _rooms(args, policy: NumpyPolicy) -> tuple[list[RoomLayout] | None, str | None]:
    """(layouts, None) of --layouts, or (None, suite) of a --suite that exists."""
    from jaxnav.evaluation import load_suite

    if args.suite is not None:
        try:
            load_suite(args.suite)
        except FileNotFoundError as err:
            raise TwinError(f"--suite: {err}") from None
        return None, args.suite
    try:
        return load_layouts(args.layouts, success_radius=policy.success_radius), None
    except LayoutError as err:
        raise TwinError(f"--layouts: {err}") from None


def _config(args, policy: NumpyPolicy) -> TwinConfig:
    """The settings of the flags; --steps defaults to the suite's time limit, else 600."""
    from jaxnav.evaluation import suite_steps

    steps = args.steps
    if steps is None:
        steps = suite_steps(args.suite, 1.0 / control_rate(policy), TwinConfig.steps)
    flags = dict(episodes=args.episodes, steps=steps, seed=args.seed, width=args.width)
    try:
        return TwinConfig(**flags, height=args.height, every_frame=args.every_frame)
    except ValueError as err:
        raise TwinError(f"--{err}") from None


def _check_outputs(args) -> None:
    if args.json is not None and Path(args.json).is_dir():
        raise TwinError(f"--json: {args.json} is a directory, expected a file name")
    for flag, folder in (("--json", args.json and Path(args.json).parent), ("--video", args.video)):
        if folder:
            try:
                Path(folder).mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise TwinError(f"{flag}: cannot create {folder} ({err.strerror or err})") from None


def _run(argv) -> None:
    from jaxnav.evaluation import format_table, strip_private
    from jaxnav.io.files import write_atomic

    args = parse_args(argv)
    policy = _policy(args.policy)
    layouts, suite = _rooms(args, policy)
    cfg = _config(args, policy)
    _check_outputs(args)
    log = lambda text: print(text, flush=True)  # noqa: E731
    results = run_twin(args.policy, layouts, suite=suite, cfg=cfg, video=bool(args.video), log=log)
    print(format_table(results))
    states = ", ".join(f"{state} {n}" for state, n in results["loop_states"].items())
    print(f"{results['control_steps_per_s']:.1f} control steps/s; loop states (ticks): {states}")
    if args.json:
        write_atomic(
            args.json, json.dumps(strip_private(results), indent=2, allow_nan=False) + "\n"
        )
        print(f"metrics: {args.json}")
    if args.video:
        gifs = write_videos(results, Path(args.video))
        print(f"video: {args.video}/ ({len(gifs)} GIF)")


def main(argv=None) -> int:
    """`python -m jaxnav.twin`; returns the exit code (2 for user mistakes)."""
    try:
        _run(argv)
    except (UsageError, LayoutError, ValueError) as err:
        print_error(err)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
