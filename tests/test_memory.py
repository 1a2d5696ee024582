"""The goal task's memory (`jaxnav.robot_side.memory`): its geometry by hand, the simulator and the
robot's numpy code reading the same memory, and what it is for: an obstacle that left the camera's
view is still seen beside the robot."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, start_in

import jaxnav
from jaxnav.core.sensors import SensorConfig
from jaxnav.io.layouts import Cylinder, RoomLayout
from jaxnav.robot_side.memory import Memory, MemorySpec, recall, sector_points


def test_recall_by_hand():
    """Bins of 90 degrees from straight behind, turning right: behind-right, right-front,
    left-front, behind-left; the nearest seen point in each, `reach` where none is that near."""
    points = np.array([[1.0, 0.0], [0.0, -0.5], [0.3, -0.3], [-2.0, 0.0], [0.0, 0.2]], np.float32)
    seen = np.array([True, True, True, True, False])  # (0, 0.2) left no point
    out = recall(points, seen, np.zeros(3, np.float32), 4, 1.5)
    # (1, 0) ahead: left-front (bearing 0 opens it); (0.3, -0.3) nearer than (0, -0.5) on the
    # right; (-2, 0) behind, beyond reach.
    np.testing.assert_allclose(out, [1.5, math.hypot(0.3, 0.3), 1.0, 1.5], rtol=1e-6)
    # Turned a quarter left, from (0.5, 0): (1, 0) is on its right now, (0, -0.5) and (0.3, -0.3)
    # behind on its left.
    pose = np.array([0.5, 0.0, math.pi / 2], np.float32)
    out = recall(points, seen, pose, 4, 1.5)
    np.testing.assert_allclose(out, [1.5, 0.5, 1.5, math.hypot(0.2, 0.3)], rtol=1e-6)


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
    with pytest.raises(ValueError, match="GoalConfig.memory_bins: needs a camera"):
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
