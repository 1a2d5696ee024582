"""`python -m jaxnav.replay BAG --policy FILE`: what the robot's node would have commanded over a bag.

python -m jaxnav.replay rec/ --policy policy.npz                       # writes rec.replay.png
python -m jaxnav.replay rec/ --policy policy.npz --topic /scan --csv rec.csv

BAG is a rosbag2 recording (a folder with metadata.yaml; sqlite3 or mcap) holding a depth image
(sensor_msgs/Image, 32FC1 or 16UC1) or sensor_msgs/LaserScan topic: `--topic`, or the one such topic
(an Image topic counts when its name contains "depth"). Its messages go, at their recorded times,
through the ROS node's own logic (`jaxnav.robot_side.ros_node.ControlLoop`, built as the node builds
it, with the node's flags), ticked at the node's rate from the first message to when the last one
goes stale. No ROS install is needed: the bag is read with the `rosbags` library
(`pip install rosbags`, or `pip install -e ".[ros]"` in the repository). The plot shows the
observation (the 8 sector distances) and the commanded (v, w) over time, with the ticks that sent zero velocity shaded; `--csv` writes one row
per tick. numpy, matplotlib and rosbags only: no jax.

A goal policy (exported from the `goal` task) also needs the goal (geometry_msgs/PoseStamped on
`--goal-topic`, or with `--goal-point` PointStamped) and the odometry (nav_msgs/Odometry on `--odom-topic`), the node's flags and
defaults (a relative name resolves in the root namespace: `goal_pose` is /goal_pose). The messages
of the three topics go to the loop in their recorded order, each as the node handles it
(`GoalInput.on_goal_msg`, `on_odom_msg`); the plot and the CSV add the goal's distance and bearing
the policy saw, and the shading tells the reasons for zero velocity apart (no goal yet, goal
reached, stale odometry, ...).

A damaged bag stops the replay with one `error: ...` line naming it (exit status 2): storage that
cannot be read (a corrupt SQLite or MCAP file), or a message that cannot be decoded (truncated
CDR), named by its topic and its number on that topic. A bad message is not skipped: without it
the loop would see other data at other times than the node saw, and the replay would show a run
that never happened. The command line is `jaxnav.cli.replay`.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from jaxnav.robot_side.bag import IMAGE, SCAN, decoded, listing, open_bag
from jaxnav.robot_side.ros_node import ControlLoop, make_loop

POSE, POINT = "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PointStamped"
ODOM = "nav_msgs/msg/Odometry"


class ReplayError(ValueError):
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
    """[T] "policy", or why the tick sent zero velocity (no data, stale data, an error; goal
    policies: whatever `GoalInput.problem` reports, e.g. "no goal yet", "goal reached")."""
    goal: np.ndarray | None = None
    """[T, 2] goal policies: the goal the policy saw, distance m and bearing rad from the heading
    (positive = left); NaN where the tick sent zero velocity. None for other policies."""
    inputs: tuple[tuple[str, int], ...] = ()
    """Goal policies: (topic, messages in the bag) of the goal and odometry topics."""


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
            f"{bag}: no single depth image or LaserScan topic, {what}; topics: {listing(topics)}; "
            "use --topic"
        )
    return next(iter(fits))


def goal_topics(topics: dict[str, str], get: dict) -> tuple[str, str]:
    """The bag's (goal, odometry) topics for a goal policy, named by the node's settings
    `goal_topic` and `odom_topic` (relative names in the root namespace, where the node runs)."""
    found = []
    goal = POINT if get.get("goal_point") else POSE  # the type the node subscribes to
    for flag, key, msgtype in (
        ("--goal-topic", "goal_topic", goal),
        ("--odom-topic", "odom_topic", ODOM),
    ):
        name = get[key] if get[key].startswith("/") else f"/{get[key]}"
        if topics.get(name) != msgtype:
            what = f"of type {topics[name]}" if name in topics else "not in the bag"
            raise ReplayError(
                f"{flag} {get[key]}: {name} is {what}, and the goal policy needs its {msgtype} "
                f"there; topics: {listing(topics)}"
            )
        found.append(name)
    return found[0], found[1]


def replay(bag, get: dict, topic: str | None = None, log=None) -> Replay:
    """Runs the node's loop over the bag's topic (and, for a goal policy, its goal and odometry
    topics). `get`: the node's settings (`make_loop`'s, and `goal_topic`, `odom_topic`)."""
    bag = Path(bag)
    reader, typestore = open_bag(bag)
    try:
        topics = {c.topic: c.msgtype for c in reader.connections}
        topic = pick_topic(bag, topics, topic)
        clock = [0.0]
        say = log or (lambda text: print(f"{clock[0]:8.2f} s  {text}"))
        loop, rate = make_loop(dict(get, scan=topics[topic] == SCAN), say)
        inputs = {topic: loop.on_observation}  # topic -> what the node calls with (msg, stamp s)
        if loop.goal is not None:
            goal_topic, odom_topic = goal_topics(topics, get)
            inputs[goal_topic] = lambda msg, stamp: loop.goal.on_goal_msg(msg)
            inputs[odom_topic] = loop.goal.on_odom_msg
        connections = [c for c in reader.connections if c.topic in inputs]
        stamped = decoded(bag, reader, connections, typestore)
        return _run(loop, rate, stamped, inputs, topic, clock)
    finally:
        reader.close()


def _run(loop: ControlLoop, rate: float, stamped, inputs: dict, topic: str, clock: list) -> Replay:
    """Ticks `loop` every 1/rate s from the first message of `stamped` ((ns, topic, msg), in time
    order; each goes to inputs[topic](msg, s)) until the last has gone stale; a message at a tick's
    time arrives before that tick. `topic`: the sensor's."""
    rows, counts, t0, last, k = [], dict.fromkeys(inputs, 0), None, 0, 0
    period = round(1e9 / rate)  # ns, as rclpy's create_timer converts it

    def tick_until(end_ns: int, inclusive: bool) -> None:
        nonlocal k
        while (ns := k * period) < end_ns or (inclusive and ns == end_ns):
            clock[0] = t = ns * 1e-9
            twist = loop.tick(t)
            rows.append((t, loop.obs, twist, loop.state))
            k += 1

    for ns, name, msg in stamped:  # times in integer ns since the first message: ties are exact
        t0 = ns if t0 is None else t0
        last = ns - t0
        tick_until(last, inclusive=False)
        inputs[name](msg, last * 1e-9)
        counts[name] += 1
    if counts[topic] == 0:
        raise ReplayError(f"--topic {topic}: no messages in the bag")
    tick_until(last + round(loop.max_age * 1e9) + period, inclusive=True)  # the final stop
    return _collect(loop, rows, topic, counts)


def _collect(loop: ControlLoop, rows: list, topic: str, counts: dict) -> Replay:
    """The Replay of `rows` ((s, obs or None, twist, state) per tick) and `counts` (topic ->
    messages delivered)."""
    policy = loop.controller.policy
    d, n = policy.observation_size, policy.sensor.num_sectors
    obs = np.array([np.full(d, np.nan) if o is None else o for _, o, _, _ in rows], np.float32)
    goal = None  # [T, 2] distance, bearing from the goal features (distance, sin, cos)
    if loop.goal is not None:
        goal = np.stack([obs[:, n], np.arctan2(obs[:, n + 1], obs[:, n + 2])], axis=1)
    return Replay(
        topic=topic,
        messages=counts.pop(topic),
        time=np.array([r[0] for r in rows]),
        obs=obs[:, :n],
        twist=np.array([tuple(r[2]) for r in rows], np.float64),
        state=tuple(r[3] for r in rows),
        goal=goal,
        inputs=tuple(counts.items()),
    )


def write_csv(result: Replay, path: Path) -> None:
    """One row per tick: time_s, state, obs_0 (rightmost) ..., (goal policies: goal_distance m,
    goal_bearing rad,) linear m/s, angular rad/s."""
    n = result.obs.shape[1]
    goal = np.zeros((len(result.time), 0)) if result.goal is None else result.goal
    names = [] if result.goal is None else ["goal_distance", "goal_bearing"]
    with open(path, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(
            ["time_s", "state", *(f"obs_{i}" for i in range(n)), *names, "linear", "angular"]
        )
        for t, state, obs, g, twist in zip(
            result.time, result.state, result.obs, goal, result.twist, strict=True
        ):
            values = (f"{x:.4f}" for x in (*obs, *g))
            out.writerow([f"{t:.4f}", state, *values, *twist.tolist()])


def _stopped_spans(result: Replay, by_state: bool = False) -> list[tuple[float, float, str]]:
    """(start, end) s of each run of ticks that sent zero velocity, each tick lasting a period, and
    the run's first state; `by_state`: a change of state starts a new run."""
    period = result.time[1] - result.time[0] if len(result.time) > 1 else 0.1
    spans = []
    for t, state in zip(result.time, result.state, strict=True):
        if state == "policy":
            continue
        if spans and np.isclose(spans[-1][1], t) and not (by_state and spans[-1][2] != state):
            spans[-1] = (spans[-1][0], t + period, spans[-1][2])
        else:
            spans.append((t, t + period, state))
    return spans


def _shade_stops(axes, result: Replay) -> None:
    """Shades the ticks that sent zero velocity: grey, or (goal policies) a colour per reason, with
    a legend of the reasons beside the v panel."""
    if result.goal is None:
        for start, end, _ in _stopped_spans(result):
            for ax in axes:
                ax.axvspan(start, end, color="0.85", lw=0)
        return
    colors = {}  # state -> colour, in order of first appearance
    for start, end, state in _stopped_spans(result, by_state=True):
        color = colors.setdefault(state, f"C{len(colors) % 10}")
        for ax in axes:
            ax.axvspan(start, end, color=color, alpha=0.2, lw=0)
    handles = [Patch(color=c, alpha=0.2, label=_short(s)) for s, c in colors.items()]
    if handles:
        axes[-2].legend(
            handles=handles, title="zero velocity", fontsize="small", loc="upper left",
            bbox_to_anchor=(1.0, 1.0),
        )  # fmt: skip


def _short(text: str, most: int = 40) -> str:
    return text if len(text) <= most else text[: most - 3] + "..."


def _plot_goal(ax, result: Replay) -> None:
    """The goal's distance (m, left axis) and bearing (deg, right axis) the policy saw."""
    ax.step(result.time, result.goal[:, 0], where="post", color="k")
    ax.set_ylabel("goal distance (m)")
    bearing = ax.twinx()
    bearing.step(result.time, np.degrees(result.goal[:, 1]), where="post", color="C3")
    bearing.set_ylabel("goal bearing (deg), + left", color="C3")


def plot(result: Replay, path: Path, title: str) -> None:
    """The observations, (goal policies: the goal seen,) and (v, w) over time, ticks that sent zero
    velocity shaded."""
    ratios = [2, 1, 1] if result.goal is None else [2, 1, 1, 1]
    fig = Figure(figsize=(10, 7 if result.goal is None else 9), constrained_layout=True)
    axes = fig.subplots(len(ratios), 1, sharex=True, height_ratios=ratios)
    ax_obs, ax_v, ax_w = axes[0], axes[-2], axes[-1]
    n = result.obs.shape[1]
    colors = [f"C{i % 10}" for i in range(n)]
    for i in range(n):
        side = " (right)" if i == 0 else " (left)" if i == n - 1 else ""
        ax_obs.step(
            result.time, result.obs[:, i], where="post", color=colors[i], label=f"{i}{side}"
        )
    ax_obs.set_ylabel("sector distance (m)")
    ax_obs.legend(title="sector", fontsize="small", loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if result.goal is not None:
        _plot_goal(axes[1], result)
    ax_v.step(result.time, result.twist[:, 0], where="post", color="k")
    ax_v.set_ylabel("v (m/s)")
    ax_w.step(result.time, result.twist[:, 1], where="post", color="k")
    ax_w.set_ylabel("w (rad/s), + left")
    ax_w.set_xlabel(f"time since the first message (s); {result.topic}")
    _shade_stops(axes, result)
    for ax in axes:
        ax.grid(alpha=0.3)
    ax_obs.set_title(title)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":  # `python -m jaxnav.replay`: the command line
    import sys

    from jaxnav.cli.replay import main

    sys.exit(main())
