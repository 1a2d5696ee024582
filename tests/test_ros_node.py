"""The ROS 2 node's safety: its own control rate, the stale-data watchdog, errors and shutdown stop.

`ControlLoop` is driven with a fake clock; the node and `main` run against stand-ins for rclpy and
the message packages, put into sys.modules, so no ROS install is needed.
"""

import math
import signal
import sys
import types

import numpy as np
import pytest
from test_robot_side import (
    BAD_CONTENT,
    DAMAGE,
    NanPolicy,
    bounded,
    damaged,
    floor_image,
    write_policy_npz,
)

from jaxnav.robot_side import ros_node
from jaxnav.robot_side.observation import Controller, Twist, horizon_rows
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.robot_side.ros_node import (
    STOP,
    ControlLoop,
    MessageReader,
    control_rate,
    image_msg_to_array,
    scan_msg_to_arrays,
)

NAN, INF = float("nan"), float("inf")


def image_msg(depth_m: np.ndarray):
    """A sensor_msgs/Image-like message of a 32FC1 depth image (metres)."""
    depth = np.asarray(depth_m, np.float32)
    h, w = depth.shape
    return types.SimpleNamespace(
        encoding="32FC1", height=h, width=w, data=depth.tobytes(), step=4 * w, is_bigendian=0
    )


def scene(left: float, right: float, h: int = 48, w: int = 64) -> np.ndarray:
    """A depth image: `left` m in the left eighth of the columns, `right` m elsewhere."""
    depth = np.full((h, w), right, np.float32)
    depth[:, : w // 8] = left
    return depth


@pytest.fixture
def policy(tmp_path):
    return NumpyPolicy.from_npz(write_policy_npz(tmp_path / "policy.npz"))


class Counting:
    """Wraps a policy, counting forward passes."""

    def __init__(self, policy):
        self.policy, self.calls = policy, 0
        self.sensor, self.commands = policy.sensor, policy.commands

    def __call__(self, obs):
        self.calls += 1
        return self.policy(obs)


class Raising(Counting):
    """A policy whose forward pass fails."""

    def __call__(self, obs):
        raise FloatingPointError("weights went bad")


def expected(policy, depth) -> Twist:
    """What the node must send for a fresh depth image (the default reader's rows)."""
    rows = horizon_rows(depth.shape[0], math.radians(49.5), 2.0)
    return Controller(policy).image_to_twist(depth, rows)


def test_several_row_policies_read_their_rays_floor_left_out(tmp_path):
    """A 5-row policy reads the pixels of its rays with the floor rule (a wall at 5 m behind
    the floor reads 5 m); the camera height and pitch parameters override the file's."""
    elevations = np.linspace(-0.38, 0.17, 5)  # SensorConfig(rows=5).elevations
    npz = write_policy_npz(tmp_path / "p.npz", elevations=elevations, camera_height=0.295)
    controller = Controller(NumpyPolicy.from_npz(npz))
    msg = image_msg(floor_image())
    np.testing.assert_allclose(MessageReader()(msg, controller), 5.0, rtol=1e-6)
    # Told the camera is 5 cm higher than it is, the floor seems 5 cm up: obstacles.
    assert MessageReader(camera_height=0.345)(msg, controller).max() < 1.0
    assert MessageReader(tilt_deg=-3.0)(msg, controller).max() < 1.0  # said to look up 3 deg
    with pytest.raises(ValueError, match="camera_height: must be > 0 m"):
        MessageReader(camera_height=0.0)


def test_image_message_conversion():
    depth = np.array([[0.5, 1.0, NAN], [2.0, 0.0, 8.5]], np.float32)
    padded = b"".join(r.tobytes() + b"\xff" * 4 for r in depth)  # step = 3 * 4 + 4 bytes
    np.testing.assert_array_equal(image_msg_to_array("32FC1", 2, 3, padded, 16), depth)
    mm = np.array([[600, 0, 65535], [1234, 8000, 1]], np.uint16)
    got = image_msg_to_array("16UC1", 2, 3, mm.tobytes(), 6)
    np.testing.assert_allclose(got, mm / 1000.0, rtol=1e-6)
    assert got.dtype == np.float32 and got[0, 1] == 0.0  # no data stays 0: unknown
    big = mm.astype(">u2").tobytes()
    np.testing.assert_allclose(
        image_msg_to_array("16UC1", 2, 3, big, 6, is_bigendian=True), mm / 1000.0
    )
    with pytest.raises(ValueError, match="rgb8"):
        image_msg_to_array("rgb8", 2, 3, bytes(18), 9)
    with pytest.raises(ValueError, match="too short"):
        image_msg_to_array("32FC1", 2, 3, bytes(20), 12)


def test_scan_and_twist_message_conversion():
    ranges, angles = scan_msg_to_arrays([1.0, INF, 2.0], -0.5, 0.25)
    np.testing.assert_allclose(angles, [-0.5, -0.25, 0.0])
    assert ranges.dtype == np.float32 and np.isinf(ranges[1])
    msg = ros_node.twist_msg(Twist(0.5, -1.5), FakeRos.Twist)
    assert (msg.linear.x, msg.angular.z, msg.linear.y) == (0.5, -1.5, 0.0)


def test_control_rate(tmp_path, policy):
    assert control_rate(policy) == 10.0  # the file does not say
    assert control_rate(policy, 4.0) == 4.0
    slow = NumpyPolicy.from_npz(
        write_policy_npz(tmp_path / "p.npz", control_period=np.float32(0.2))
    )
    assert slow.control_period == pytest.approx(0.2) and control_rate(slow) == pytest.approx(5.0)
    with pytest.raises(ValueError, match="rate_hz: must be > 0"):
        control_rate(policy, 0.0)


def test_loop_acts_on_the_newest_message_at_its_own_rate(policy):
    """A 30 Hz camera and a 10 Hz timer: each tick acts on the newest frame, once per frame."""
    counting = Counting(policy)
    log = []
    loop = ControlLoop(Controller(counting), MessageReader(), log=log.append)
    frames = [scene(0.9 + 0.4 * i, 3.0 + 0.3 * i) for i in range(9)]
    sent = []
    for i, frame in enumerate(frames):  # frames at 30 Hz, ticks every third frame (10 Hz)
        t = i / 30
        loop.on_observation(image_msg(frame), t)
        if i % 3 == 2:
            sent.append(loop.tick(t + 0.01))
            sent.append(loop.tick(t + 0.02))  # a second tick on the same frame: no new forward pass
    want = [expected(policy, frames[i]) for i in (2, 2, 5, 5, 8, 8)]
    assert np.array(sent) == pytest.approx(np.array(want)) and counting.calls == 3
    assert loop.state == "policy" and loop.obs.shape == (8,)
    assert log == ["policy: driving"]


def test_watchdog_stops_on_stale_data(policy):
    log = []
    loop = ControlLoop(Controller(policy), MessageReader(), max_age=0.25, log=log.append)
    assert loop.tick(0.0) == STOP and loop.state == "no sensor message yet" and loop.obs is None
    frame = scene(1.0, 4.0)
    loop.on_observation(image_msg(frame), 1.0)
    assert loop.tick(1.25) == pytest.approx(expected(policy, frame))  # exactly max_age: fresh
    assert loop.tick(1.26) == STOP and loop.obs is None
    assert loop.tick(5.0) == STOP
    loop.on_observation(image_msg(frame), 5.1)  # the camera is back
    assert loop.tick(5.2) == pytest.approx(expected(policy, frame))
    assert log == [  # each change once
        "policy: driving",
        "no sensor message for over 0.25 s: sending zero velocity",
        "policy: driving",
    ]


def test_errors_send_zero_and_the_loop_carries_on(policy):
    log = []
    loop = ControlLoop(Controller(policy), MessageReader(), log=log.append)
    bad = image_msg(scene(1.0, 4.0))
    bad.encoding = "rgb8"
    loop.on_observation(bad, 0.0)
    assert loop.tick(0.05) == STOP and loop.tick(0.1) == STOP
    assert len(log) == 1 and log[0].startswith("error: ValueError: image encoding 'rgb8'")
    truncated = image_msg(scene(1.0, 4.0))
    truncated.data = truncated.data[:100]
    loop.on_observation(truncated, 0.2)
    assert loop.tick(0.2) == STOP and "too short" in log[-1]
    frame = scene(1.0, 4.0)
    loop.on_observation(image_msg(frame), 0.3)
    assert loop.tick(0.3) == pytest.approx(expected(policy, frame)) and loop.state == "policy"

    loop = ControlLoop(Controller(Raising(policy)), MessageReader(), log=log.append)
    loop.on_observation(image_msg(frame), 0.0)
    assert loop.tick(0.0) == STOP
    assert log[-1] == "error: FloatingPointError: weights went bad: sending zero velocity"


def test_shutdown_stops_for_good(policy):
    loop = ControlLoop(Controller(policy), MessageReader(scan=True), log=lambda text: None)
    scan = types.SimpleNamespace(ranges=[2.0] * 90, angle_min=-0.7, angle_increment=1.4 / 89)
    loop.on_observation(scan, 0.0)
    assert loop.tick(0.0) != STOP
    assert loop.shutdown() == STOP and loop.state == "shut down"
    loop.on_observation(scan, 0.1)
    assert loop.tick(0.1) == STOP


def test_node_flags():
    args, rest = ros_node.parse_args(["--policy", "p.npz", "--scan", "--ros-args", "-p", "x:=1"])
    assert args.policy == "p.npz" and args.scan and rest == ["--ros-args", "-p", "x:=1"]
    assert args.speed_calibration == 1.0 and args.band_deg == 2.0 and args.rate_hz is None
    assert args.max_age == 0.25 and args.blind_fraction == 0.5


class FakeRos:
    """Stand-ins for rclpy, its Node, timers and publishers, and the message classes."""

    class Vector:
        x = y = z = 0.0

    class Twist:
        def __init__(self):
            self.linear, self.angular = FakeRos.Vector(), FakeRos.Vector()

    def __init__(self, params=None, spin=None):
        self.time, self.params, self.spin_body = 0.0, params or {}, spin
        self.events, self.nodes = [], []  # ("publish", (v, w)) / ("init", kwargs) / ("shutdown",)

    def modules(self, signals: bool = True) -> dict:
        ros = self

        class Node:
            def __init__(self, name):
                self.subscriptions_, self.timers_ = [], []
                ros.nodes.append(self)

            def declare_parameter(self, name, value):
                return types.SimpleNamespace(value=ros.params.get(name, value))

            def create_publisher(self, msg_type, topic, depth):
                self.cmd_topic = topic
                publish = lambda m: ros.events.append(("publish", (m.linear.x, m.angular.z)))
                return types.SimpleNamespace(publish=publish)

            def create_subscription(self, msg_type, topic, callback, qos):
                self.subscriptions_.append((msg_type.__name__, topic, callback))

            def create_timer(self, period, callback):
                self.timers_.append((period, callback))

            def get_clock(self):
                now = lambda: types.SimpleNamespace(nanoseconds=int(round(ros.time * 1e9)))
                return types.SimpleNamespace(now=now)

            def get_logger(self):
                log = lambda text: ros.events.append(("log", text))
                return types.SimpleNamespace(info=log, warning=log)

            def destroy_node(self):
                ros.events.append(("destroy",))

        rclpy = types.SimpleNamespace(
            init=lambda **kw: self.events.append(("init", kw)),
            spin=lambda node: self.spin_body(self, node),
            try_shutdown=lambda: self.events.append(("shutdown",)),
        )
        image, scan = type("Image", (), {}), type("LaserScan", (), {})
        return {
            "rclpy": rclpy,
            "rclpy.node": types.SimpleNamespace(Node=Node),
            "rclpy.qos": types.SimpleNamespace(qos_profile_sensor_data=None),
            "rclpy.signals": types.SimpleNamespace(SignalHandlerOptions=types.SimpleNamespace(NO=0))
            if signals
            else None,  # None in sys.modules: ImportError, as on Foxy
            "sensor_msgs": types.SimpleNamespace(),
            "sensor_msgs.msg": types.SimpleNamespace(Image=image, LaserScan=scan),
            "geometry_msgs": types.SimpleNamespace(),
            "geometry_msgs.msg": types.SimpleNamespace(Twist=FakeRos.Twist),
        }

    def install(self, monkeypatch, signals: bool = True):
        for name, module in self.modules(signals).items():
            monkeypatch.setitem(sys.modules, name, module)
        return self

    def published(self):
        return [e[1] for e in self.events if e[0] == "publish"]


@pytest.mark.parametrize(
    "file_period, params, period",
    [(None, {}, 0.1), (0.2, {}, 0.2), (0.2, {"rate_hz": 4.0}, 0.25)],
)
def test_node_timer_rate(monkeypatch, tmp_path, file_period, params, period):
    """The timer runs at rate_hz: the parameter, else 1 / the policy's control period, else 10."""
    extra = {} if file_period is None else {"control_period": np.float32(file_period)}
    npz = str(write_policy_npz(tmp_path / "policy.npz", **extra))
    FakeRos(params).install(monkeypatch)
    node = ros_node._make_node(ros_node.parse_args(["--policy", npz])[0])
    assert [p for p, _ in node.timers_] == [pytest.approx(period)]


def test_node_wiring_and_watchdog(monkeypatch, tmp_path, policy):
    """Messages only update the newest reading; the timer publishes; stale data publishes zero."""
    npz = str(write_policy_npz(tmp_path / "policy.npz"))
    ros = FakeRos({"speed_calibration": 2.0}).install(monkeypatch)
    node = ros_node._make_node(ros_node.parse_args(["--policy", npz])[0])
    (kind, topic, on_message), (_, on_timer) = node.subscriptions_[0], node.timers_[0]
    assert (kind, topic, node.cmd_topic) == ("Image", "/camera/depth/image_raw", "cmd_vel")
    frame = scene(0.9, 3.0)
    ros.time = 10.0
    on_message(image_msg(frame))
    assert ros.published() == []  # no command per camera frame
    ros.time = 10.1
    on_timer()
    rows = horizon_rows(48, math.radians(49.5), 2.0)
    want = Controller(policy, speed_calibration=2.0).image_to_twist(frame, rows)
    assert ros.published() == [pytest.approx(want)] and want != STOP
    ros.time = 10.3  # 0.3 s after the frame
    on_timer()
    assert ros.published()[-1] == (0.0, 0.0)
    assert ("log", "no sensor message for over 0.25 s: sending zero velocity") in ros.events

    args, _ = ros_node.parse_args(["--policy", npz, "--scan", "--topic", "/scan"])
    node = ros_node._make_node(args)
    assert node.subscriptions_[0][:2] == ("LaserScan", "/scan")


def drive_then_signal(signum):
    """A spin that drives for two ticks, then receives `signum` as from the keyboard or kill."""

    def spin(ros, node):
        _, on_message = node.subscriptions_[0][1:]
        _, on_timer = node.timers_[0]
        for _ in range(2):
            ros.time += 0.1
            on_message(image_msg(scene(1.0, 4.0)))
            on_timer()
        signal.raise_signal(signum)  # the handler runs here, in the main thread
        raise AssertionError("spin went on after the signal")

    return spin


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize("has_signal_options", [True, False])
def test_main_sends_zero_on_signal_before_shutdown(
    monkeypatch, tmp_path, signum, has_signal_options
):
    npz = str(write_policy_npz(tmp_path / "policy.npz"))
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    ros = FakeRos(spin=drive_then_signal(signum)).install(monkeypatch, has_signal_options)
    assert ros_node.main(["--policy", npz, "--ros-args", "-r", "cmd_vel:=commands/velocity"]) == 0
    init = ros.events[0]
    assert init[0] == "init" and init[1]["args"][1:] == [
        "--ros-args",
        "-r",
        "cmd_vel:=commands/velocity",
    ]
    assert init[1].get("signal_handler_options", "absent") == (
        0 if has_signal_options else "absent"
    )
    kinds = [e[0] for e in ros.events]
    published = ros.published()
    assert published[:2] != [(0.0, 0.0)] * 2 and published[1] != (0.0, 0.0)  # it drove
    assert published[2:] == [(0.0, 0.0), (0.0, 0.0)]  # the handler's stop, then main's
    last_publish = max(i for i, k in enumerate(kinds) if k == "publish")
    assert kinds[last_publish + 1 :] == ["destroy", "shutdown"]  # zero sent before shutting down
    assert {s: signal.getsignal(s) for s in before} == before  # the handlers are given back


def test_main_sends_zero_when_spin_fails(monkeypatch, tmp_path):
    def spin(ros, node):
        raise RuntimeError("executor broke")

    npz = str(write_policy_npz(tmp_path / "policy.npz"))
    ros = FakeRos(spin=spin).install(monkeypatch)
    with pytest.raises(RuntimeError, match="executor broke"):
        ros_node.main(["--policy", npz])
    assert ros.published() == [(0.0, 0.0)] and ros.events[-1] == ("shutdown",)


def test_main_bad_policy_is_one_line(monkeypatch, tmp_path, capsys):
    ros = FakeRos().install(monkeypatch)
    assert ros_node.main(["--policy", str(tmp_path / "missing.npz")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "missing.npz" in err and err.count("\n") == 1
    assert ros.events[-1] == ("shutdown",)
    ros = FakeRos({"max_age": -1.0}).install(monkeypatch)
    npz = str(write_policy_npz(tmp_path / "policy.npz"))
    assert ros_node.main(["--policy", npz]) == 2
    assert capsys.readouterr().err == "error: max_age: must be > 0 s, got -1.0\n"


@pytest.mark.parametrize("kind", [*BAD_CONTENT, *DAMAGE])
def test_main_refuses_a_bad_policy_file_before_any_command(monkeypatch, tmp_path, capsys, kind):
    """One line naming the file, exit status 2, nothing published; a FIFO does not block."""
    path, message = damaged(kind, tmp_path)
    ros = FakeRos().install(monkeypatch)
    fifo = path if kind == "fifo" else None
    assert bounded(ros_node.main, ["--policy", str(path)], fifo=fifo) == 2
    assert capsys.readouterr().err == f"error: {path}: {message}\n"
    assert ros.published() == [] and ros.events[-1] == ("shutdown",)
    assert all(not node.timers_ for node in ros.nodes)


def test_loop_stops_on_a_non_finite_command(policy):
    """A command that is not finite is an error: the loop sends zero velocity and carries on."""
    log = []
    loop = ControlLoop(Controller(NanPolicy(policy.sensor)), MessageReader(), log=log.append)
    loop.on_observation(image_msg(scene(1.0, 4.0)), 0.0)
    assert loop.tick(0.0) == STOP and loop.obs is None
    assert log == ["error: ValueError: command (nan, 0.0) is not finite: sending zero velocity"]
