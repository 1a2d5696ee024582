"""`python -m jaxnav.replay`: a real rosbag2, written with rosbags, replayed through the node's loop."""

import csv

import numpy as np
import pytest
from test_robot_side import write_policy_npz

from jaxnav import replay
from jaxnav.robot_side.observation import Controller
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.robot_side.ros_node import ControlLoop, MessageReader

rosbags = pytest.importorskip("rosbags", reason="needs rosbags (pip install 'jaxnav[ros]')")
from rosbags.rosbag2 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
T0 = 1_700_000_000_000_000_000  # ns: the bag's clock
DEPTH, SCAN, RGB = "/camera/depth/image_raw", "/scan", "/camera/rgb/image_raw"


def header(ns: int):
    stamp = TS.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return TS.types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera")


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
    assert replay.main(args) == 0, capsys.readouterr().err
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
    assert replay.main(args) == 0
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
    assert replay.main([str(bag), "--policy", str(npz)]) == 0
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
    assert replay.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1, err


def test_no_fitting_topic(tmp_path, capsys):
    bag = write_bag(
        tmp_path / "rgb", {RGB: [(0, image(T0, np.zeros((4, 8, 3), np.uint8), "rgb8"))]}
    )
    npz = write_policy_npz(tmp_path / "policy.npz")
    assert replay.main([str(bag), "--policy", str(npz)]) == 2
    err = capsys.readouterr().err
    assert "none fits; topics: /camera/rgb/image_raw (sensor_msgs/msg/Image); use --topic" in err
