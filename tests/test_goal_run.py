"""A goal policy end to end: `train --env goal --actions continuous --task.memory-bins 8` on the
command line, evaluation reading the task from the run (success rate, SPL), export to numpy and
ONNX, and the robot side (goal observation, memory, the control loop's goal inputs, the ROS 2
node's goal and odometry topics).

Slow, all of it: a goal training run on the command line, then its evaluation and export.
"""

import json
import math
import subprocess
import sys
import types

import jax
import numpy as np
import pytest
from conftest import run_cli
from test_ros_node import FakeRos

import jaxnav
from jaxnav.core.robot import TURTLEBOT2I
from jaxnav.export import export
from jaxnav.io.layouts import RoomLayout, save_layouts
from jaxnav.robot_side import ros_node
from jaxnav.robot_side.memory import Memory, MemorySpec
from jaxnav.robot_side.observation import Controller
from jaxnav.robot_side.policy import (
    MEMORY_FORMAT,
    FrameStack,
    NumpyPolicy,
    goal_features,
    goal_observation,
)
from jaxnav.robot_side.ros_node import STOP, ControlLoop, GoalInput, MessageReader
from jaxnav.tasks.goal import goal_features as sim_goal_features

TINY = [
    *("--num-envs", "16", "--rollout-length", "16", "--minibatch-size", "128"),
    *("--num-epochs", "2", "--total-steps", str(16 * 16 * 2), "--updates-per-chunk", "2"),
    *("--seed", "3", "--no-progress", "--task.memory-bins", "8"),
]
BINS = 8  # the memory's entries, the observation's last
ROOM = RoomLayout(name="hall", size=(5.0, 4.0), robot_pos=(-1.5, 0.0), goal_pos=(1.5, 0.5))


pytestmark = pytest.mark.slow  # every test here shares one CLI training run


@pytest.fixture(scope="module")
def goal_run(tmp_path_factory):
    """A tiny continuous-action goal run with a memory through the CLI: (run folder, layout
    file)."""
    out = tmp_path_factory.mktemp("goal") / "run"
    proc = run_cli("--env", "goal", "--actions", "continuous", "--out", str(out), *TINY)
    assert proc.returncode == 0, proc.stderr
    rooms = out.parent / "rooms.json"
    save_layouts(rooms, [ROOM, RoomLayout(name="open", size=(4.0, 4.0))])
    return out, rooms


def test_cli_run_evaluates_with_goal_metrics(goal_run):
    out, rooms = goal_run
    config = json.loads((out / "config.json").read_text())
    assert config["env"] == "goal" and config["task"]["actions"] == "continuous"
    report = out.parent / "eval.json"
    cmd = ["--checkpoint", str(out), "--layouts", str(rooms), "--episodes", "3", "--steps", "20"]
    proc = subprocess.run(
        [sys.executable, "-m", "jaxnav.evaluate", *cmd, "--json", str(report)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    results = json.loads(report.read_text())
    for metrics in [*results["layouts"].values(), results["overall"]]:
        assert {"success_rate", "spl", "time_to_goal", "collision_free_rate"} <= set(metrics)
        assert 0.0 <= metrics["spl"] <= metrics["success_rate"] <= 1.0
    assert "SPL" in proc.stdout and (report.parent / "hall.png").is_file()


def test_export_and_robot_side_take_the_goal_observation(goal_run, tmp_path):
    out, _ = goal_run
    policy = jaxnav.load_policy(out)
    numpy_file = export(out, "numpy", tmp_path / "policy.npz")
    onnx_file = export(out, "onnx", tmp_path / "policy.onnx")
    robot = NumpyPolicy.from_npz(numpy_file)
    assert robot.continuous and robot.success_radius == 0.3
    assert robot.observation_size == 13 * (1 + robot.history) + BINS and robot.history == 16
    assert robot.memory == MemorySpec(BINS, 20, 1.5, TURTLEBOT2I.camera_forward)
    rng = np.random.default_rng(0)
    sectors = rng.uniform(0.6, 8.0, (50, 8)).astype(np.float32)
    poses = rng.uniform(-2, 2, (50, 3)).astype(np.float32)
    goal, last = np.array([1.0, -0.5], np.float32), np.array([0.3, -0.7], np.float32)
    stack = FrameStack(robot.history)
    memory = Memory(robot.memory, robot.sensor.fov, robot.sensor.range_min, 8.0)
    obs = np.stack(
        [
            np.concatenate(
                [stack(goal_observation(s, p, goal, last, robot.command_scale)), memory(s, p)]
            )
            for s, p in zip(sectors, poses, strict=True)
        ]
    )
    np.testing.assert_array_equal(obs[1:, 13:26], obs[:-1, :13])  # the previous frame follows
    # The robot's goal features are the simulator's.
    sim = jax.vmap(sim_goal_features, (0, None))(poses, goal)
    np.testing.assert_allclose(obs[:, 8:11], sim, atol=1e-5)
    np.testing.assert_allclose(obs[:, 11:13], np.tile(last / [0.5, 1.5], (50, 1)), rtol=1e-6)
    with jax.default_matmul_precision("highest"):  # float32, as the file computes
        want = np.asarray(policy.act(obs, jax.random.PRNGKey(0)))
    np.testing.assert_allclose(robot(obs), want, atol=1e-5)
    assert (robot(obs) >= robot.action_low).all() and (robot(obs) <= robot.action_high).all()
    import onnxruntime as ort

    session = ort.InferenceSession(str(onnx_file), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(session.run(["action"], {"obs": obs})[0], want, atol=1e-5)
    arrays = dict(np.load(numpy_file))
    assert int(arrays["format_version"]) == MEMORY_FORMAT
    del arrays["memory_reach"]
    with pytest.raises(ValueError, match="^policy.npz: memory_bins without memory_reach$"):
        NumpyPolicy.from_arrays(arrays, "policy.npz")


def scan(distance: float):
    return types.SimpleNamespace(ranges=[distance] * 90, angle_min=-0.7, angle_increment=1.4 / 89)


def test_control_loop_goal_inputs(goal_run, tmp_path):
    robot = NumpyPolicy.from_npz(export(goal_run[0], "numpy", tmp_path / "policy.npz"))
    log = []
    goal = GoalInput()
    loop = ControlLoop(Controller(robot), MessageReader(scan=True), log=log.append, goal=goal)
    loop.on_observation(scan(1.0), 0.0)
    assert loop.tick(0.0) == STOP and loop.state == "no goal yet"
    goal.on_goal(2.0, 1.0, "odom")
    assert loop.tick(0.05) == STOP and loop.state == "no odometry yet"
    goal.on_pose(0.0, 0.0, 0.5, 0.05, "odom")
    twist = loop.tick(0.1)
    sectors = Controller(robot).scan_obs(*ros_node.scan_msg_to_arrays(*vars(scan(1.0)).values()))
    obs = goal_observation(sectors, (0.0, 0.0, 0.5), (2.0, 1.0), np.zeros(2), robot.command_scale)
    obs = np.tile(obs, 1 + robot.history)  # the first frame stands in for the earlier ones
    memory = Memory(robot.memory, robot.sensor.fov, robot.sensor.range_min, 8.0)
    obs = np.concatenate([obs, memory(sectors, (0.0, 0.0, 0.5))])
    np.testing.assert_allclose(loop.obs, obs)
    assert (obs[-BINS:] < 1.5).sum() == 2  # the wall 1 m ahead, in the two bins ahead
    assert twist == pytest.approx(tuple(robot(obs))) and loop.state == "policy"
    goal.on_pose(0.0, 0.0, 0.5 + math.pi, 0.12, "odom")  # turned round, still on the same scan
    loop.tick(0.15)  # the next observation carries the command just sent
    np.testing.assert_allclose(loop.obs[11:13], np.asarray(twist) / robot.command_scale, rtol=1e-6)
    np.testing.assert_allclose(loop.obs[13:-BINS], obs[: -13 - BINS])  # and the frames before it
    # The scan already remembered is read back from the new pose, not added again.
    want = memory(sectors, (0.0, 0.0, 0.5 + math.pi), remember=False)
    np.testing.assert_allclose(loop.obs[-BINS:], want)
    assert (want[[0, -1]] < 1.5).all() and (want[1:-1] == 1.5).all()  # the wall is behind
    assert loop.tick(0.5) == STOP and loop.state == "no sensor message for over 0.25 s"
    loop.on_observation(scan(3.0), 0.5)
    assert loop.tick(0.5) == STOP and loop.state == "no odometry for over 0.25 s"
    goal.on_pose(1.9, 0.9, 0.0, 0.5, "odom")
    assert loop.tick(0.55) == STOP and loop.state == "goal reached"
    goal.on_goal(-2.0, 0.0, "map")
    assert loop.tick(0.6) == STOP and loop.state == "goal in frame 'map', odometry in 'odom'"
    assert np.allclose(goal_features((0, 0, 0), (0, 2)), [2.0, 1.0, 0.0], atol=1e-6)


def test_ros_node_subscribes_to_goal_and_odometry(goal_run, tmp_path, monkeypatch):
    npz = str(export(goal_run[0], "numpy", tmp_path / "policy.npz"))
    ros = FakeRos().install(monkeypatch)
    ns = types.SimpleNamespace
    monkeypatch.setitem(sys.modules, "nav_msgs", ns())
    monkeypatch.setitem(sys.modules, "nav_msgs.msg", ns(Odometry=type("Odometry", (), {})))
    geometry = sys.modules["geometry_msgs.msg"]
    geometry.PoseStamped = type("PoseStamped", (), {})
    geometry.PointStamped = type("PointStamped", (), {})
    node = ros_node._make_node(ros_node.parse_args(["--policy", npz, "--scan"])[0])
    subs = {kind: (topic, callback) for kind, topic, callback in node.subscriptions_}
    assert subs["PoseStamped"][0] == "goal_pose" and subs["Odometry"][0] == "odom"
    (_, on_timer) = node.timers_[0]
    quaternion = ns(x=0.0, y=0.0, z=np.sin(0.25), w=np.cos(0.25))  # yaw 0.5 rad
    header = ns(frame_id="odom")
    ros.time = 1.0
    subs["LaserScan"][1](scan(3.0))
    subs["Odometry"][1](
        ns(header=header, pose=ns(pose=ns(position=ns(x=0.0, y=0.0), orientation=quaternion)))
    )
    on_timer()
    assert ros.published()[-1] == (0.0, 0.0)  # no goal yet
    subs["PoseStamped"][1](ns(header=header, pose=ns(position=ns(x=2.0, y=1.0))))
    on_timer()
    assert node.loop.goal.pose == pytest.approx((0.0, 0.0, 0.5))
    assert ros.published()[-1] != (0.0, 0.0) and node.loop.state == "policy"
