"""The goal task's memory (`jaxnav.robot_side.memory`): its geometry by hand, the simulator and the
robot's numpy code reading the same memory, and what it is for: an obstacle that left the camera's
view is still seen beside the robot."""

import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, start_in
from test_robot_side import write_policy_npz
from test_ros_node import odometry

import jaxnav
from jaxnav.core.sensors import SensorConfig
from jaxnav.io.layouts import Cylinder, RoomLayout
from jaxnav.robot_side.memory import Memory, MemorySpec, recall, sector_points
from jaxnav.robot_side.observation import Controller
from jaxnav.robot_side.policy import MEMORY_FORMAT, NumpyPolicy
from jaxnav.robot_side.ros_node import ControlLoop, GoalInput, MessageReader, scan_msg_to_arrays


def test_recall_by_hand():
    """Bins of 90 degrees from straight behind, turning right: behind-right, right-front,
    left-front, behind-left; the nearest seen point in each, `reach` where none is that near."""
    points = np.array([[1.0, 0.0], [0.0, -0.5], [0.3, -0.3], [-2.0, 0.0], [0.0, 0.2]], np.float32)
    seen = np.array([True, True, True, True, False])  # (0, 0.2) left no point
    out = recall(points, seen, np.zeros(3, np.float32), 4, 1.5)
    # (1, 0) ahead: left-front (bearing 0 opens it); (0.3, -0.3) nearer than (0, -0.5) on the
    # right; (-2, 0) behind, beyond reach.
    np.testing.assert_allclose(out, [1.5, math.hypot(0.3, 0.3), 1.0, 1.5], rtol=1e-6)
    # Turned a quarter left, from (0.5, -0.1): (1, 0) is on its right now, (0, -0.5) and
    # (0.3, -0.3) behind on its left, (-2, 0) ahead on the left, beyond reach.
    pose = np.array([0.5, -0.1, math.pi / 2], np.float32)
    out = recall(points, seen, pose, 4, 1.5)
    np.testing.assert_allclose(
        out, [1.5, math.hypot(0.5, 0.1), 1.5, math.hypot(0.2, 0.2)], rtol=1e-6
    )


@pytest.mark.parametrize("bins", [4, 7, 16])
def test_recall_bins_are_the_bearings(bins):
    """Each remembered point counts in the bin of its bearing from the heading, atan2's angle
    binned as the module docstring says, computed here independently in float64 for random
    points and poses (points within 1e-4 rad of a bin's edge left out); numpy (the robot) and
    jax.numpy (the simulator) alike."""
    rng = np.random.default_rng(bins)
    points = rng.uniform(-1.2, 1.2, (200, 2)).astype(np.float32)
    seen = rng.random(200) < 0.8
    for pose in rng.uniform([-0.3, -0.3, -4.0], [0.3, 0.3, 4.0], (20, 3)).astype(np.float32):
        d = points.astype(np.float64) - pose[:2]
        bearing = np.mod(np.arctan2(d[:, 1], d[:, 0]) - pose[2] + np.pi, 2 * np.pi)  # [0, 2 pi)
        where = bearing * bins / (2 * np.pi)
        clear = np.abs(where - np.round(where)) > 1e-4 * bins / (2 * np.pi)
        which = np.floor(where).astype(int) % bins
        distance = np.hypot(d[:, 0], d[:, 1])
        want = [min([1.5, *distance[(which == b) & seen & clear]]) for b in range(bins)]
        for xp in (np, jnp):
            got = recall(points[clear], seen[clear], pose, bins, np.float32(1.5), xp=xp)
            np.testing.assert_allclose(np.asarray(got), want, rtol=1e-6)


def test_sector_points_by_hand():
    """Two sectors of a 60 degree camera centred at -15 and +15 degrees; camera depth d along the
    axis puts the point d ahead and d tan(15 deg) to the side, from a camera 0.1 m behind."""
    sectors = np.array([1.0, 2.0], np.float32)
    points, seen = sector_points(sectors, np.zeros(3, np.float32), math.pi / 3, 0.6, 8.0, -0.1)
    t = math.tan(math.radians(15))
    np.testing.assert_allclose(points, [[0.9, -t], [1.9, 2 * t]], rtol=1e-6)
    assert seen.all()
    pose = np.array([1.0, 2.0, math.pi], np.float32)  # facing -x from (1, 2)
    points, _ = sector_points(sectors, pose, math.pi / 3, 0.6, 8.0, -0.1)
    np.testing.assert_allclose(points, [[0.1, 2 + t], [-0.9, 2 - 2 * t]], rtol=1e-6, atol=1e-6)
    # range_min (the camera could not read it) and range_max (nothing) leave no point.
    _, seen = sector_points(np.array([0.6, 8.0], np.float32), pose, math.pi / 3, 0.6, 8.0, 0.0)
    assert not seen.any()


def test_memory_spec_is_checked():
    with pytest.raises(ValueError, match="steps >= 1"):
        MemorySpec(bins=8, steps=0, reach=1.0)
    with pytest.raises(ValueError, match="reach > 0"):
        MemorySpec(bins=8, steps=4, reach=0.0)
    with pytest.raises(ValueError, match="GoalConfig.memory_bins: needs a camera .* 0"):
        jaxnav.make_env("goal", sensor=SensorConfig(model="lidar", fov=4.0), memory_bins=8)


# Facing east towards the goal; a pillar ahead on the right that the robot passes 0.12 m clear.
PASS = RoomLayout(
    name="pass",
    size=(6.0, 4.0),
    robot_pos=(-2.0, 0.0),
    robot_yaw=0.0,
    goal_pos=(2.5, 0.0),
    obstacles=(Cylinder(pos=(-0.5, -0.45), radius=0.15),),
)


def test_an_obstacle_that_left_the_view_stays_beside_the_robot():
    """Driving past the pillar: once it is out of the 60 degree view the sectors do not see it,
    but the memory's bins on the right read it as near as it is, and the robot side's `Memory`,
    fed the simulator's sectors and poses, reads what the simulator reads at every step."""
    env = jaxnav.make_env("goal", layouts=[PASS], randomize=EXACT, memory_bins=16)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    state = start_in(env, reset, 0)
    sensor, spec = env.sensor, env._memory
    robot = Memory(spec, sensor.fov, sensor.range_min, sensor.range_max)
    assert env.observation_size == 13 * 17 + 16
    for _ in range(31):
        sectors, pose = np.asarray(state.obs[:8]), np.asarray(state.data.qpos[:3])
        np.testing.assert_allclose(robot(sectors, pose), state.obs[-16:], atol=1e-5)
        state = step(state, jnp.int32(0))  # forward
    x = float(state.data.qpos[0])
    assert -0.55 < x < -0.4 and not bool(state.done)  # beside the pillar
    assert np.asarray(state.obs[:8]).min() > 2.0  # out of view: the sectors see the far wall
    memory = np.asarray(state.obs[-16:])
    right = memory[3:5].min()  # bearings -112.5 to -67.5 degrees
    surface = math.hypot(x + 0.5, 0.45) - 0.15  # the pillar's nearest point, m
    assert abs(right - surface) < 0.08, (right, surface)
    assert (memory[8:] == spec.reach).all()  # nothing on the left


def goal_memory_policy(path) -> NumpyPolicy:
    """A small goal policy with a memory of 8 bins (no stacked frames), in the export format."""
    size = 8 + 5 + 8  # sectors, the goal and the last command, the memory
    rng = np.random.default_rng(0)
    return NumpyPolicy.from_npz(
        write_policy_npz(
            path,
            W0=rng.normal(size=(size, 16)).astype(np.float32),
            obs_mean=np.zeros(size, np.float32),
            obs_var=np.ones(size, np.float32),
            obs_std=np.ones(size, np.float32),
            extra_observations=np.int32(5),
            command_scale=np.array([0.5, 1.5], np.float32),
            success_radius=np.float64(0.3),
            control_period=np.float64(0.1),
            memory_bins=np.int32(8),
            memory_steps=np.int32(20),
            memory_reach=np.float64(1.5),
            memory_forward=np.float64(-0.05),
            format_version=np.int32(MEMORY_FORMAT),
        )
    )


def scan(distance: float):
    return types.SimpleNamespace(ranges=[distance] * 90, angle_min=-0.7, angle_increment=1.4 / 89)


def test_the_control_loop_remembers_each_frame_once_and_forgets_when_it_must(tmp_path):
    """The robot's loop: a sensor message is remembered once (a later tick on the same message
    reads it back from the new pose), a short stop keeps the memory, a stop longer than the
    memory's 2 s, a new goal or an odometry jump empties it; the observation is the robot
    side's `Memory` fed the same frames."""
    robot = goal_memory_policy(tmp_path / "policy.npz")
    assert robot.observation_size == 21 and robot.memory.bins == 8
    goal = GoalInput()
    loop = ControlLoop(Controller(robot), MessageReader(scan=True), log=lambda _: None, goal=goal)
    goal.on_goal(5.0, 0.0, "odom")
    near = Controller(robot).scan_obs(*scan_msg_to_arrays(*vars(scan(1.0)).values()))
    memory = Memory(robot.memory, robot.sensor.fov, robot.sensor.range_min, 8.0)

    def tick(now, yaw=0.0, message=None):
        goal.on_pose(0.0, 0.0, yaw, now, "odom")
        if message is not None:
            loop.on_observation(message, now)
        loop.tick(now)
        return None if loop.obs is None else loop.obs[-8:]

    got = tick(0.0, message=scan(1.0))  # a wall 1 m ahead: the two bins ahead
    np.testing.assert_allclose(got, memory(near, (0, 0, 0)))
    assert (got[3:5] < 1.5).all() and (np.delete(got, [3, 4]) == 1.5).all()
    got = tick(0.05, yaw=math.pi)  # turned round on the same message: the wall behind
    np.testing.assert_allclose(got, memory(near, (0, 0, math.pi), remember=False))
    assert (got[[0, -1]] < 1.5).all() and (got[1:-1] == 1.5).all()
    far = tick(0.1, yaw=math.pi, message=scan(3.0))  # a new frame sees nothing near...
    assert (far[[0, -1]] < 1.5).all()  # ...and the wall behind is remembered
    assert tick(0.5, yaw=math.pi) is None and loop.state.startswith("no sensor message")
    assert (tick(0.6, yaw=math.pi, message=scan(3.0))[[0, -1]] < 1.5).all()  # a short stop
    assert tick(1.0, yaw=math.pi) is None
    assert (tick(3.5, yaw=math.pi, message=scan(3.0)) == 1.5).all()  # 2.5 s stopped: forgotten
    assert (tick(3.6, message=scan(1.0))[3:5] < 1.5).all()
    assert (tick(3.62, yaw=math.pi, message=scan(3.0))[[0, -1]] < 1.5).all()  # behind now
    goal.on_goal(-5.0, 0.0, "odom")  # a new goal: a new episode
    assert (tick(3.65, yaw=math.pi) == 1.5).all()  # the wall, seen before it, is forgotten
    assert (tick(3.7, message=scan(1.0))[3:5] < 1.5).all()
    goal.on_odom_msg(odometry(0.0, 0.0, 0.0), 3.72)
    goal.on_odom_msg(odometry(0.0, 0.0, math.pi / 3), 3.74)  # 60 deg in 0.02 s: a jump
    for i in range(5):  # waited out
        goal.on_odom_msg(odometry(0.0, 0.0, math.pi / 3), 3.76 + 0.02 * i)
    assert goal.jump is None and goal.jumps == 1
    loop.on_observation(scan(3.0), 3.9)
    loop.tick(3.9)  # the wall 1 m ahead of the pose before the jump is forgotten
    assert (loop.obs[-8:] == 1.5).all()


def test_odometry_poses_between_messages_are_interpolated():
    """`GoalInput.pose_at`: between two odometry poses, the straight mix of their positions and
    the shorter turn between their headings (across +-pi too); the oldest kept before them, the
    newest after; a pose of the same stamp replaces the last; nothing across an odometry jump."""
    goal = GoalInput()
    assert goal.pose_at(1.0) is None
    goal.on_odom_msg(odometry(0.0, 0.0, math.pi - 0.1), 1.00)
    goal.on_odom_msg(odometry(0.01, 0.02, -math.pi + 0.1), 1.02)  # 0.2 rad left, past +pi
    x, y, yaw = goal.pose_at(1.015)
    assert (x, y) == pytest.approx((0.0075, 0.015)) and yaw == pytest.approx(math.pi + 0.05)
    assert goal.pose_at(0.5) == pytest.approx((0.0, 0.0, math.pi - 0.1))
    assert goal.pose_at(2.0) == goal.pose
    goal.on_pose(0.02, 0.04, -math.pi + 0.1, 1.02, "odom")  # the same stamp again: it stands
    assert goal.pose_at(1.015)[:2] == pytest.approx((0.015, 0.03))  # for it; the track stays
    goal.on_odom_msg(odometry(3.0, 0.0, 0.0), 1.04)  # 3 m in 0.02 s: a jump
    assert goal.jumps == 1 and goal.pose_at(1.01) == goal.pose


def test_the_control_loop_places_a_frame_at_the_pose_it_was_taken_from(tmp_path):
    """A frame that arrives while the robot drives is remembered at the odometry pose of its
    time (with `header_stamps`, its header stamp), not at the pose of the tick that reads it: a
    wall 1 m ahead when the frame was taken reads 6-7 cm nearer 0.15 s later."""
    robot = goal_memory_policy(tmp_path / "policy.npz")
    goal = GoalInput()
    loop = ControlLoop(
        Controller(robot), MessageReader(scan=True), log=lambda _: None, goal=goal,
        header_stamps=True,
    )  # fmt: skip
    goal.on_goal(5.0, 0.0, "odom")
    for i in range(11):  # 0.5 m/s ahead, turning left at 1.5 rad/s, odometry at 50 Hz
        goal.on_odom_msg(odometry(0.01 * i, 0.0, 0.03 * i), 0.02 * i)
    message = scan(1.0)
    message.header = types.SimpleNamespace(stamp=types.SimpleNamespace(sec=0, nanosec=50_000_000))
    loop.on_observation(message, 0.2)  # taken at 0.05 s, read at 0.2 s
    loop.tick(0.2)
    near = Controller(robot).scan_obs(*scan_msg_to_arrays(*vars(scan(1.0)).values()))
    memory = Memory(robot.memory, robot.sensor.fov, robot.sensor.range_min, 8.0)
    expected = memory(near, goal.pose, taken_at=(0.025, 0.0, 0.075))
    np.testing.assert_allclose(loop.obs[-8:], expected, rtol=1e-5)
    memory.reset()
    at_tick = memory(near, goal.pose)  # what placing it at the tick's pose would read
    ahead = [3, 4]  # the bins of the wall; the others read the reach either way
    assert (at_tick - expected)[ahead].min() > 0.06, (at_tick, expected)


def test_a_policy_file_with_a_bad_memory_is_refused_in_one_line(tmp_path):
    """Memory entries without the goal inputs, a count that would allocate without bound, and
    a missing entry are each one line naming the file and the entry."""
    path = tmp_path / "policy.npz"
    good = dict(np.load(write_policy_npz(path)))  # the paper's policy, no memory
    memory = dict(memory_bins=np.int32(8), memory_steps=np.int32(20))
    memory.update(memory_reach=np.float64(1.5), memory_forward=np.float64(0.0))
    sized = {k: np.ones(16, np.float32) for k in ("obs_mean", "obs_var", "obs_std")}
    sized["W0"] = np.ones((16, 16), np.float32)  # 8 sectors and 8 bins
    for changes, message in (
        ({**memory, **sized}, "memory_bins without the goal inputs"),
        ({**memory, "memory_steps": np.int32(10**6)}, "memory_steps: must be in \\[0, 600\\]"),
        ({"memory_bins": np.int32(8)}, "memory_bins without memory_steps, memory_reach, memory_"),
    ):
        with pytest.raises(ValueError, match=f"^policy.npz: {message}") as err:
            NumpyPolicy.from_arrays({**good, **changes}, "policy.npz")
        assert "\n" not in str(err.value)
