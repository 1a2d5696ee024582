"""`python -m jaxnav.replay BAG --policy FILE`: what the robot's node would have commanded over a bag.

The command line over `jaxnav.replay` (which says what is replayed and how): the output folders
are checked before the replay runs; a plot (and `--csv`, a row per tick) is written and a line
printed. Exit status 0, or 2 for user mistakes (a damaged bag, a bad policy file). numpy,
matplotlib and rosbags only: no jax.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from jaxnav.cli import Parser, print_error
from jaxnav.replay import ReplayError, plot, replay, write_csv
from jaxnav.robot_side.ros_node import add_goal_flags, add_loop_flags


def parse_args(argv=None):
    p = Parser(prog="python -m jaxnav.replay", description=__doc__.splitlines()[0])
    p.add_argument("bag", metavar="BAG", type=Path, help="rosbag2 folder")
    p.add_argument("--policy", required=True, help="exported policy (.npz)")
    p.add_argument("--topic", help="depth image or LaserScan topic (default: the one that fits)")
    p.add_argument("--plot", type=Path, help="PNG to write (default: BAG.replay.png beside it)")
    p.add_argument("--csv", type=Path, help="also write one row per tick here")
    add_goal_flags(p)
    add_loop_flags(p)
    return p.parse_args(argv)


def _outputs(args) -> tuple[Path, Path | None]:
    """(plot, csv or None) paths, checked before the replay runs."""
    out = args.plot or args.bag.parent / f"{args.bag.resolve().name}.replay.png"
    for flag, path in (("--plot", out), ("--csv", args.csv)):
        if path is not None and not path.parent.is_dir():
            raise ReplayError(f"{flag} {path}: no folder {path.parent}")
    return out, args.csv


def main(argv=None) -> int:
    try:
        args = parse_args(argv)
        out, csv_path = _outputs(args)
        result = replay(args.bag, vars(args), args.topic)
    except ValueError as err:  # UsageError, ReplayError, a bad policy file or setting
        print_error(err)
        return 2
    plot(result, out, f"{args.bag.name}: {args.policy}")
    if csv_path is not None:
        write_csv(result, csv_path)
    driving = sum(s == "policy" for s in result.state)
    span = result.time[-1] if len(result.time) else math.nan
    inputs = ", ".join(f"{count} on {t}" for t, count in result.inputs)
    inputs = f"; goal inputs: {inputs}" if inputs else ""
    print(
        f"{result.topic}: {result.messages} messages, {len(result.time)} ticks over {span:.2f} s; "
        f"{driving} driving, {len(result.time) - driving} at zero velocity{inputs}; wrote {out}"
        + (f" and {csv_path}" if csv_path is not None else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
