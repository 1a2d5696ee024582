"""`python -m jaxnav.replay`: a real rosbag2, written with rosbags, replayed through the node's loop."""

import csv
import math

import numpy as np
import pytest
from test_robot_side import BAD_CONTENT, DAMAGE, bounded, damaged, write_policy_npz

from jaxnav import replay
from jaxnav.cli import replay as replay_cli
from jaxnav.robot_side.observation import Controller
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.robot_side.ros_node import ControlLoop, MessageReader

rosbags = pytest.importorskip("rosbags", reason="needs rosbags (pip install 'jaxnav[ros]')")
from rosbags.rosbag2 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
T0 = 1_700_000_000_000_000_000  # ns: the bag's clock
DEPTH, SCAN, RGB = "/camera/depth/image_raw", "/scan", "/camera/rgb/image_raw"


def header(ns: int, frame: str = "camera"):
    stamp = TS.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return TS.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def image(ns: int, pixels: np.ndarray, encoding: str = "32FC1"):
    h, w = pixels.shape[:2]
    data = np.frombuffer(pixels.tobytes(), np.uint8)
    return TS.types["sensor_msgs/msg/Image"](
        header=header(ns), height=h, width=w, encoding=encoding, is_bigendian=0,
        step=data.size // h, data=data,
    )  # fmt: skip


def scan(ns: int, ranges: np.ndarray):
    n = ranges.size
    return TS.types["sensor_msgs/msg/LaserScan"](
        header=header(ns), angle_min=-0.7, angle_max=0.7, angle_increment=1.4 / (n - 1),
        time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=12.0,
        ranges=ranges.astype(np.float32), intensities=np.zeros(0, np.float32),
    )  # fmt: skip


def depth_frames():
    """(t_ns since T0, message): 30 Hz frames, a stall, an undecodable frame, frames again."""
    rng = np.random.default_rng(0)
    out = []
    for i, t in enumerate([*(j / 30 for j in range(16)), 1.2, 1.25, 1.3, 1.45, 1.5]):
        far = (4.0, 6.0) if i % 2 else (0.7, 1.5)  # open space / cluttered, in turns
        depth = rng.uniform(*far, (48, 64)).astype(np.float32)
        depth[:, rng.integers(0, 56) :][:, :8] = 0.0 if i % 4 == 0 else 0.8  # a near patch
        out.append((round(t * 1e9), image(T0 + round(t * 1e9), depth)))
    rgb = np.zeros((48, 64, 3), np.uint8)
    out.append((round(1.0 * 1e9), image(T0 + 10**9, rgb, "rgb8")))  # on the depth topic: error
    return sorted(out, key=lambda x: x[0])


def scan_frames():
    rng = np.random.default_rng(1)
    times = [0.0, 0.1, 0.2, 0.31, 0.4, 0.9, 1.0]  # 0.4 -> 0.9: the scanner stalls
    return [(round(t * 1e9), scan(T0 + round(t * 1e9), rng.uniform(0.3, 9.0, 90))) for t in times]


def write_bag(path, topics: dict):
    """A rosbag2 at `path` holding topic -> [(t_ns since T0, message)]."""
    with Writer(path, version=9) as writer:
        for topic, frames in topics.items():
            conn = writer.add_connection(topic, frames[0][1].__msgtype__, typestore=TS)
            for t, msg in frames:
                writer.write(conn, T0 + t, TS.serialize_cdr(msg, msg.__msgtype__))
    return path


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bags")
    rgb = [(0, image(T0, np.zeros((48, 64, 3), np.uint8), "rgb8"))]
    return write_bag(folder / "rec", {DEPTH: depth_frames(), SCAN: scan_frames(), RGB: rgb})


def direct(policy, frames, reader, rate=10.0, max_age=0.25):
    """(times, twists, states) of a ControlLoop driven by hand: ticks every 1/rate s from the first
    frame until the last one is stale, each frame delivered before the ticks at or after it."""
    loop = ControlLoop(Controller(policy), reader, max_age, log=lambda text: None)
    fields = [(t * 1e-9, msg) for t, msg in frames]
    end, out, pending = fields[-1][0] + max_age + 1 / rate, [], list(fields)
    for k in range(int(end * rate + 1e-9) + 1):
        now = k * round(1e9 / rate) * 1e-9
        while pending and pending[0][0] <= now:
            loop.on_observation(pending[0][1], pending[0][0])
            pending.pop(0)
        twist = loop.tick(now)
        out.append((now, tuple(twist), loop.state, loop.obs))
    return out


def read_csv(path):
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    obs = np.array([[float(r[f"obs_{i}"]) for i in range(8)] for r in rows])
    twists = [(float(r["linear"]), float(r["angular"])) for r in rows]
    return [float(r["time_s"]) for r in rows], twists, [r["state"] for r in rows], obs


@pytest.mark.parametrize("topic, frames, scan_topic", [(DEPTH, depth_frames, False), (SCAN, scan_frames, True)])  # fmt: skip
def test_replay_equals_the_node_loop(bag, tmp_path, capsys, topic, frames, scan_topic):
    npz = write_policy_npz(tmp_path / "policy.npz")
    args = [str(bag), "--policy", str(npz), "--topic", topic, "--csv", str(tmp_path / "r.csv")]
    assert replay_cli.main(args) == 0, capsys.readouterr().err
    times, twists, states, obs = read_csv(tmp_path / "r.csv")
    want = direct(NumpyPolicy.from_npz(npz), frames(), MessageReader(scan=scan_topic))
    assert times == pytest.approx([w[0] for w in want], abs=1e-4)
    assert twists == [w[1] for w in want]
    assert states == [w[2] for w in want]
    want_obs = np.array([np.full(8, np.nan) if w[3] is None else w[3] for w in want])
    np.testing.assert_allclose(obs, want_obs, atol=1e-4)
    # The replay saw everything the node must handle: driving, a stall and (images) an error.
    assert "policy" in states and "no sensor message for over 0.25 s" in states
    assert states[-1] != "policy" and len({t for t in twists if t != (0.0, 0.0)}) >= 2
    assert any(s.startswith("error: ValueError") for s in states) != scan_topic
    png = bag.parent / "rec.replay.png"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    out = capsys.readouterr().out
    assert f"wrote {png}" in out and "sending zero velocity" in out


def test_replay_options_reach_the_loop(bag, tmp_path):
    """The node's flags apply: a slower rate, a speed calibration, a longer max age."""
    npz = write_policy_npz(tmp_path / "policy.npz", control_period=np.float64(0.2))
    args = [str(bag), "--policy", str(npz), "--topic", SCAN, "--plot", str(tmp_path / "p.png")]
    args += ["--csv", str(tmp_path / "r.csv"), "--speed-calibration", "2", "--max-age", "1"]
    assert replay_cli.main(args) == 0
    times, twists, states, _ = read_csv(tmp_path / "r.csv")
    policy = NumpyPolicy.from_npz(npz)
    loop = direct(policy, scan_frames(), MessageReader(scan=True), rate=5.0, max_age=1.0)
    assert times == pytest.approx([w[0] for w in loop], abs=1e-4) and times[1] == 0.2
    assert twists == [tuple(2 * x for x in w[1]) for w in loop]
    assert "no sensor message for over 0.25 s" not in states  # the stall is shorter than 1 s
    assert (tmp_path / "p.png").is_file()


def test_topic_is_found_when_one_fits(tmp_path, capsys):
    bag = write_bag(tmp_path / "only-depth", {DEPTH: depth_frames()[:3], RGB: depth_frames()[:1]})
    npz = write_policy_npz(tmp_path / "policy.npz")
    assert replay_cli.main([str(bag), "--policy", str(npz)]) == 0
    assert f"\n{DEPTH}: 3 messages" in capsys.readouterr().out
    assert (tmp_path / "only-depth.replay.png").is_file()


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing"], "missing: no such rosbag2 (a folder holding metadata.yaml)"),
        ([], "no single depth image or LaserScan topic, several fit (/camera/depth/image_raw, "),
        (["--topic", RGB, "--csv", "nowhere/r.csv"], "--csv nowhere/r.csv: no folder nowhere"),
        (["--topic", "/tf"], "--topic /tf: not in the bag; depth image or LaserScan topics: "),
        (["--topic", SCAN, "--policy", "bad.npz"], "bad.npz: unreadable policy file"),
        (["--topic", SCAN, "--max-age", "0"], "max_age: must be > 0 s, got 0.0"),
    ],
)
def test_mistakes_are_one_line(bag, tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    write_policy_npz(tmp_path / "policy.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a policy")
    if args[:1] == ["missing"]:
        args = [str(tmp_path / "missing"), *args[1:]]
        message = f"{tmp_path}/{message}"
    else:
        args = [str(bag), *args]
    if "--policy" not in args:
        args += ["--policy", "policy.npz"]
    assert replay_cli.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1, err


def test_no_fitting_topic(tmp_path, capsys):
    bag = write_bag(
        tmp_path / "rgb", {RGB: [(0, image(T0, np.zeros((4, 8, 3), np.uint8), "rgb8"))]}
    )
    npz = write_policy_npz(tmp_path / "policy.npz")
    assert replay_cli.main([str(bag), "--policy", str(npz)]) == 2
    err = capsys.readouterr().err
    assert "none fits; topics: /camera/rgb/image_raw (sensor_msgs/msg/Image); use --topic" in err


GOAL, ODOM, START, TARGET = "/goal_pose", "/odom", (-0.5, -0.4), (1.2, 0.6)
NO_GOAL = [(DEPTH, "sensor_msgs/msg/Image"), (ODOM, "nav_msgs/msg/Odometry")]


def write_goal_policy_npz(path):
    """A continuous goal policy in export format 3: 8 sectors, goal features, last command."""
    rng = np.random.default_rng(2)
    scale, low, high = [0.5, 1.5], [0.0, -1.5], [0.5, 1.5]
    return write_policy_npz(
        path, W0=rng.normal(size=(13, 16)).astype(np.float32), b1=np.zeros(2, np.float32),
        W1=rng.normal(scale=0.2, size=(16, 2)).astype(np.float32),
        obs_mean=np.array([3.0] * 8 + [1.0, 0, 0, 0.25, 0], np.float32),
        obs_var=np.full(13, 4.0, np.float32), obs_std=np.full(13, 2.0, np.float32),
        action_names=np.array(["forward", "yaw"]), commands=np.array([low, high], np.float32),
        action_low=np.array(low, np.float32), action_high=np.array(high, np.float32),
        extra_observations=np.int32(5), command_scale=np.array(scale, np.float32),
        success_radius=np.float64(0.3), format_version=np.int32(3),
    )  # fmt: skip


def pose_at(t: float):
    """The recorded robot's (x, y, yaw) at t s: a straight line to the goal, reached at 1.8 s,
    turning from side to side (yaw beyond pi: the bearing wraps)."""
    f = min(t / 1.8, 1.0)
    x, y = (a + f * (b - a) for a, b in zip(START, TARGET, strict=True))
    return x, y, 0.3 + 3.0 * math.sin(2.0 * t)


def pose_msg(x: float, y: float, yaw: float):
    t = TS.types
    q = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    return t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0), orientation=q)  # fmt: skip


def odometry(ns: int, x: float, y: float, yaw: float):
    t, cov = TS.types, np.zeros(36)
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return t["nav_msgs/msg/Odometry"](
        header=header(ns, "odom"), child_frame_id="base_footprint",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(x, y, yaw), covariance=cov),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=cov
        ),
    )  # fmt: skip


def goal_frames():
    """topic -> [(t_ns, message)]: 15 Hz depth, 20 Hz odometry with a 0.4 s gap after 1.0 s
    (times on the ticks' 0.1 s grid: a message at a tick's time comes first), one goal at 0.45 s."""
    rng = np.random.default_rng(3)
    depth = []
    for j in range(30):
        ns = round(j / 15 * 1e9)
        depth.append((ns, image(T0 + ns, rng.uniform(0.8, 5.0, (24, 32)).astype(np.float32))))
    odom = [(j * 50_000_000, pose_at(j * 0.05)) for j in range(41)]
    odom = [(ns, odometry(T0 + ns, *pose)) for ns, pose in odom if not 1.0e9 < ns < 1.4e9]
    goal = TS.types["geometry_msgs/msg/PoseStamped"](
        header=header(T0 + 450_000_000, "odom"), pose=pose_msg(*TARGET, 0.0)
    )
    return {DEPTH: depth, ODOM: odom, GOAL: [(450_000_000, goal)]}


@pytest.fixture(scope="module")
def goal_bag(tmp_path_factory):
    folder = tmp_path_factory.mktemp("goal")
    return write_bag(folder / "rec", goal_frames()), write_goal_policy_npz(folder / "policy.npz")


def newest(frames, now: int):
    """The last (t_ns, message) of `frames` at or before `now` ns, or (None, None)."""
    return max((f for f in frames if f[0] <= now), default=(None, None), key=lambda f: f[0])


def expected_goal_ticks(policy, frames, ticks):
    """(state, twist, goal distance, bearing) per tick time (ns), from the recorded messages: the
    newest of each topic at or before the tick, the goal turned into the frame of the recorded
    pose of the newest odometry; the command sent is fed back (zero after a stop)."""
    controller, last, out = Controller(policy), np.zeros(2), []
    for now in ticks:
        (t_img, img), (t_goal, _), (t_odom, _) = (
            newest(frames[k], now) for k in (DEPTH, GOAL, ODOM)
        )
        x, y, yaw = pose_at(t_odom * 1e-9)
        dx, dy = TARGET[0] - x, TARGET[1] - y
        ahead, left = (
            math.cos(yaw) * dx + math.sin(yaw) * dy,
            math.cos(yaw) * dy - math.sin(yaw) * dx,
        )
        distance, bearing = math.hypot(ahead, left), math.atan2(left, ahead)
        state = "goal reached" if distance <= 0.3 else "policy"
        if now - t_img > 250_000_000:
            state = "no sensor message for over 0.25 s"
        elif t_goal is None:
            state = "no goal yet"
        elif now - t_odom > 250_000_000:
            state = "no odometry for over 0.25 s"
        if state != "policy":
            last = np.zeros(2)
            out.append((state, (0.0, 0.0), math.nan, math.nan))
            continue
        features = [distance, math.sin(bearing), math.cos(bearing)]
        obs = np.concatenate([MessageReader()(img, controller), features, last / [0.5, 1.5]])
        last = np.array(controller.act(obs))
        out.append((state, tuple(last), distance, bearing))
    return out


def test_goal_policy_replays_goal_and_odometry(goal_bag, tmp_path, capsys):
    """Depth, odometry and the goal reach the loop in recorded order: the goal features the policy
    saw are the goal in the frame of the newest odometry pose, and it stops before the goal, on
    stale odometry and at the goal."""
    (bag, npz), table = goal_bag, tmp_path / "goal.csv"
    args = [
        str(bag),
        "--policy",
        str(npz),
        "--plot",
        str(tmp_path / "goal.png"),
        "--csv",
        str(table),
    ]
    assert replay_cli.main(args) == 0
    with open(table) as fh:
        rows = list(csv.DictReader(fh))
    ticks = [k * 100_000_000 for k in range(len(rows))]
    want = expected_goal_ticks(NumpyPolicy.from_npz(npz), goal_frames(), ticks)
    states = [w[0] for w in want]
    assert [float(r["time_s"]) for r in rows] == pytest.approx([t * 1e-9 for t in ticks], abs=1e-4)
    assert [r["state"] for r in rows] == states
    got = np.array([[float(r[k]) for k in ("goal_distance", "goal_bearing", "linear", "angular")] for r in rows])  # fmt: skip
    distance, bearing = np.array([w[2:] for w in want]).T
    np.testing.assert_allclose(got[:, 0], distance, atol=2e-4)  # NaN where it stopped, in both
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 1] - bearing))), 0 * bearing, atol=2e-4)
    np.testing.assert_allclose(got[:, 2:], [w[1] for w in want], atol=1e-4)
    assert (
        states[:5] == ["no goal yet"] * 5 and (got[:5, 2:] == 0).all()
    )  # the goal comes at 0.45 s
    assert {"no odometry for over 0.25 s", "goal reached"} <= set(states) and states[-1] != "policy"
    assert states.count("policy") >= 8 and (np.abs(bearing) > 2.5).any()  # bearings wrap past pi
    assert len({w[1] for w in want if w[0] == "policy"}) >= 4  # the commands vary
    out = capsys.readouterr().out
    assert "goal reached: sending zero velocity" in out
    assert f"; goal inputs: 1 on {GOAL}, 34 on {ODOM}; wrote" in out


def test_goal_policy_replays_a_point_goal(goal_bag, tmp_path):
    """A goal as geometry_msgs/PointStamped (RViz's Publish Point, the node's --goal-point) on
    another topic replays as the PoseStamped goal does; without --goal-point the replay says
    which type the node would subscribe to."""
    bag, npz = goal_bag
    frames = goal_frames()
    ns, pose = frames.pop(GOAL)[0]
    point = TS.types["geometry_msgs/msg/PointStamped"](header=pose.header, point=pose.pose.position)
    frames["/clicked_point"] = [(ns, point)]
    points = write_bag(tmp_path / "points", frames)
    get = dict(vars(replay_cli.parse_args([str(bag), "--policy", str(npz)])))
    want = replay.replay(bag, get, log=lambda text: None)
    get.update(goal_topic="/clicked_point", goal_point=True)
    got = replay.replay(points, get, log=lambda text: None)
    assert got.state == want.state and "goal reached" in got.state
    np.testing.assert_array_equal(got.twist, want.twist)
    np.testing.assert_array_equal(got.goal, want.goal)
    with pytest.raises(replay.ReplayError, match="needs its geometry_msgs/msg/PoseStamped there"):
        replay.replay(points, {**get, "goal_point": False}, log=lambda text: None)


@pytest.mark.parametrize(
    "drop, flags, message",
    [
        (GOAL, [], f"--goal-topic goal_pose: {GOAL} is not in the bag, and the goal policy needs its geometry_msgs/msg/PoseStamped there; topics: {', '.join(f'{n} ({t})' for n, t in NO_GOAL)}"),
        (None, ["--odom-topic", "/robot/odom"], "--odom-topic /robot/odom: /robot/odom is not in the bag, and the goal policy needs its nav_msgs/msg/Odometry there; topics: "),
        (None, ["--goal-topic", "odom"], f"--goal-topic odom: {ODOM} is of type nav_msgs/msg/Odometry, and the goal policy needs its geometry_msgs/msg/PoseStamped"),
    ],
)  # fmt: skip
def test_goal_policy_needs_goal_and_odometry_topics(
    goal_bag, tmp_path, capsys, drop, flags, message
):
    bag, npz = goal_bag
    if drop is not None:
        bag = write_bag(tmp_path / "rec", {k: v for k, v in goal_frames().items() if k != drop})
    args = [str(bag), "--policy", str(npz), "--plot", str(tmp_path / "p.png"), *flags]
    assert replay_cli.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1, err


@pytest.mark.parametrize("kind", [*BAD_CONTENT, *DAMAGE])
def test_bad_policy_file_is_one_line(bag, tmp_path, capsys, kind):
    """A damaged, special or refused --policy: one line naming it, exit 2; a FIFO does not block."""
    path, message = damaged(kind, tmp_path)
    args = [str(bag), "--policy", str(path), "--topic", SCAN, "--plot", str(tmp_path / "p.png")]
    assert bounded(replay_cli.main, args, fifo=path if kind == "fifo" else None) == 2
    assert capsys.readouterr().err == f"error: {path}: {message}\n"
    assert not (tmp_path / "p.png").exists()


def write_damaged_bag(path, frames, bad: int | None = None):
    """A rosbag2 of depth `frames` whose message `bad` (counting from 0) holds truncated CDR."""
    with Writer(path, version=9) as writer:
        conn = writer.add_connection(DEPTH, replay.IMAGE, typestore=TS)
        for i, (t, msg) in enumerate(frames):
            raw = TS.serialize_cdr(msg, msg.__msgtype__)
            writer.write(conn, T0 + t, raw[:60] if i == bad else raw)
    return path


def corrupt_page(db, needle: bytes) -> None:
    """Overwrites the header of the SQLite page holding `needle` (the page size is in the file's
    header, bytes 16-17)."""
    data = bytearray(db.read_bytes())
    size = int.from_bytes(data[16:18], "big")
    page = data.find(needle) // size * size
    data[page : page + 16] = b"\xff" * 16
    db.write_bytes(bytes(data))


def test_damaged_bag_is_one_line(tmp_path, capsys):
    """A message of truncated CDR and a corrupt SQLite page each stop the replay: one line naming
    the bag (and the message), exit 2, no traceback."""
    npz, frames = write_policy_npz(tmp_path / "policy.npz"), depth_frames()
    bag = write_damaged_bag(tmp_path / "cdr", frames, bad=3)
    assert replay_cli.main([str(bag), "--policy", str(npz)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {bag}: {DEPTH}: message 4 on that topic cannot be decoded as ")
    assert "sensor_msgs/msg/Image (Invalid sequence length" in err and err.count("\n") == 1, err
    assert err.endswith("; the bag is damaged\n") and not (tmp_path / "cdr.replay.png").exists()

    bag = write_damaged_bag(tmp_path / "sqlite", frames)
    raw = bytes(TS.serialize_cdr(frames[5][1], replay.IMAGE))
    corrupt_page(bag / "sqlite.db3", raw[4000:4064])  # inside message 5's data
    assert replay_cli.main([str(bag), "--policy", str(npz)]) == 2
    err = capsys.readouterr().err
    want = f"error: {bag}: unreadable rosbag2 after 5 messages (database disk image is malformed)\n"
    assert err == want
