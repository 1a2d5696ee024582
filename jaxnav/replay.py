"""`python -m jaxnav.replay BAG --policy FILE`: what the robot's node would have commanded over a bag.

python -m jaxnav.replay rec/ --policy policy.npz                       # writes rec.replay.png
python -m jaxnav.replay rec/ --policy policy.npz --topic /scan --csv rec.csv

BAG is a rosbag2 recording (a folder with metadata.yaml; sqlite3 or mcap) holding a depth image
(sensor_msgs/Image, 32FC1 or 16UC1) or sensor_msgs/LaserScan topic: `--topic`, or the one such topic
(an Image topic counts when its name contains "depth"). Its messages go, at their recorded times,
through the ROS node's own logic (`jaxnav.robot_side.ros_node.ControlLoop`, built as the node builds
it, with the node's flags), ticked at the node's rate from the first message to when the last one
goes stale. No ROS install is needed: the bag is read with the `rosbags` library
(pip install "jaxnav[ros]"). The plot shows the observation (the 8 sector distances) and the
commanded (v, w) over time, with the ticks that sent zero velocity shaded; `--csv` writes one row
per tick. numpy, matplotlib and rosbags only: no jax.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from jaxnav.cli import Parser, UsageError, print_error
from jaxnav.robot_side.ros_node import ControlLoop, add_loop_flags, make_loop

IMAGE, SCAN = "sensor_msgs/msg/Image", "sensor_msgs/msg/LaserScan"


class ReplayError(UsageError):
    """A user mistake (bag, topic, policy file); one line naming it."""


@dataclasses.dataclass(frozen=True)
class Replay:
    """What the node's loop did over a bag: one row per timer tick."""

    topic: str
    """The topic replayed."""
    messages: int
    """How many messages of it the bag held."""
    time: np.ndarray
    """[T] s since the topic's first message: when each tick ran."""
    obs: np.ndarray
    """[T, num_sectors] m, right to left; NaN where the tick sent zero velocity without acting."""
    twist: np.ndarray
    """[T, 2] the command sent: forward m/s, yaw rad/s (positive = left)."""
    state: tuple[str, ...]
    """[T] "policy", or why the tick sent zero velocity (no data, stale data, an error)."""


def _rosbags():
    """(Reader, typestore) of the rosbags library, or a ReplayError saying how to get it."""
    try:
        from rosbags.rosbag2 import Reader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ReplayError(
            "python -m jaxnav.replay needs the 'rosbags' package (pip install 'jaxnav[ros]')"
        ) from None
    # sensor_msgs/Image and LaserScan are the same in every ROS 2 distribution.
    return Reader, get_typestore(Stores.ROS2_HUMBLE)


def pick_topic(bag: Path, topics: dict[str, str], topic: str | None) -> str:
    """The topic to replay among `topics` (name -> message type); errors name the bag."""
    fits = {n: t for n, t in topics.items() if t == SCAN or (t == IMAGE and "depth" in n)}
    if topic is not None:
        if topics.get(topic) not in (IMAGE, SCAN):
            found = topics.get(topic, "not in the bag")
            raise ReplayError(
                f"--topic {topic}: {found}; depth image or LaserScan topics: {sorted(fits) or 'none'}"
            )
        return topic
    if len(fits) != 1:
        what = f"several fit ({', '.join(sorted(fits))})" if fits else "none fits"
        raise ReplayError(
            f"{bag}: no single depth image or LaserScan topic, {what}; topics: "
            f"{', '.join(f'{n} ({t})' for n, t in sorted(topics.items())) or 'none'}; use --topic"
        )
    return next(iter(fits))


def replay(bag, get: dict, topic: str | None = None, log=None) -> Replay:
    """Runs the node's loop over the bag's topic. `get`: the node's settings (`make_loop`)."""
    bag = Path(bag)
    if not (bag / "metadata.yaml").is_file():
        raise ReplayError(f"{bag}: no such rosbag2 (a folder holding metadata.yaml)")
    Reader, typestore = _rosbags()
    try:
        reader = Reader(bag)
        reader.open()
    except Exception as err:  # noqa: BLE001 - rosbags raises several kinds for a broken bag
        raise ReplayError(f"{bag}: unreadable rosbag2 ({err})") from None
    try:
        topics = {c.topic: c.msgtype for c in reader.connections}
        topic = pick_topic(bag, topics, topic)
        clock = [0.0]
        say = log or (lambda text: print(f"{clock[0]:8.2f} s  {text}"))
        loop, rate = make_loop(dict(get, scan=topics[topic] == SCAN), say)
        connections = [c for c in reader.connections if c.topic == topic]
        stamped = (
            (ns, typestore.deserialize_cdr(raw, c.msgtype))
            for c, ns, raw in reader.messages(connections)
        )
        return _run(loop, rate, stamped, topic, clock)
    finally:
        reader.close()


def _run(loop: ControlLoop, rate: float, stamped, topic: str, clock: list) -> Replay:
    """Ticks `loop` every 1/rate s from the first message of `stamped` ((ns, msg), in time order)
    until the last has gone stale; a message at a tick's time arrives before that tick."""
    rows, count, t0, last, k = [], 0, None, 0, 0
    period = round(1e9 / rate)  # ns, as rclpy's create_timer converts it

    def tick_until(end_ns: int, inclusive: bool) -> None:
        nonlocal k
        while (ns := k * period) < end_ns or (inclusive and ns == end_ns):
            clock[0] = t = ns * 1e-9
            twist = loop.tick(t)
            rows.append((t, loop.obs, twist, loop.state))
            k += 1

    for ns, msg in stamped:  # times in integer ns since the first message: ties are exact
        t0 = ns if t0 is None else t0
        last = ns - t0
        tick_until(last, inclusive=False)
        loop.on_observation(msg, last * 1e-9)
        count += 1
    if count == 0:
        raise ReplayError(f"--topic {topic}: no messages in the bag")
    tick_until(last + round(loop.max_age * 1e9) + period, inclusive=True)  # the final stop
    n = loop.controller.policy.sensor.num_sectors
    obs = np.array([np.full(n, np.nan) if o is None else o for _, o, _, _ in rows], np.float32)
    return Replay(
        topic=topic,
        messages=count,
        time=np.array([r[0] for r in rows]),
        obs=obs,
        twist=np.array([tuple(r[2]) for r in rows], np.float64),
        state=tuple(r[3] for r in rows),
    )


def write_csv(result: Replay, path: Path) -> None:
    """One row per tick: time_s, state, obs_0 (rightmost) ..., linear_m_s, angular_rad_s."""
    n = result.obs.shape[1]
    with open(path, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["time_s", "state", *(f"obs_{i}" for i in range(n)), "linear", "angular"])
        for t, state, obs, twist in zip(
            result.time, result.state, result.obs, result.twist, strict=True
        ):
            out.writerow([f"{t:.4f}", state, *(f"{x:.4f}" for x in obs), *twist.tolist()])


def _stopped_spans(result: Replay) -> list[tuple[float, float]]:
    """(start, end) s of each run of ticks that sent zero velocity, each tick lasting a period."""
    period = result.time[1] - result.time[0] if len(result.time) > 1 else 0.1
    spans = []
    for t, state in zip(result.time, result.state, strict=True):
        if state == "policy":
            continue
        if spans and np.isclose(spans[-1][1], t):
            spans[-1] = (spans[-1][0], t + period)
        else:
            spans.append((t, t + period))
    return spans


def plot(result: Replay, path: Path, title: str) -> None:
    """The observations and (v, w) over time, ticks that sent zero velocity shaded."""
    fig = Figure(figsize=(10, 7), constrained_layout=True)
    ax_obs, ax_v, ax_w = fig.subplots(3, 1, sharex=True, height_ratios=[2, 1, 1])
    n = result.obs.shape[1]
    colors = [f"C{i % 10}" for i in range(n)]
    for i in range(n):
        side = " (right)" if i == 0 else " (left)" if i == n - 1 else ""
        ax_obs.step(
            result.time, result.obs[:, i], where="post", color=colors[i], label=f"{i}{side}"
        )
    ax_obs.set_ylabel("sector distance (m)")
    ax_obs.legend(title="sector", fontsize="small", loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax_v.step(result.time, result.twist[:, 0], where="post", color="k")
    ax_v.set_ylabel("v (m/s)")
    ax_w.step(result.time, result.twist[:, 1], where="post", color="k")
    ax_w.set_ylabel("w (rad/s), + left")
    ax_w.set_xlabel(f"time since the first message (s); {result.topic}")
    for start, end in _stopped_spans(result):
        for ax in (ax_obs, ax_v, ax_w):
            ax.axvspan(start, end, color="0.85", lw=0)
    for ax in (ax_obs, ax_v, ax_w):
        ax.grid(alpha=0.3)
    ax_obs.set_title(title)
    fig.savefig(path, dpi=110)


def parse_args(argv=None):
    p = Parser(prog="python -m jaxnav.replay", description=__doc__.splitlines()[0])
    p.add_argument("bag", metavar="BAG", type=Path, help="rosbag2 folder")
    p.add_argument("--policy", required=True, help="exported policy (.npz)")
    p.add_argument("--topic", help="depth image or LaserScan topic (default: the one that fits)")
    p.add_argument("--plot", type=Path, help="PNG to write (default: BAG.replay.png beside it)")
    p.add_argument("--csv", type=Path, help="also write one row per tick here")
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
    except ValueError as err:  # UsageError and ReplayError, a bad policy file or setting
        print_error(err)
        return 2
    plot(result, out, f"{args.bag.name}: {args.policy}")
    if csv_path is not None:
        write_csv(result, csv_path)
    driving = sum(s == "policy" for s in result.state)
    span = result.time[-1] if len(result.time) else math.nan
    print(
        f"{result.topic}: {result.messages} messages, {len(result.time)} ticks over {span:.2f} s; "
        f"{driving} driving, {len(result.time) - driving} at zero velocity; wrote {out}"
        + (f" and {csv_path}" if csv_path is not None else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
