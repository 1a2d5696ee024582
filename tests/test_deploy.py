"""Robot-side conversions: sensor readings -> the simulator's observation, actions -> Twist, ROS bytes."""

import math
import sys
import types

import jax
import numpy as np
import pytest
from conftest import EXACT
from test_robot_side import write_policy_npz

import jaxnav
from jaxnav.core.sensors import ray_depths
from jaxnav.io.layouts import Box, Cylinder, RoomLayout
from jaxnav.robot_side import observation as deploy
from jaxnav.robot_side import ros_node
from jaxnav.robot_side.observation import Sensor
from jaxnav.robot_side.policy import NumpyPolicy

NAN, INF = float("nan"), float("inf")
# What an exported policy of the default settings carries (test_export checks the export writes it).
SENSOR = Sensor(fov=math.radians(60.0), num_sectors=8, range_min=0.6, range_max=8.0)
COMMANDS = np.array([[0.5, 0.0], [0.0, 1.5], [0.0, -1.5]], np.float32)  # forward, left, right


@pytest.fixture(scope="module")
def scene():
    """(obs [8], per-ray depths [24], ray angles [24], robot-side Sensor) of a lopsided room.

    Obstacles on the left and right differ so a mirrored sector order would fail; the room is 20 m
    long so the rays straight ahead read beyond range_max (clipped).
    """
    layout = RoomLayout(
        name="lopsided",
        size=(20.0, 4.0),
        robot_pos=(0.0, 0.0),
        robot_yaw=0.0,
        obstacles=(
            Box(pos=(2.0, 0.7), size=(0.4, 0.6)),
            Box(pos=(3.0, -0.9), size=(0.5, 0.5), yaw=0.5),
            Cylinder(pos=(1.2, -0.35), radius=0.1),
        ),
    )
    env = jaxnav.make_env("avoid", layouts=[layout], randomize=EXACT)
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    m = env.scene.model_for(state.info["params"])
    depths = jax.jit(ray_depths, static_argnums=(2, 3, 4))(
        m, state.data, env.sensor, env.robot, env.scene.robot_body
    )
    obs, depths = np.asarray(state.obs), np.asarray(depths)
    assert len(set(np.round(obs, 3))) >= 5 and obs.max() == env.sensor.range_max  # a varied scene
    cfg = env.sensor
    sensor = Sensor(cfg.fov, cfg.num_sectors, cfg.range_min, cfg.range_max)
    return obs, depths, cfg.ray_angles, sensor


def test_scan_reproduces_simulated_sectors(scene):
    obs, depths, angles, sensor = scene
    ranges = depths / np.cos(angles)  # what a LaserScan of the same rays would read
    np.testing.assert_allclose(deploy.scan_to_sectors(ranges, angles, sensor), obs, atol=1e-4)
    # A real scan is wider than the camera: beams beyond +-fov/2 must not count.
    wide = np.linspace(-math.pi / 2, math.pi / 2, 41)
    outside = np.abs(wide) > sensor.fov / 2
    ranges = np.concatenate([ranges, np.full(outside.sum(), 0.7)])
    angles = np.concatenate([angles, wide[outside]])
    np.testing.assert_allclose(deploy.scan_to_sectors(ranges, angles, sensor), obs, atol=1e-4)


def test_depth_image_reproduces_simulated_sectors(scene):
    obs, depths, angles, sensor = scene
    row = np.where(np.isinf(depths), 0.0, depths)[::-1]  # column 0 = leftmost ray; 0 = no data
    np.testing.assert_allclose(deploy.depth_image_to_sectors(row[None], sensor), obs, atol=1e-4)
    # The floor below the horizon reads close; only the horizon row must count.
    image = np.stack([row, np.full_like(row, 0.7), np.full_like(row, 0.65)])
    got = deploy.depth_image_to_sectors(image, sensor, rows=[0])
    np.testing.assert_allclose(got, obs, atol=1e-4)
    got = deploy.depth_image_to_sectors(image, sensor, rows=slice(0, 1), column_angles=angles[::-1])
    np.testing.assert_allclose(got, obs, atol=1e-4)


def test_invalid_readings_are_ignored():
    # One sector per beam triple, right to left; expected sector values after the rules.
    beams = [
        [0.0, NAN, 2.0],  # invalid ones ignored -> 2.0
        [INF, -1.0, 3.0],  # -> 3.0
        [0.0, NAN, INF],  # nothing valid -> range_max
        [0.3, 5.0, 6.0],  # below range_min -> range_min
        [9.0, 12.0, INF],  # beyond range_max -> range_max
        [-INF, 1.5, 1.0],  # -> 1.0
        [4.0, 4.0, 4.0],
        [7.0, 0.0, 2.5],
    ]
    want = [2.0, 3.0, 8.0, 0.6, 8.0, 1.0, 4.0, 2.5]
    depth = np.array(beams, np.float64).ravel()  # [24], right to left
    image = depth[::-1][None]  # left to right
    np.testing.assert_allclose(deploy.depth_image_to_sectors(image, SENSOR), want, rtol=1e-6)
    angles = (np.arange(24) + 0.5) / 24 * SENSOR.fov - 0.5 * SENSOR.fov  # the simulator's rays
    ranges = depth / np.cos(angles)
    np.testing.assert_allclose(deploy.scan_to_sectors(ranges, angles, SENSOR), want, rtol=1e-6)
    empty = deploy.depth_image_to_sectors(np.zeros((5, 640), np.float32), SENSOR)
    np.testing.assert_array_equal(empty, np.full(8, 8.0, np.float32))
    assert empty.dtype == np.float32


def test_uneven_widths_and_geometry_helpers():
    # 10 columns into 8 sectors: slices of 1 or 2 columns, rightmost first.
    image = np.arange(1.0, 11.0)[None]  # column 0 (left) = 1 m ... column 9 (right) = 10 m
    got = deploy.depth_image_to_sectors(image, Sensor(SENSOR.fov, 8, 0.6, 20.0))
    assert got[0] == 10.0 and got[-1] == 1.0 and np.all(np.diff(got) < 0)
    with pytest.raises(ValueError, match="fewer than 8 sectors"):
        deploy.depth_image_to_sectors(np.ones((2, 5)), SENSOR)
    angles = deploy.pinhole_column_angles(640, SENSOR.fov)
    assert angles[0] > 0 > angles[-1] and np.allclose(angles, -angles[::-1])
    assert abs(angles[0] - math.radians(30)) < math.radians(0.1)
    rows = deploy.horizon_rows(480, math.radians(49.5), 2.0)
    assert rows[0] + rows[-1] == 479 and 30 < len(rows) < 40  # symmetric about the centre
    tilted = deploy.horizon_rows(480, math.radians(49.5), 2.0, tilt=math.radians(5))
    assert tilted.mean() < rows.mean()  # looking down: the horizon is higher in the image
    assert len(deploy.horizon_rows(480, math.radians(49.5), 0.0)) == 1


def test_action_to_twist():
    assert deploy.action_to_twist(0, COMMANDS) == (0.5, 0.0)
    assert deploy.action_to_twist(1, COMMANDS) == (0.0, 1.5)  # left = positive yaw rate
    assert deploy.action_to_twist(2, COMMANDS) == (0.0, -1.5)
    assert deploy.action_to_twist(np.int64(0), COMMANDS, speed_calibration=1.25) == (0.625, 0.0)
    assert deploy.action_to_twist(2, COMMANDS * 0.8, speed_calibration=1.25) == pytest.approx(
        (0.0, -1.5)
    )
    with pytest.raises(ValueError, match=r"action must be in 0\.\.2, got 3"):
        deploy.action_to_twist(3, COMMANDS)


def test_sensor_checks_name_the_field():
    with pytest.raises(ValueError, match="Sensor.num_sectors"):
        Sensor(SENSOR.fov, 0, 0.6, 8.0)
    with pytest.raises(ValueError, match="Sensor.range_min/range_max"):
        Sensor(SENSOR.fov, 8, 8.0, 0.6)


class TurnAway:
    """A stand-in policy: turns away from the nearer side; carries what a NumpyPolicy carries."""

    sensor, commands = Sensor(SENSOR.fov, 8, 0.6, 8.0), COMMANDS * 0.5

    def __call__(self, obs):
        return 1 if obs[0] < obs[-1] else 2


def test_controller_in_one_call():
    controller = deploy.Controller(TurnAway(), speed_calibration=1.1)
    image = np.full((3, 80), 5.0, np.float32)
    image[:, -10:] = 1.0  # close on the right
    assert controller.image_to_twist(image) == pytest.approx((0.0, 0.75 * 1.1))
    angles = np.linspace(-0.5, 0.5, 30)
    ranges = np.where(angles > 0.3, 1.0, 5.0)  # close on the left
    assert controller.scan_to_twist(ranges, angles) == pytest.approx((0.0, -0.75 * 1.1))
    with pytest.raises(ValueError, match="Controller.speed_calibration"):
        deploy.Controller(TurnAway(), speed_calibration=0.0)


def test_image_message_conversion():
    depth = np.array([[0.5, 1.0, NAN], [2.0, 0.0, 8.5]], np.float32)
    padded = b"".join(r.tobytes() + b"\xff" * 4 for r in depth)  # step = 3 * 4 + 4 bytes
    got = ros_node.image_msg_to_array("32FC1", 2, 3, padded, 16)
    np.testing.assert_array_equal(got, depth)
    mm = np.array([[600, 0, 65535], [1234, 8000, 1]], np.uint16)
    got = ros_node.image_msg_to_array("16UC1", 2, 3, mm.tobytes(), 6)
    np.testing.assert_allclose(got, mm / 1000.0, rtol=1e-6)
    assert got.dtype == np.float32 and got[0, 1] == 0.0  # no data stays invalid
    big = mm.astype(">u2").tobytes()
    np.testing.assert_allclose(
        ros_node.image_msg_to_array("16UC1", 2, 3, big, 6, is_bigendian=True), mm / 1000.0
    )
    with pytest.raises(ValueError, match="rgb8"):
        ros_node.image_msg_to_array("rgb8", 2, 3, bytes(18), 9)
    with pytest.raises(ValueError, match="too short"):
        ros_node.image_msg_to_array("32FC1", 2, 3, bytes(20), 12)


def test_scan_and_twist_message_conversion():
    ranges, angles = ros_node.scan_msg_to_arrays([1.0, INF, 2.0], -0.5, 0.25)
    np.testing.assert_allclose(angles, [-0.5, -0.25, 0.0])
    assert ranges.dtype == np.float32 and np.isinf(ranges[1])

    class Vector:
        x = y = z = 0.0

    class TwistMsg:  # the fields of geometry_msgs/Twist the node sets
        def __init__(self):
            self.linear, self.angular = Vector(), Vector()

    msg = ros_node.twist_msg(deploy.Twist(0.5, -1.5), TwistMsg)
    assert (msg.linear.x, msg.angular.z, msg.linear.y) == (0.5, -1.5, 0.0)


def test_ros_node_flags():
    # Importing ros_node without ROS (and without jax) is checked in test_robot_side.
    args, rest = ros_node.parse_args(["--policy", "p.npz", "--scan", "--ros-args", "-p", "x:=1"])
    assert args.policy == "p.npz" and args.scan and rest == ["--ros-args", "-p", "x:=1"]
    assert args.speed_calibration == 1.0 and args.band_deg == 2.0


@pytest.fixture
def fake_ros(monkeypatch):
    """Stand-ins for rclpy and the message packages: the node's wiring runs without ROS."""
    published = []

    class Node:
        def __init__(self, name):
            self.subscriptions_ = []

        def declare_parameter(self, name, value):
            return types.SimpleNamespace(value={"speed_calibration": 2.0}.get(name, value))

        def create_publisher(self, msg_type, topic, depth):
            self.cmd_topic = topic
            return types.SimpleNamespace(publish=published.append)

        def create_subscription(self, msg_type, topic, callback, qos):
            self.subscriptions_.append((msg_type.__name__, topic))

        def get_logger(self):
            return types.SimpleNamespace(info=lambda text: None)

    class Vector:
        x = y = z = 0.0

    class Twist:
        def __init__(self):
            self.linear, self.angular = Vector(), Vector()

    fakes = {
        "rclpy": {},
        "rclpy.node": {"Node": Node},
        "rclpy.qos": {"qos_profile_sensor_data": None},
        "sensor_msgs": {},
        "sensor_msgs.msg": {"Image": type("Image", (), {}), "LaserScan": type("LaserScan", (), {})},
        "geometry_msgs": {},
        "geometry_msgs.msg": {"Twist": Twist},
    }
    for name, attrs in fakes.items():
        monkeypatch.setitem(sys.modules, name, types.SimpleNamespace(**attrs))
    return published


def test_ros_node_wiring(fake_ros, tmp_path):
    npz = str(write_policy_npz(tmp_path / "policy.npz"))
    args, _ = ros_node.parse_args(["--policy", npz])
    node = ros_node._make_node(args)  # speed_calibration 2.0 comes from the (fake) ROS parameter
    assert node.subscriptions_ == [("Image", "/camera/depth/image_raw")]
    assert node.cmd_topic == "cmd_vel"
    depth_mm = np.full((48, 64), 3000, np.uint16)
    depth_mm[:, :8] = 900  # close on the left
    msg = types.SimpleNamespace(
        encoding="16UC1", height=48, width=64, data=depth_mm.tobytes(), step=128, is_bigendian=0
    )
    node.on_image(msg)
    obs = deploy.depth_image_to_sectors(depth_mm / 1000.0, SENSOR)
    policy = NumpyPolicy.from_npz(npz)
    want = deploy.action_to_twist(policy(obs), policy.commands, speed_calibration=2.0)
    assert (fake_ros[-1].linear.x, fake_ros[-1].angular.z) == pytest.approx(want)
    node.stop()
    assert (fake_ros[-1].linear.x, fake_ros[-1].angular.z) == (0.0, 0.0)

    args, _ = ros_node.parse_args(["--policy", npz, "--scan", "--topic", "/scan"])
    node = ros_node._make_node(args)
    assert node.subscriptions_ == [("LaserScan", "/scan")]
    scan = types.SimpleNamespace(
        ranges=[1.0] * 60 + [5.0] * 60, angle_min=-1.0, angle_increment=1 / 60
    )
    node.on_scan(scan)
    ranges, angles = ros_node.scan_msg_to_arrays(scan.ranges, -1.0, 1 / 60)
    action = policy(deploy.scan_to_sectors(ranges, angles, SENSOR))
    want = deploy.action_to_twist(action, policy.commands, speed_calibration=2.0)
    assert (fake_ros[-1].linear.x, fake_ros[-1].angular.z) == pytest.approx(want)
