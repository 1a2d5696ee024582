"""The ROS 2 node's safety: its own control rate, the stale-data watchdog, errors and shutdown stop;
what it reads (scans, blind frames, header stamps, camera_info), goal inputs and its interfaces.

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
    ASTRA_K,
    BAD_CONTENT,
    DAMAGE,
    NanPolicy,
    astra_frame,
    bounded,
    damaged,
    floor_image,
    write_policy_npz,
)

from jaxnav.robot_side import ros_node
from jaxnav.robot_side.observation import (
    BlindFrame,
    Controller,
    Intrinsics,
    Twist,
    depth_image_to_sectors,
)
from jaxnav.robot_side.policy import NumpyPolicy
from jaxnav.robot_side.ros_node import (
    STOP,
    ControlLoop,
    GoalInput,
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


def expected(policy, depth, speed_calibration=1.0) -> Twist:
    """What the node must send for a fresh depth image with no camera_info: the rows within
    +-2 deg of the horizon and columns binned by angle, the policy's fov across the image."""
    camera = Intrinsics.from_hfov(depth.shape[1], depth.shape[0], policy.sensor.fov)
    controller = Controller(policy, speed_calibration)
    return controller.act(
        controller.image_obs(depth, camera.horizon_rows(), camera.column_angles())
    )


def test_several_row_policies_read_their_rays_floor_left_out(tmp_path):
    """A 5-row policy reads the pixels of its rays with the floor rule (a wall at 5 m behind
    the floor reads 5 m); the camera height and pitch parameters override the file's."""
    elevations = np.linspace(-0.38, 0.17, 5)  # SensorConfig(rows=5).elevations
    npz = write_policy_npz(tmp_path / "p.npz", elevations=elevations, camera_height=0.295)
    controller = Controller(NumpyPolicy.from_npz(npz))
    msg = image_msg(floor_image())  # 49.5 deg vertically
    np.testing.assert_allclose(MessageReader(vfov_deg=49.5)(msg, controller), 5.0, rtol=1e-6)
    # Told the camera is 5 cm higher than it is, the floor seems 5 cm up: obstacles.
    assert MessageReader(vfov_deg=49.5, camera_height=0.345)(msg, controller).max() < 1.0
    looking_up = MessageReader(vfov_deg=49.5, tilt_deg=-3.0)  # said to look up 3 deg
    assert looking_up(msg, controller).max() < 1.0
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


def test_avoid_policy_with_history_sees_stacked_frames(tmp_path):
    """An avoid policy with `history` 2 gets the newest sectors, then the two frames before them
    (the first frame standing in for them at the start and after a stop), as the simulator
    stacks them."""
    rng = np.random.default_rng(3)
    stacked = NumpyPolicy.from_npz(
        write_policy_npz(
            tmp_path / "stacked.npz",
            W0=rng.normal(size=(24, 16)).astype(np.float32),
            obs_mean=np.full(24, 3.0, np.float32),
            obs_var=np.full(24, 4.0, np.float32),
            obs_std=np.full(24, 2.0, np.float32),
            history=np.int32(2),
        )
    )
    loop = ControlLoop(Controller(stacked), MessageReader(), max_age=0.25, log=lambda _: None)
    frames = [scene(0.9 + 0.4 * i, 3.0 + 0.3 * i) for i in range(4)]
    seen = []
    for i, frame in enumerate(frames):
        loop.on_observation(image_msg(frame), 0.1 * i)
        loop.tick(0.1 * i)
        seen.append(loop.obs[:8].copy())
        assert loop.obs.shape == (24,)
    np.testing.assert_array_equal(loop.obs, np.concatenate(seen[:0:-1]))  # 3, 2, 1: newest first
    loop.tick(0.35)  # a tick without a new frame stacks the newest again, as the simulator does
    np.testing.assert_array_equal(loop.obs, np.concatenate([seen[3], seen[3], seen[2]]))
    assert loop.tick(1.0) == STOP  # no frame for 0.7 s: stopped, the stack starts afresh
    loop.on_observation(image_msg(frames[0]), 1.0)
    loop.tick(1.0)
    np.testing.assert_array_equal(loop.obs, np.tile(seen[0], 3))


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
    assert args.max_age == 0.25 and args.blind_fraction == 0.5 and args.readings_per_stray == 50
    assert args.max_unknown == 0.9 and math.isnan(args.vfov_deg) and args.header_stamps
    assert args.blind_hold == ros_node.BLIND_HOLD
    assert not args.stamped and args.enable_topic == "~/enable" and args.camera_info_topic == ""
    assert ros_node.parse_args(["--no-header-stamps", "--stamped"])[0].header_stamps is False


def message(kind: str, /, **defaults):
    """A stand-in message class: instances start with `defaults` (made fresh per instance)."""

    def __init__(self, **fields):
        for key, value in {**defaults, **fields}.items():
            setattr(self, key, value() if callable(value) else value)

    return type(kind, (), {"__init__": __init__})


class FakeRos:
    """Stand-ins for rclpy, its Node, timers and publishers, and the message classes."""

    Vector = message("Vector3", x=0.0, y=0.0, z=0.0)
    Twist = message("Twist", linear=Vector, angular=Vector)
    Time = message("Time", sec=0, nanosec=0)
    Header = message("Header", stamp=Time, frame_id="")
    TwistStamped = message("TwistStamped", header=Header, twist=Twist)
    String = message("String", data="")
    Bool = message("Bool", data=False)
    CameraInfo = message("CameraInfo", header=Header, width=0, height=0, k=lambda: [0.0] * 9)
    KeyValue = message("KeyValue", key="", value="")
    DiagnosticStatus = type(
        "DiagnosticStatus",
        (
            message(
                "DiagnosticStatus", level=b"\x00", name="", message="", hardware_id="", values=list
            ),
        ),
        dict(OK=b"\x00", WARN=b"\x01", ERROR=b"\x02"),
    )
    DiagnosticArray = message("DiagnosticArray", header=Header, status=list)
    Trigger = type("Trigger", (), {})
    TriggerResponse = message("TriggerResponse", success=False, message="")

    class Future:
        """rclpy.task.Future's part the node uses: set_result, and await in a coroutine."""

        def __init__(self):
            self.answer, self.is_done = None, False

        def set_result(self, answer):
            self.answer, self.is_done = answer, True

        def __await__(self):
            while not self.is_done:
                yield
            return self.answer

    def __init__(self, params=None, spin=None):
        self.time, self.params, self.spin_body = 0.0, params or {}, spin
        self.events, self.nodes = [], []  # ("publish", topic, msg) / ("init", kwargs) / ...

    def modules(self, signals: bool = True) -> dict:
        ros = self

        class Node:
            def __init__(self, name):
                self.subscriptions_, self.timers_, self.publishers_ = [], [], {}
                self.services_ = {}
                ros.nodes.append(self)

            def declare_parameter(self, name, value):
                return types.SimpleNamespace(value=ros.params.get(name, value))

            def create_publisher(self, msg_type, topic, depth):
                self.publishers_[topic] = msg_type.__name__
                if msg_type in (FakeRos.Twist, FakeRos.TwistStamped):
                    self.cmd_topic = topic
                publish = lambda m: ros.events.append(("publish", topic, m))
                return types.SimpleNamespace(publish=publish)

            def create_subscription(self, msg_type, topic, callback, qos):
                self.subscriptions_.append((msg_type.__name__, topic, callback))

            def create_service(self, srv_type, name, callback):
                self.services_[name] = (srv_type.__name__, callback)

            def create_timer(self, period, callback):
                self.timers_.append((period, callback))

            def get_clock(self):
                def now():
                    ns = int(round(ros.time * 1e9))
                    stamp = lambda: FakeRos.Time(sec=ns // 10**9, nanosec=ns % 10**9)
                    return types.SimpleNamespace(nanoseconds=ns, to_msg=stamp)

                return types.SimpleNamespace(now=now)

            def get_logger(self):
                log = lambda text: ros.events.append(("log", text))
                return types.SimpleNamespace(info=log, warning=log)

            def destroy_node(self):
                ros.events.append(("destroy",))

            def get_name(self):
                return "jaxnav_policy"

        rclpy = types.SimpleNamespace(
            init=lambda **kw: self.events.append(("init", kw)),
            spin=lambda node: self.spin_body(self, node),
            try_shutdown=lambda: self.events.append(("shutdown",)),
        )
        image, scan = type("Image", (), {}), type("LaserScan", (), {})
        geometry = dict(Twist=FakeRos.Twist, TwistStamped=FakeRos.TwistStamped)
        return {
            "rclpy": rclpy,
            "rclpy.node": types.SimpleNamespace(Node=Node),
            "rclpy.qos": types.SimpleNamespace(qos_profile_sensor_data=None),
            "rclpy.task": types.SimpleNamespace(Future=FakeRos.Future),
            "rclpy.signals": types.SimpleNamespace(SignalHandlerOptions=types.SimpleNamespace(NO=0))
            if signals
            else None,  # None in sys.modules: ImportError, as on Foxy
            "sensor_msgs": types.SimpleNamespace(),
            "sensor_msgs.msg": types.SimpleNamespace(
                Image=image, LaserScan=scan, CameraInfo=FakeRos.CameraInfo
            ),
            "geometry_msgs": types.SimpleNamespace(),
            "geometry_msgs.msg": types.SimpleNamespace(**geometry),
            "std_msgs": types.SimpleNamespace(),
            "std_msgs.msg": types.SimpleNamespace(Bool=FakeRos.Bool, String=FakeRos.String),
            "std_srvs": types.SimpleNamespace(),
            "std_srvs.srv": types.SimpleNamespace(Trigger=FakeRos.Trigger),
            "diagnostic_msgs": types.SimpleNamespace(),
            "diagnostic_msgs.msg": types.SimpleNamespace(
                DiagnosticArray=FakeRos.DiagnosticArray,
                DiagnosticStatus=FakeRos.DiagnosticStatus,
                KeyValue=FakeRos.KeyValue,
            ),
        }

    def install(self, monkeypatch, signals: bool = True):
        for name, module in self.modules(signals).items():
            monkeypatch.setitem(sys.modules, name, module)
        return self

    def messages(self, kind: str) -> list:
        """The messages of class `kind` published, in order."""
        return [e[2] for e in self.events if e[0] == "publish" and type(e[2]).__name__ == kind]

    def published(self):
        """(forward m/s, yaw rad/s) of each velocity command published, Twist or TwistStamped."""
        kinds = ("Twist", "TwistStamped")
        sent = [e[2] for e in self.events if e[0] == "publish" and type(e[2]).__name__ in kinds]
        return [(m.linear.x, m.angular.z) for m in (getattr(m, "twist", m) for m in sent)]


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
    want = expected(policy, frame, speed_calibration=2.0)
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


def beams(n: int = 640):
    """Beam angles (rad, right to left) of a `depthimage_to_laserscan` scan of an Astra image of
    n columns (ASTRA_K), one beam per column."""
    half = math.atan(319.5 / ASTRA_K.fx)
    return np.linspace(-half, half, n)


def scan_msg(ranges):
    angles = beams(len(ranges))
    return types.SimpleNamespace(
        ranges=list(ranges), angle_min=angles[0], angle_increment=angles[1] - angles[0]
    )


def test_scan_nan_is_unknown_not_far(policy):
    """`depthimage_to_laserscan` writes NaN for columns the camera returned nothing in (REP 117:
    no valid measurement), e.g. a surface inside the Astra's 0.6 m blind zone. The node read NaN
    as range_max: measured before, a box 0.4 m ahead across the middle quarter read 8.0 m in
    sectors 3 and 4, and a wall 0.4 m ahead across the whole view 8.0 m in all eight, so the robot
    drove on. NaN is now unknown, like a depth image's 0 (a sector at least half unknown reads
    range_min; a scan over 90 % unknown stops the robot); +inf (no return within range) still
    reads range_max and -inf (too close) range_min."""
    log = []
    loop = ControlLoop(Controller(policy), MessageReader(scan=True), log=log.append)
    angles = beams()
    wall = 3.0 / np.cos(angles)  # a wall 3 m ahead: camera depth 3 m
    box = np.where(np.abs(angles) < math.radians(7.5), NAN, wall)  # 0.4 m ahead: no return
    loop.on_observation(scan_msg(box), 0.0)
    assert loop.tick(0.0) != STOP
    np.testing.assert_allclose(loop.obs, [3, 3, 3, 0.6, 0.6, 3, 3, 3], rtol=1e-5)
    loop.on_observation(scan_msg(np.full(640, NAN)), 0.1)  # the wall at 0.4 m
    assert loop.tick(0.1) == STOP and loop.state.startswith("sensor blind: over 90% of its")
    edge = math.radians(22.5)  # sector 0 no return within range, sector 7 too close
    ranges = np.where(angles < -edge, INF, np.where(angles > edge, -INF, wall))
    loop.on_observation(scan_msg(ranges), 0.2)
    assert loop.tick(0.2) != STOP
    np.testing.assert_allclose(loop.obs, [8, 3, 3, 3, 3, 3, 3, 0.6], rtol=1e-5)


def unknown_share(policy, depth) -> float:
    """The share of the pixels the node reads in `depth` (ASTRA_K) that are unknown."""
    try:
        MessageReader()(image_msg(depth), Controller(policy, max_unknown=0.0), ASTRA_K)
    except BlindFrame as err:
        return err.share
    return 0.0


def test_broken_frames_stop_the_robot(policy):
    """A covered lens or sunlight gives frames of (almost) only 0; every sector then read range_min
    and the policy acted on "everything at 0.6 m" (spinning). Measured unknown shares of the pixels
    the node reads in 640 x 480 frames (ASTRA_K; band of a one-row policy / rays of a 5-row one):
    a wall at 5 m 0 / 0 %, with 10 % dropout 10 / 10 %, a black (no-return) surface over the left
    half 50 / 50 %, a box at 0.4 m over the middle quarter 25 / 25 %, sunlight over 80 % of the
    view 80 / 80 %, a hall with nothing within 8 m 100 / 40 % (the 5 rows see the floor); a covered
    lens or a wall at 0.4 m 100 / 100 %, sunlight over all of it with 2 % speckle 98 / 98 %. At most
    16 * (1 - share) sectors can be read (each needs half of its pixels known): above 90 % at most
    one. So frames over 90 % unknown stop the robot, with the reason logged once; the scenes below
    80 % drive."""
    rng = np.random.default_rng(0)
    wall = astra_frame()
    covered = np.zeros_like(wall)
    speckle = np.where(rng.random(wall.shape) < 0.02, rng.uniform(0.6, 8.0, wall.shape), 0.0)
    half, sunlit = wall.copy(), wall.copy()
    half[:, :320], sunlit[:, :512] = 0.0, 0.0
    shares = [unknown_share(policy, f) for f in (wall, half, sunlit, covered, speckle)]
    assert shares == pytest.approx([0.0, 0.5, 0.8, 1.0, 0.98], abs=0.005)
    log = []
    loop = ControlLoop(Controller(policy), MessageReader(), log=log.append)
    loop.on_camera_info(camera_info(ASTRA_K))
    for t, frame in enumerate([sunlit, covered, speckle, half]):
        loop.on_observation(image_msg(frame), t)
        assert (loop.tick(t) == STOP) == (t in (1, 2)), t
    blind = f"sensor blind: {BlindFrame(1.0, 0.9)}: sending zero velocity"
    assert log[1:] == ["policy: driving", blind, "policy: driving"]
    assert "over 90% of its readings unknown (lens covered, sunlight, or a surface" in blind


def test_a_wall_in_the_blind_zone_reads_near_for_a_while(policy):
    """A wall nearer than range_min across the whole view is unknown in every pixel, which the
    frame check refused: in the twin the node stopped for good facing it in 6 of 256 goal
    episodes, where the simulator reads it near and the policy turns away. After a frame that
    measured a surface within NEAR_MARGIN of range_min, such a frame now reads range_min in every
    sector for `blind_hold` s, then stops; after a far frame, or one that read near only by the
    blind share (sunlight), it still stops at once (a covered lens)."""
    sensor = policy.sensor
    near_wall, far_wall, covered = astra_frame(wall=0.7), astra_frame(), np.zeros((480, 640))
    log = []
    loop = ControlLoop(Controller(policy), MessageReader(), log=log.append, blind_hold=1.0)
    loop.on_camera_info(camera_info(ASTRA_K))
    loop.on_observation(image_msg(near_wall), 0.0)
    assert loop.tick(0.0) != STOP and loop.state == "policy"
    assert loop.obs.max() <= sensor.range_min + ros_node.NEAR_MARGIN
    all_near = Controller(policy).act(np.full(sensor.num_sectors, sensor.range_min, np.float32))
    for t in (0.1, 0.5, 1.0):
        loop.on_observation(image_msg(covered), t)
        assert loop.tick(t) == pytest.approx(all_near) and loop.state == ros_node.BLIND_ZONE
        assert (loop.obs == sensor.range_min).all() and loop.diagnosis()[0] == 1
    loop.on_observation(image_msg(covered), 1.1)
    assert loop.tick(1.1) == STOP and loop.state.startswith("sensor blind")
    sunlit = far_wall.copy()
    sunlit[:, :512] = 0.0
    for first in (far_wall, sunlit):  # nothing measured near: a covered lens stops at once
        loop.on_observation(image_msg(first), 2.0)
        assert loop.tick(2.0) != STOP
        loop.on_observation(image_msg(covered), 2.1)
        assert loop.tick(2.1) == STOP and loop.state.startswith("sensor blind")
    off = ControlLoop(Controller(policy), MessageReader(), log=log.append, blind_hold=0.0)
    off.on_camera_info(camera_info(ASTRA_K))
    off.on_observation(image_msg(near_wall), 0.0)
    off.tick(0.0)
    off.on_observation(image_msg(covered), 0.1)
    assert off.tick(0.1) == STOP
    with pytest.raises(ValueError, match="blind_hold"):
        ControlLoop(Controller(policy), MessageReader(), blind_hold=-1.0)


def stamped(msg, seconds: float):
    """`msg` with a header stamped `seconds` (0: unset)."""
    sec = math.floor(seconds)
    stamp = FakeRos.Time(sec=sec, nanosec=round((seconds - sec) * 1e9))
    msg.header = FakeRos.Header(stamp=stamp, frame_id="camera_depth_optical_frame")
    return msg


def test_messages_are_aged_by_their_header_stamp(monkeypatch, tmp_path, policy):
    """Staleness counted from arrival: a frame 0.3 s old on arrival (transport or driver delay)
    was acted on as fresh. With header stamps it is aged from its stamp; a zero stamp (unset)
    falls back to its arrival; a stamp more than 0.05 s ahead of its arrival (clocks apart) is
    refused, since it would keep a stalled camera's last frame fresh that much longer. The node
    ages by stamp unless `--no-header-stamps`; the replay (a bag's clock) by arrival."""
    frame = scene(1.0, 4.0)
    log = []
    loop = ControlLoop(Controller(policy), MessageReader(), log=log.append, header_stamps=True)
    loop.on_observation(stamped(image_msg(frame), 99.7), 100.0)
    assert loop.tick(100.0) == STOP
    assert loop.state == f"sensor messages over 0.25 s old on arrival{ros_node.OTHER_CLOCK}"
    loop.on_observation(stamped(image_msg(frame), 100.0), 100.1)
    assert loop.tick(100.25) == pytest.approx(expected(policy, frame))
    assert loop.tick(100.26) == STOP and loop.state == "no sensor message for over 0.25 s"
    loop.on_observation(stamped(image_msg(frame), 0.0), 101.0)  # unset: arrival
    assert loop.tick(101.2) != STOP
    loop.on_observation(stamped(image_msg(frame), 103.0), 101.3)
    assert loop.tick(101.3) == STOP
    assert loop.state == f"sensor stamps over 0.05 s ahead of this clock{ros_node.OTHER_CLOCK}"
    by_arrival = ControlLoop(Controller(policy), MessageReader(), log=log.append)
    by_arrival.on_observation(stamped(image_msg(frame), 99.7), 100.0)
    assert by_arrival.tick(100.0) != STOP
    npz = str(write_policy_npz(tmp_path / "p.npz"))
    for params, sent in [({}, STOP), ({"header_stamps": False}, expected(policy, frame))]:
        ros = FakeRos(params).install(monkeypatch)
        node = ros_node._make_node(ros_node.parse_args(["--policy", npz])[0])
        ros.time = 50.0
        node.subscriptions_[0][2](stamped(image_msg(frame), 49.5))
        node.timers_[0][1]()
        assert ros.published() == [pytest.approx(sent)]


def camera_info(camera: Intrinsics):
    """A sensor_msgs/CameraInfo of `camera`."""
    k = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    return FakeRos.CameraInfo(width=camera.width, height=camera.height, k=k)


def test_camera_info_places_columns_and_rows(monkeypatch, tmp_path):
    """The node took its focal length from 49.5 deg vertically (520.6 px, 63.2 deg across); the
    common Astra calibration is 570.3 px (58.6 deg across). Measured with a 5-row policy on
    640 x 480 frames of that camera: its "+-30 deg" columns covered +-27.8 deg, so a 5 cm post
    2 m ahead at 29 deg left read 5.0 m (the wall behind it) in sector 7, and its ray rows sat
    higher (1.2 deg on the second row, 1.7 deg on the lowest), so the second row met a box face
    1 m ahead 6.9 cm up instead of 4.8 cm and missed a 6 cm box in sectors 2-5. With the K of
    camera_info: the post at 2.0 m, the box at 1.0 m in sectors 1-6. Without camera_info the
    policy's 60 deg across the image (554.3 px) is used; it sees both here."""
    rows = dict(elevations=np.linspace(-0.38, 0.17, 5), camera_height=0.295)
    npz = write_policy_npz(tmp_path / "p.npz", **rows)
    controller = Controller(NumpyPolicy.from_npz(npz))
    post = image_msg(astra_frame(posts=[(2.0, 2.0 * math.tan(math.radians(29.0)), 0.05)]))
    box = image_msg(astra_frame(box=(1.0, 0.06)))
    old = MessageReader(vfov_deg=49.5)
    assert old(post, controller)[7] == 5.0 and (old(box, controller)[2:6] == 5.0).all()
    log = []
    loop = ControlLoop(controller, MessageReader(), log=log.append)
    loop.on_camera_info(FakeRos.CameraInfo(width=640, height=480))  # K all zero: not used
    loop.on_camera_info(camera_info(ASTRA_K))
    assert loop.camera == ASTRA_K
    assert log == [
        "camera_info not used: K is all zero (an uncalibrated camera)",
        "camera_info: fx 570.3, fy 570.3, cx 319.5, cy 239.5 px for 640x480 images",
    ]
    loop.on_observation(post, 0.0)
    assert loop.tick(0.0) != STOP and loop.obs[7] == pytest.approx(2.0)
    loop.on_observation(box, 0.1)
    loop.tick(0.1)
    np.testing.assert_allclose(loop.obs[1:7], 1.0, rtol=1e-6)
    off = Intrinsics(500.0, 505.0, 330.0, 225.0, 640, 480)  # any calibration is followed
    loop.on_camera_info(camera_info(off))
    loop.on_observation(box, 0.2)
    loop.tick(0.2)
    sensor = controller.policy.sensor
    want = depth_image_to_sectors(astra_frame(box=(1.0, 0.06)), sensor, camera=off)
    np.testing.assert_array_equal(loop.obs, want)
    loop.on_observation(image_msg(np.full((240, 320), 3.0, np.float32)), 0.3)
    assert loop.tick(0.3) == STOP
    assert "calibration is for 640x480 images, the image is 320x240" in loop.state
    ros = FakeRos().install(monkeypatch)
    topics = [
        ([], "/camera/depth/camera_info"),  # beside the image topic
        (["--topic", "/cam/depth/image_rect"], "/cam/depth/camera_info"),
        (["--camera-info-topic", "info"], "info"),
    ]
    for flags, topic in topics:
        node = ros_node._make_node(ros_node.parse_args(["--policy", str(npz), *flags])[0])
        assert node.subscriptions_[1][:2] == ("CameraInfo", topic)
        node.subscriptions_[1][2](camera_info(ASTRA_K))
        assert node.loop.camera == ASTRA_K
    node = ros_node._make_node(ros_node.parse_args(["--policy", str(npz), "--scan"])[0])
    assert "CameraInfo" not in [kind for kind, _, _ in node.subscriptions_]
    assert ros.events.count(("log", log[1])) == 3


def write_goal_policy_npz(path):
    """A continuous goal policy (format 3): 8 sectors, goal features, last command; radius 0.3 m."""
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


def odometry(x: float, y: float, yaw: float, frame: str = "odom"):
    """A nav_msgs/Odometry-like message of the pose (x, y, yaw)."""
    ns = types.SimpleNamespace
    q = ns(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    return ns(header=ns(frame_id=frame), pose=ns(pose=ns(position=ns(x=x, y=y), orientation=q)))


@pytest.fixture
def goal_loop(tmp_path):
    """(loop, log) of a goal policy reading a scan 3 m ahead, its goal (5, 0) in odom."""
    log = []
    policy = NumpyPolicy.from_npz(write_goal_policy_npz(tmp_path / "goal.npz"))
    loop = ControlLoop(
        Controller(policy), MessageReader(scan=True), log=log.append, goal=GoalInput()
    )
    loop.goal.on_goal(5.0, 0.0, "odom")
    return loop, log


def drive(loop, t: float, pose) -> Twist:
    """One 50 Hz step of `loop` at t s: a fresh scan, odometry at `pose`, a tick."""
    loop.on_observation(scan_msg(np.full(640, 3.0)), t)
    loop.on_odometry(odometry(*pose), t)
    return loop.tick(t)


def test_odometry_jump_stops_until_steady(goal_loop):
    """An odometry jump of 2.2 m and 57 deg between consecutive messages was accepted (the policy
    drove on towards a goal it then saw elsewhere). The robot can move at most 0.7 m/s and
    180 deg/s: between 50 Hz messages (0.02 s) 1.4 cm and 3.6 deg. Allowed: twice that over the
    interval plus 0.05 s of stamp and delivery jitter, 9.8 cm and 25 deg at 50 Hz, 21 cm and
    54 deg at 10 Hz, 1.5 m and any turn after a silence of 1 s or more (the interval counts up
    to 1 s: odometry that stale stopped the robot). The replay test's recorded path (1.1 m/s,
    up to 6 rad/s at 20 Hz) stays within. A jump stops the robot with a warning until 5
    consecutive messages (0.1 s at 50 Hz) agree again."""
    assert ros_node.odometry_jump((0, 0, 0), (0.095, 0, 0.4), 0.02) is None
    assert ros_node.odometry_jump((0, 0, 0), (0.105, 0, 0), 0.02) == "0.10 m and 0 deg in 0.02 s"
    assert ros_node.odometry_jump((0, 0, 0), (0, 0, math.radians(26)), 0.02) is not None
    assert ros_node.odometry_jump((0, 0, 0), (NAN, 0, 0), 0.02) is not None
    assert ros_node.odometry_jump((0, 0, 0), (1.4, 0, 3.0), 5.0) is None
    loop, log = goal_loop
    for i in range(5):
        assert drive(loop, 0.02 * i, (0.01 * i, 0.0, 0.0)) != STOP
    jumped = (0.04 + 2.2 * math.cos(0.3), 2.2 * math.sin(0.3), math.radians(57))
    assert drive(loop, 0.1, jumped) == STOP and loop.goal_status() == "odometry jump"
    warning = "odometry jump of 2.20 m and 57 deg in 0.02 s: waiting for 5 consistent messages"
    assert loop.state == warning and log[-1] == f"{warning}: sending zero velocity"
    steady = [(jumped[0] + 0.01 * i, jumped[1], jumped[2]) for i in range(1, 6)]
    stopped = [drive(loop, 0.1 + 0.02 * i, pose) == STOP for i, pose in enumerate(steady, 1)]
    assert stopped == [True] * 4 + [False]
    assert loop.state == "policy" and loop.goal_status() == "driving"


def test_goal_reached_latches_until_a_new_goal(goal_loop):
    """Within the success radius (0.3 m) the robot stopped, but at 0.31 m (odometry drift, a push)
    it drove again. "goal reached" now holds until a new goal comes, even the same one."""
    loop, log = goal_loop
    assert drive(loop, 0.0, (4.71, 0.0, 0.0)) == STOP and loop.state == "goal reached"
    assert drive(loop, 0.02, (4.69, 0.0, 0.0)) == STOP and loop.state == "goal reached"
    assert loop.goal_status() == "reached"
    loop.goal.on_goal(5.0, 0.0, "odom")
    assert drive(loop, 0.04, (4.69, 0.0, 0.0)) != STOP and loop.goal_status() == "driving"


def install_goal_messages(monkeypatch) -> None:
    """Stand-ins of the goal policies' message classes, beside FakeRos's."""
    ns = types.SimpleNamespace
    monkeypatch.setitem(sys.modules, "nav_msgs", ns())
    monkeypatch.setitem(sys.modules, "nav_msgs.msg", ns(Odometry=type("Odometry", (), {})))
    sys.modules["geometry_msgs.msg"].PoseStamped = type("PoseStamped", (), {})
    sys.modules["geometry_msgs.msg"].PointStamped = type("PointStamped", (), {})


def test_node_goal_status_topic(monkeypatch, tmp_path):
    """A goal policy's node publishes the goal's status at every tick on `goal_status_topic`."""
    npz = str(write_goal_policy_npz(tmp_path / "goal.npz"))
    ros = FakeRos().install(monkeypatch)
    ns = types.SimpleNamespace
    install_goal_messages(monkeypatch)
    args = ros_node.parse_args(["--policy", npz, "--scan", "--goal-point", "--goal-topic", "/clicked_point"])[0]  # fmt: skip
    point = ros_node._make_node(args)  # RViz's Publish Point: a PointStamped goal
    assert ("PointStamped", "/clicked_point") in [s[:2] for s in point.subscriptions_]
    node = ros_node._make_node(ros_node.parse_args(["--policy", npz, "--scan"])[0])
    assert node.publishers_ == {
        "cmd_vel": "Twist",
        "goal_status": "String",
        "/diagnostics": "DiagnosticArray",
    }
    subs = {kind: callback for kind, _, callback in node.subscriptions_}
    on_timer = node.timers_[0][1]
    for t, goal in [(1.0, None), (1.1, (2.0, 0.0)), (1.2, (0.2, 0.0))]:
        ros.time = t
        subs["LaserScan"](scan_msg(np.full(640, 3.0)))
        subs["Odometry"](odometry(0.0, 0.0, 0.0))
        if goal:
            position = ns(x=goal[0], y=goal[1])
            subs["PoseStamped"](ns(header=ns(frame_id="odom"), pose=ns(position=position)))
        on_timer()
    assert [m.data for m in ros.messages("String")] == ["no goal", "driving", "reached"]
    point.loop.goal.on_goal_msg(ns(header=ns(frame_id="odom"), point=ns(x=1.5, y=-0.5, z=0.0)))
    assert point.loop.goal.goal == (1.5, -0.5) and point.loop.goal.goal_frame == "odom"


def test_node_stamped_commands_and_enable_topic(monkeypatch, tmp_path, policy):
    """`--stamped` publishes geometry_msgs/TwistStamped (Nav2, newer distributions) stamped with
    the node's clock in base_link; false on the enable topic (std_msgs/Bool) sends zero velocity
    at once and at every tick until true comes."""
    npz = str(write_policy_npz(tmp_path / "policy.npz"))
    ros = FakeRos().install(monkeypatch)
    node = ros_node._make_node(ros_node.parse_args(["--policy", npz, "--stamped"])[0])
    assert node.publishers_ == {"cmd_vel": "TwistStamped", "/diagnostics": "DiagnosticArray"}
    subs = {kind: (topic, callback) for kind, topic, callback in node.subscriptions_}
    on_message, on_timer = subs["Image"][1], node.timers_[0][1]
    frame = scene(0.9, 3.0)
    ros.time = 5.25
    on_message(image_msg(frame))
    on_timer()
    command = ros.messages("TwistStamped")[-1]
    assert (command.header.stamp.sec, command.header.stamp.nanosec) == (5, 250_000_000)
    assert command.header.frame_id == "base_link"
    assert ros.published() == [pytest.approx(expected(policy, frame))] != [(0.0, 0.0)]
    topic, on_enable = subs["Bool"]
    assert topic == "~/enable"
    on_enable(FakeRos.Bool(data=False))
    on_message(image_msg(frame))
    on_timer()
    assert ros.published()[1:] == [(0.0, 0.0)] * 2
    assert node.loop.state == "paused (false on the enable topic)"
    on_enable(FakeRos.Bool(data=True))
    on_timer()
    assert ros.published()[-1] == pytest.approx(expected(policy, frame))
    logs = [e[1] for e in ros.events if e[0] == "log"]
    assert "paused (false on the enable topic): sending zero velocity" in logs
    ros_node._make_node(ros_node.parse_args(["--policy", npz])[0])
    assert ros.nodes[-1].publishers_ == {"cmd_vel": "Twist", "/diagnostics": "DiagnosticArray"}


def quaternion(yaw: float):
    """A geometry_msgs/Quaternion-like rotation by `yaw` (rad) about z."""
    return types.SimpleNamespace(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def test_transform_points_by_hand():
    """Map's origin at (1, 2) in odom, turned 90 deg: map's x axis is odom's y axis, so the map
    point (3, 0) is odom's (1, 2 + 3) and (3, 4) is (1 - 4, 2 + 3). Turned 30 deg and at
    (0.5, -1): (2, 0) is (0.5 + 2 cos 30, -1 + 2 sin 30) = (2.2320508, 0)."""
    quarter = (1.0, 2.0, math.pi / 2)
    np.testing.assert_allclose(ros_node.transform_points(quarter, (3.0, 0.0)), [1.0, 5.0])
    points = np.array([[3.0, 0.0], [3.0, 4.0], [0.0, 0.0]])  # [3, 2]
    want = [[1.0, 5.0], [-3.0, 5.0], [1.0, 2.0]]
    np.testing.assert_allclose(ros_node.transform_points(quarter, points), want, atol=1e-12)
    turned = (0.5, -1.0, math.radians(30.0))
    got = ros_node.transform_points(turned, (2.0, 0.0))
    np.testing.assert_allclose(got, [2.2320508, 0.0], atol=1e-7)
    ns = types.SimpleNamespace
    msg = ns(translation=ns(x=1.0, y=2.0, z=0.3), rotation=quaternion(math.pi / 2))
    assert ros_node.planar_transform(msg) == pytest.approx(quarter)


def test_goal_in_map_is_driven_to_its_odom_point(goal_loop):
    """A goal in `map` was refused (zero velocity) while odometry is in `odom`. It is now placed
    in odom at every tick with the newest map -> odom transform: the policy sees exactly what it
    sees for the goal given in odom at that point, also after map and odom drift apart (the
    goal stays one goal: no new episode), and stops within the success radius of it there."""
    loop, _ = goal_loop
    map_in_odom, asked = [(1.0, 2.0, math.pi / 2)], []

    def lookup(target, source):
        asked.append((target, source))
        return map_in_odom[0]

    loop.goal.transforms = lookup
    loop.goal.on_goal(3.0, 0.0, "map")  # by hand: odom (1 - 0, 2 + 3)
    same = ControlLoop(loop.controller, MessageReader(scan=True), log=[].append, goal=GoalInput())
    same.goal.on_goal(1.0, 5.0, "odom")
    twist = drive(loop, 0.0, (0.0, 0.0, 0.0))
    assert asked == [("odom", "map")] and loop.goal.target == pytest.approx((1.0, 5.0))
    assert twist == drive(same, 0.0, (0.0, 0.0, 0.0)) != STOP and loop.state == "policy"
    np.testing.assert_array_equal(loop.obs, same.obs)
    map_in_odom[0] = (1.5, 2.0, math.pi / 2)  # localisation moved map 0.5 m along odom's x
    same.goal.on_goal(1.5, 5.0, "odom")
    assert drive(loop, 0.02, (0.01, 0.0, 0.0)) == drive(same, 0.02, (0.01, 0.0, 0.0))
    np.testing.assert_array_equal(loop.obs, same.obs)
    assert loop.goal.goal == (3.0, 0.0) and loop.goal.target == pytest.approx((1.5, 5.0))
    loop.goal.on_pose(1.5, 4.75, 0.0, 0.04, "odom")  # there: 0.25 m from the odom point
    loop.on_observation(scan_msg(np.full(640, 3.0)), 0.04)
    assert loop.tick(0.04) == STOP and loop.goal_status() == "reached"


MISSING_MAP = '("map" passed to lookupTransform argument source_frame does not exist.)'


def test_goal_in_another_frame_without_a_transform_is_refused(goal_loop):
    """No transforms (the replay, the twin): refused, as before. tf2 without the transform (no
    localisation yet, a frame of another tree): refused with tf2's reason, in the goal status and
    the diagnostics (WARN); driven to once the transform comes, refused again once it fails."""
    loop, log = goal_loop
    loop.goal.on_goal(3.0, 0.0, "map")
    assert drive(loop, 0.0, (0.0, 0.0, 0.0)) == STOP
    frames = "goal in frame 'map', odometry in 'odom'"
    assert loop.state == frames and loop.goal.target is None
    known = {}

    def lookup(target, source):
        if (target, source) not in known:
            raise LookupError(f'"{source}" passed to lookupTransform argument source_frame does '
                              "not exist. ")  # fmt: skip
        return known[target, source]

    loop.goal.transforms = lookup
    assert drive(loop, 0.02, (0.0, 0.0, 0.0)) == STOP
    why = f"{frames}: no transform {MISSING_MAP}"
    assert loop.state == why and loop.goal_status() == f"stopped: {why}"
    assert loop.diagnosis()[:2] == (1, why) and log[-1] == f"{why}: sending zero velocity"
    known["odom", "map"] = (0.0, 0.0, 0.0)
    assert drive(loop, 0.04, (0.0, 0.0, 0.0)) != STOP and loop.goal_status() == "driving"
    del known["odom", "map"]
    assert drive(loop, 0.06, (0.0, 0.0, 0.0)) == STOP and loop.state == why
    known["odom", "map"] = (NAN, 0.0, 0.0)  # a broken transform
    assert drive(loop, 0.07, (0.0, 0.0, 0.0)) == STOP
    assert loop.state == f"{frames}: no transform (not finite: the goal at [nan, 0.0])"
    loop.goal.transforms = ros_node.no_transforms("goal_frame_tf is false")
    assert drive(loop, 0.08, (0.0, 0.0, 0.0)) == STOP
    assert loop.state == f"{frames}: no transform (goal_frame_tf is false)"


class TfBuffer:
    """tf2_ros.Buffer's lookup_transform: the transforms set in `known`, else tf2's error."""

    def __init__(self):
        self.known, self.times, self.stamps = {}, [], {}

    def lookup_transform(self, target, source, time):
        self.times.append(time)
        if (target, source) not in self.known:
            raise LookupError(f'"{source}" passed to lookupTransform argument source_frame does '
                              "not exist. ")  # fmt: skip
        stamp = self.stamps.get((target, source), 0.0)  # 0: /tf_static's
        header = FakeRos.Header(stamp=FakeRos.Time(sec=int(stamp), nanosec=0), frame_id=target)
        return types.SimpleNamespace(header=header, transform=self.known[target, source])


def test_a_stale_map_transform_refuses_the_goal(monkeypatch, tmp_path):
    """A localisation node that died left its last map -> odom transform in tf2's buffer, and the
    robot drove to a goal placed with it for good. The node now refuses a goal whose transform is
    more than goal_tf_max_age s older than its clock, saying so; a fresh or static (stamp 0) one
    places it."""
    npz = str(write_goal_policy_npz(tmp_path / "goal.npz"))
    ns = types.SimpleNamespace
    buffer = TfBuffer()
    tf2 = ns(Buffer=lambda: buffer, TransformListener=lambda buffer, node: None)
    ros = FakeRos({"goal_tf_max_age": 2.0}).install(monkeypatch)
    install_goal_messages(monkeypatch)
    monkeypatch.setitem(sys.modules, "tf2_ros", tf2)
    monkeypatch.setitem(sys.modules, "rclpy.time", ns(Time=lambda: "newest"))
    node = ros_node._make_node(ros_node.parse_args(["--policy", npz, "--scan"])[0])
    subs = {kind: callback for kind, _, callback in node.subscriptions_}
    subs["PoseStamped"](ns(header=ns(frame_id="map"), pose=ns(position=ns(x=3.0, y=0.0))))
    buffer.known["odom", "map"] = ns(translation=ns(x=1.0, y=0.0, z=0.0), rotation=quaternion(0))
    for t, stamp in ((10.0, 7.0), (10.1, 9.0), (10.2, 0.0)):
        buffer.stamps["odom", "map"] = stamp
        ros.time = t
        subs["LaserScan"](scan_msg(np.full(640, 3.0)))
        subs["Odometry"](odometry(0.0, 0.0, 0.0))
        node.timers_[0][1]()
    frames = "stopped: goal in frame 'map', odometry in 'odom': no transform"
    stale = f"{frames} (newest transform 3.0 s old, over goal_tf_max_age 2 s)"
    assert [m.data for m in ros.messages("String")] == [stale, "driving", "driving"]
    assert node.loop.goal.target == pytest.approx((4.0, 0.0))
    assert ros_node.parse_args([])[0].goal_tf_max_age == ros_node.GOAL_TF_MAX_AGE


def test_node_places_map_goals_with_tf2(monkeypatch, tmp_path):
    """The node listens to tf2 (a Buffer filled by a TransformListener on the node) and looks up
    the newest transform (rclpy Time(): zero) at every tick without waiting; with tf2_ros
    missing, or goal_frame_tf false, a map goal is refused, the reason in the goal status."""
    npz = str(write_goal_policy_npz(tmp_path / "goal.npz"))
    ns = types.SimpleNamespace
    buffers = []

    def buffer():
        buffers.append(TfBuffer())
        return buffers[-1]

    tf2 = ns(Buffer=buffer, TransformListener=lambda buffer, node: ("listening", buffer, node))
    cases = [(tf2, {}), (tf2, {"goal_frame_tf": False}), (None, {})]  # None: ImportError
    statuses = []
    for module, params in cases:
        ros = FakeRos(params).install(monkeypatch)
        install_goal_messages(monkeypatch)
        monkeypatch.setitem(sys.modules, "tf2_ros", module)
        monkeypatch.setitem(sys.modules, "rclpy.time", ns(Time=lambda: "newest"))
        node = ros_node._make_node(ros_node.parse_args(["--policy", npz, "--scan"])[0])
        subs = {kind: callback for kind, _, callback in node.subscriptions_}
        on_timer = node.timers_[0][1]
        goal = ns(header=ns(frame_id="map"), pose=ns(position=ns(x=3.0, y=0.0)))
        subs["PoseStamped"](goal)
        for t in (1.0, 1.1):
            ros.time = t
            subs["LaserScan"](scan_msg(np.full(640, 3.0)))
            subs["Odometry"](odometry(0.0, 0.0, 0.0))
            on_timer()
            if module is not None and not params and t == 1.0:  # the transform comes
                quarter = ns(translation=ns(x=1.0, y=2.0, z=0.0), rotation=quaternion(math.pi / 2))
                buffers[-1].known["odom", "map"] = quarter
        statuses.append([m.data for m in ros.messages("String")])
        if module is not None and not params:
            assert node.tf_listener == ("listening", buffers[-1], node)
            assert node.loop.goal.target == pytest.approx((1.0, 5.0))
            assert buffers[-1].times == ["newest", "newest"]
    frames = "stopped: goal in frame 'map', odometry in 'odom': no transform"
    assert statuses[0] == [f"{frames} {MISSING_MAP}", "driving"]
    assert statuses[1] == [f"{frames} (goal_frame_tf is false)"] * 2
    assert statuses[2][0].startswith(f"{frames} (tf2_ros does not import: ")
    assert any(e[1].startswith("goals only in the odometry's frame: tf2_ros does not import")
               for e in ros.events if e[0] == "log")  # fmt: skip
